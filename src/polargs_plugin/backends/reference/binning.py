"""Tile binning: which Gaussians can touch which screen tile, front to back, with one sort.

No gradients flow here; the output is integer index lists shared by every compositing path. On
CPU the lists are filled by a compiled counting pass over the Gaussians in depth order
(:func:`counted_tile_lists`), which gives the same lists as the sort
(:func:`sorted_tile_lists`, any device) without the expansion, the sort and the index
arithmetic over all pairs.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

__all__ = ["DEFAULT_TILE_SIZE", "TileBins", "bin_gaussians", "counted_tile_lists", "sorted_tile_lists", "tile_centres"]

DEFAULT_TILE_SIZE = 16  # pixels, vanilla 3DGS's


class TileBins(NamedTuple):
    """Per-tile Gaussian lists sorted by depth.

    Attributes:
        gauss_ids: (M,) int64 Gaussian index of each (tile, Gaussian) pair, grouped by tile in
            row-major tile order and sorted front to back (mean camera z) within a tile.
        tile_offsets: (T + 1,) int64; tile t owns gauss_ids[tile_offsets[t]:tile_offsets[t + 1]].
        tiles_x, tiles_y: tile grid size, T = tiles_x * tiles_y.
        tile_size: tile edge in pixels.
        visible: (N,) bool, the Gaussian touches at least one pixel centre of the image.
    """

    gauss_ids: Tensor
    tile_offsets: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int
    visible: Tensor


@torch.no_grad()
def bin_gaussians(
    means2d: Tensor, extents: Tensor, depths: Tensor, width: int, height: int, tile_size: int = DEFAULT_TILE_SIZE
) -> TileBins:
    """Per screen tile, the Gaussians that can touch it, front to back: the (tile, Gaussian) pairs
    in the order of the key tile_id * N + depth rank.

    A Gaussian is assigned to every tile holding a pixel centre (u + 0.5, v + 0.5) inside the
    axis-aligned box of half-widths ``extents`` around its mean, so every pixel it can affect
    (alpha >= 1/255) is covered.

    Args:
        means2d: (N, 2) projected means in pixels.
        extents: (N, 2) float half-widths (x, y) in pixels, 0 = culled.
        depths: (N,) camera z used for the front-to-back order.
        width, height: image size.
        tile_size: tile edge in pixels.

    Returns:
        :class:`TileBins`.
    """
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    r = extents.to(means2d.dtype)
    # Pixel index i has centre i + 0.5; the covered centres satisfy |i + 0.5 - m| <= r.
    lo = torch.ceil(means2d - r - 0.5).clamp_min(0)
    hi = torch.floor(means2d + r - 0.5)
    hi = torch.minimum(hi, torch.tensor([width - 1, height - 1], dtype=hi.dtype, device=device))
    visible = (r > 0).all(dim=-1) & (lo <= hi).all(dim=-1)
    lo_t = torch.div(lo.clamp_max(max(width, height)).long(), tile_size, rounding_mode="floor")
    hi_t = torch.div(hi.clamp_min(0).long(), tile_size, rounding_mode="floor")
    depth_order = torch.argsort(depths)
    tile_lists = counted_tile_lists if device.type == "cpu" else sorted_tile_lists
    gauss_ids, tile_offsets = tile_lists(depth_order, lo_t, hi_t, visible, tiles_x, tiles_y)
    return TileBins(gauss_ids, tile_offsets, tiles_x, tiles_y, tile_size, visible)


def tile_centres(bins: TileBins, dtype: torch.dtype) -> Tensor:
    """(T, 2) pixel coordinates (x, y) of each tile's centre in ``dtype`` (pixel centres at
    +0.5, so a one-pixel tile's is its pixel's): where ``order="ray"`` follows the rays."""
    tile = torch.arange(bins.tile_offsets.shape[0] - 1, device=bins.tile_offsets.device)
    half = bins.tile_size / 2
    return torch.stack([((tile % bins.tiles_x) * bins.tile_size).to(dtype) + half,
                        ((tile // bins.tiles_x) * bins.tile_size).to(dtype) + half], dim=-1)


def sorted_tile_lists(
    depth_order: Tensor, lo_t: Tensor, hi_t: Tensor, visible: Tensor, tiles_x: int, tiles_y: int
) -> tuple[Tensor, Tensor]:
    """(gauss_ids, tile_offsets) of :class:`TileBins` by sorting: every (tile, Gaussian) pair of
    the visible Gaussians' tile boxes, sorted by the key tile_id * N + depth rank (any device).

    Args:
        depth_order: (N,) int64 Gaussian indices front to back.
        lo_t, hi_t: (N, 2) int64 first and last tile (x, y) of each Gaussian's box.
        visible: (N,) bool, the Gaussians that get pairs.
        tiles_x, tiles_y: tile grid size.
    """
    device = depth_order.device
    n = depth_order.shape[0]
    span = (hi_t - lo_t + 1).clamp_min(0)
    counts = torch.where(visible, span[:, 0] * span[:, 1], torch.zeros_like(span[:, 0]))
    gid = torch.repeat_interleave(torch.arange(n, device=device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.shape[0], device=device) - starts[gid]
    span_x = span[gid, 0]
    tile_x = lo_t[gid, 0] + local % span_x
    tile_y = lo_t[gid, 1] + torch.div(local, span_x, rounding_mode="floor")
    tile_id = tile_y * tiles_x + tile_x

    depth_rank = torch.empty(n, dtype=torch.int64, device=device)
    depth_rank[depth_order] = torch.arange(n, device=device)
    order = torch.argsort(tile_id * n + depth_rank[gid])
    gauss_ids = gid[order]
    per_tile = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    tile_offsets = torch.cat([per_tile.new_zeros(1), torch.cumsum(per_tile, 0)])
    return gauss_ids, tile_offsets


def counted_tile_lists(
    depth_order: Tensor, lo_t: Tensor, hi_t: Tensor, visible: Tensor, tiles_x: int, tiles_y: int
) -> tuple[Tensor, Tensor]:
    """(gauss_ids, tile_offsets) of :class:`TileBins` by counting (CPU tensors, compiled):
    visible Gaussians, taken in ``depth_order``, are appended to every tile of their tile box
    [lo_t, hi_t]; the same lists as :func:`sorted_tile_lists` (same arguments)."""
    arrays = (t.contiguous().numpy() for t in (depth_order, lo_t, hi_t, visible))
    gauss_ids, offsets = _tile_lists_kernel(*arrays, tiles_x, tiles_x * tiles_y)
    return torch.from_numpy(gauss_ids), torch.from_numpy(offsets)


@numba.njit(cache=True)
def _tile_lists_kernel(depth_order, lo_t, hi_t, visible, tiles_x, num_tiles):
    n = depth_order.shape[0]
    offsets = np.zeros(num_tiles + 1, np.int64)
    for g in range(n):
        if visible[g]:
            for ty in range(lo_t[g, 1], hi_t[g, 1] + 1):
                for tx in range(lo_t[g, 0], hi_t[g, 0] + 1):
                    offsets[ty * tiles_x + tx + 1] += 1
    for t in range(num_tiles):
        offsets[t + 1] += offsets[t]
    fill = offsets[:-1].copy()
    gauss_ids = np.empty(offsets[num_tiles], np.int64)
    for k in range(n):
        g = depth_order[k]
        if visible[g]:
            for ty in range(lo_t[g, 1], hi_t[g, 1] + 1):
                for tx in range(lo_t[g, 0], hi_t[g, 0] + 1):
                    t = ty * tiles_x + tx
                    gauss_ids[fill[t]] = g
                    fill[t] += 1
    return gauss_ids, offsets
