"""Exact front-to-back alpha compositing in pure torch (the reference path, CPU and CUDA).

Compositing rule, identical in every path of this package. For one pixel, walk its tile's
Gaussians front to back with T = 1:

    alpha = min(0.99, o * exp(-0.5 d^T conic d))      d = pixel centre - mean2d
    if alpha < 1/255: skip this Gaussian
    if T * (1 - alpha) < 1e-4: stop (this Gaussian and all later ones are left out)
    weight = alpha * T;  T = T * (1 - alpha)

The median depth is the depth of the Gaussian at which T first drops below 0.5 (0 if it never
does). Since T only decreases, "contributes" is the same as "alpha >= 1/255 and the product of
(1 - alpha) over the contributing Gaussians up to and including this one is >= 1e-4", which is
what the vectorised two passes below evaluate:

1. a no-grad pass finds the contributing (pixel, Gaussian) pairs, each pixel testing its tile
   list a slab at a time and dropping out once T < 1e-4 (no padding to the longest list);
2. a differentiable sparse pass over those pairs recomputes alpha, the exclusive transmittance
   as a segmented cumulative sum of log(1 - alpha) (float64, so long sums stay exact), and
   index-adds the weighted features into the pixels.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .binning import TileBins
from .projection import ALPHA_MIN, Projection

__all__ = [
    "ALPHA_MAX",
    "T_MIN",
    "Composite",
    "gaussian_alpha",
    "pixel_depth",
    "contributing_pairs",
    "exclusive_transmittance",
    "composite_torch",
]

ALPHA_MAX = 0.99
T_MIN = 1e-4
_LOG_T_MIN = math.log(T_MIN)


class Composite(NamedTuple):
    """Raw compositing sums of one image (channel-first).

    Attributes:
        color: (3, H, W) sum of weight * colour (no background).
        depth: (1, H, W) sum of weight * per-pixel depth (not normalised).
        normal: (3, H, W) sum of weight * normal.
        alpha: (1, H, W) sum of weights = 1 - final transmittance.
        median_depth: (1, H, W) depth of the Gaussian where T first drops below 0.5, else 0.
        distance: (1, H, W) sum of weight * plane distance, when per-Gaussian distances were given.
    """

    color: Tensor
    depth: Tensor
    normal: Tensor
    alpha: Tensor
    median_depth: Tensor
    distance: Tensor | None = None


def gaussian_alpha(means2d: Tensor, conics: Tensor, opacities: Tensor, px: Tensor, py: Tensor) -> Tensor:
    """Clamped alpha min(0.99, o exp(-sigma)) of Gaussians at pixel centres (broadcasting)."""
    dx = px - means2d[..., 0]
    dy = py - means2d[..., 1]
    sigma = 0.5 * (conics[..., 0] * dx * dx + conics[..., 2] * dy * dy) + conics[..., 1] * dx * dy
    return torch.clamp(opacities * torch.exp(-sigma), max=ALPHA_MAX)


def pixel_depth(ray_coeffs: Tensor, ray_offsets: Tensor, depth_bounds: Tensor, px: Tensor, py: Tensor) -> Tensor:
    """Camera z of the maximum-density point along the ray through (px, py), clamped.

    Args:
        ray_coeffs: (..., 3, 3) Q of :class:`Projection`.
        ray_offsets: (..., 3) b of :class:`Projection`.
        depth_bounds: (..., 2) clamp interval.
        px, py: (...) pixel coordinates (centres at +0.5).

    Returns:
        (...) depth.
    """
    a = ray_coeffs[..., 0] * px[..., None] + ray_coeffs[..., 1] * py[..., None] + ray_coeffs[..., 2]
    t = (a * ray_offsets).sum(-1) / (a * a).sum(-1)
    return torch.minimum(torch.maximum(t, depth_bounds[..., 0]), depth_bounds[..., 1])


@torch.no_grad()
def contributing_pairs(
    proj: Projection, opacities: Tensor, bins: TileBins, width: int, height: int,
    chunk_elems: int = 1 << 21, slab: int = 32,
) -> tuple[Tensor, Tensor]:
    """(pixel index, Gaussian index) of every contributing pair, grouped by pixel, front to back.

    Pixels walk their tile's list ``slab`` entries at a time, carrying log T; a pixel leaves the
    walk once T < 1e-4 or its list ends, so the work follows the pairs actually composited
    rather than the longest list.
    """
    device = proj.means2d.device
    dtype = proj.means2d.dtype
    ts = bins.tile_size
    counts = bins.tile_offsets[1:] - bins.tile_offsets[:-1]
    tiles = torch.nonzero(counts > 0)[:, 0]
    local = torch.arange(ts * ts, device=device)
    tiles_per_chunk = max(1, chunk_elems // (slab * ts * ts))
    slot_range = torch.arange(slab, device=device)
    pix_parts, slot_parts, gauss_parts = [], [], []
    for first in range(0, tiles.shape[0], tiles_per_chunk):
        chunk = tiles[first : first + tiles_per_chunk]
        u = ((chunk % bins.tiles_x)[:, None] * ts + local % ts).reshape(-1)
        v = ((chunk // bins.tiles_x)[:, None] * ts + local // ts).reshape(-1)
        tile = chunk[:, None].expand(-1, ts * ts).reshape(-1)
        inside = (u < width) & (v < height)
        u, v, tile = u[inside], v[inside], tile[inside]
        px, py = (u + 0.5).to(dtype)[:, None], (v + 0.5).to(dtype)[:, None]
        list_start, list_len = bins.tile_offsets[tile], counts[tile]
        log_t = torch.zeros(u.shape[0], dtype=dtype, device=device)
        active = torch.arange(u.shape[0], device=device)
        offset = 0
        while active.numel() > 0:
            slots = offset + slot_range  # (S,)
            in_list = slots < list_len[active, None]  # (A, S)
            pair = (list_start[active, None] + slots).clamp_max(bins.gauss_ids.shape[0] - 1)
            g = torch.where(in_list, bins.gauss_ids[pair], torch.zeros_like(pair))
            alpha = gaussian_alpha(proj.means2d[g], proj.conics[g], opacities[g], px[active], py[active])
            valid = (alpha >= ALPHA_MIN) & in_list
            cum = log_t[active, None] + torch.cumsum(
                torch.where(valid, torch.log1p(-alpha), torch.zeros_like(alpha)), dim=-1
            )
            rows, cols = torch.nonzero(valid & (cum >= _LOG_T_MIN), as_tuple=True)
            pix_parts.append(v[active[rows]] * width + u[active[rows]])
            slot_parts.append(slots[cols])
            gauss_parts.append(g[rows, cols])
            log_t[active] = cum[:, -1]
            offset += slab
            active = active[(cum[:, -1] >= _LOG_T_MIN) & (list_len[active] > offset)]
    if not pix_parts:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return empty, empty
    pix, slot, gauss = torch.cat(pix_parts), torch.cat(slot_parts), torch.cat(gauss_parts)
    order = torch.argsort(pix * (int(counts.max()) + 1) + slot)
    return pix[order], gauss[order]


def exclusive_transmittance(alpha: Tensor, pix: Tensor) -> Tensor:
    """Transmittance in front of each pair (float64): the product of (1 - alpha) over the pairs
    before it in its pixel's group (pairs grouped by pixel, front to back, as
    :func:`contributing_pairs` returns them)."""
    log_1m = torch.log1p(-alpha.double())
    # Segmented exclusive cumulative sum: global cumsum minus its value at each pixel's first pair.
    excl = torch.cumsum(log_1m, 0) - log_1m
    first = torch.ones_like(pix, dtype=torch.bool)
    first[1:] = pix[1:] != pix[:-1]
    segment = torch.cumsum(first.long(), 0) - 1
    excl = excl - excl[first][segment]
    return torch.exp(excl)


def composite_torch(
    proj: Projection,
    opacities: Tensor,
    colors: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    distances: Tensor | None = None,
    chunk_elems: int = 1 << 21,
    slab: int = 32,
) -> Composite:
    """Composite projected Gaussians into one image, exactly and differentiably.

    Args:
        proj: :class:`Projection` of the N Gaussians.
        opacities: (N,) opacities in (0, 1).
        colors: (N, 3) per-Gaussian colour for this view.
        bins: :class:`TileBins` from the same projection.
        width, height: image size.
        distances: optional (N,) per-Gaussian plane distances, composited like a colour channel.
        chunk_elems: bound on the elements of one block of the no-grad pass (pixels x slab).
        slab: list entries a pixel tests per step of the no-grad pass.

    Returns:
        :class:`Composite` (gradients flow to every float field of ``proj``, opacities, colors).
    """
    pix, g = contributing_pairs(proj, opacities, bins, width, height, chunk_elems, slab)
    dtype = proj.means2d.dtype
    num_pix = width * height
    px = (pix % width).to(dtype) + 0.5
    py = torch.div(pix, width, rounding_mode="floor").to(dtype) + 0.5

    alpha = gaussian_alpha(proj.means2d[g], proj.conics[g], opacities[g], px, py)
    trans = exclusive_transmittance(alpha, pix)
    weight = (alpha * trans).to(dtype)
    depth = pixel_depth(proj.ray_coeffs[g], proj.ray_offsets[g], proj.depth_bounds[g], px, py)

    columns = [colors[g], depth[:, None], proj.normals[g], torch.ones_like(depth)[:, None]]
    if distances is not None:
        columns.append(distances[g][:, None].to(dtype))
    values = torch.cat(columns, dim=-1)
    sums = torch.zeros(num_pix, values.shape[1], dtype=dtype, device=pix.device).index_add(
        0, pix, weight[:, None] * values
    )

    with torch.no_grad():
        crossing = (trans >= 0.5) & (trans * (1.0 - alpha.double()) < 0.5)
    median = torch.zeros(num_pix, dtype=dtype, device=pix.device).index_add(
        0, pix[crossing], depth[crossing]
    )
    image = sums.T.reshape(values.shape[1], height, width)
    return Composite(
        color=image[0:3],
        depth=image[3:4],
        normal=image[4:7],
        alpha=image[7:8],
        median_depth=median.reshape(1, height, width),
        distance=image[8:9] if distances is not None else None,
    )
