"""Tile binning: which Gaussians can touch which screen tile, front to back, with one sort.

No gradients flow here; the output is integer index lists shared by every compositing path. On
CPU (with numba) the lists are filled by a counting pass over the Gaussians in depth order
(:func:`~.composite_numba.tile_lists`), which gives the same lists as the sort without the
expansion, the sort and the index arithmetic over all pairs.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["TileBins", "bin_gaussians"]


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
    means2d: Tensor, extents: Tensor, depths: Tensor, width: int, height: int, tile_size: int = 16
) -> TileBins:
    """Expand Gaussians into (tile, Gaussian) pairs and sort them by the key tile_id * N + depth rank.

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
    n = means2d.shape[0]
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
    span = (hi_t - lo_t + 1).clamp_min(0)
    counts = torch.where(visible, span[:, 0] * span[:, 1], torch.zeros_like(span[:, 0]))
    depth_order = torch.argsort(depths)

    if device.type == "cpu":
        try:
            from .composite_numba import tile_lists
        except ImportError:  # numba missing: the torch expansion and sort below
            pass
        else:
            gauss_ids, tile_offsets = tile_lists(depth_order, lo_t, hi_t, visible, tiles_x, tiles_y)
            return TileBins(gauss_ids, tile_offsets, tiles_x, tiles_y, tile_size, visible)

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
    return TileBins(gauss_ids, tile_offsets, tiles_x, tiles_y, tile_size, visible)
