"""Compiled CPU compositing (Numba) with a hand-written backward, same rule as :mod:`.composite_torch`.

The forward walks each pixel's tile list front to back with per-pixel early termination, threads
over tiles (``prange``). The backward walks the same list back to front from the final
transmittance (T_i = T_{i+1} / (1 - alpha_i), alpha <= 0.99 keeps this stable) and writes each
(tile, Gaussian) pair's gradient into its own row, so threads never share a row; torch then
sums the rows per Gaussian with ``index_add``. Gradients match the torch path (tests/).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numba
import numpy as np
import torch
from torch import Tensor

from .binning import TileBins
from .composite_torch import ALPHA_MAX, T_MIN, Composite
from .projection import ALPHA_MIN, Projection

__all__ = ["composite_numba"]

# Columns of the per-pair gradient rows: means2d 2, conics 3, opacity 1, colour 3, normal 3,
# ray_coeffs 9, ray_offsets 3, depth_bounds 2.
_GRAD_COLS = 26
_TILES_PER_CHUNK = 4


@numba.njit(inline="always")
def _alpha(means2d, conics, opacities, g, px, py):
    dx = px - means2d[g, 0]
    dy = py - means2d[g, 1]
    sigma = 0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) + conics[g, 1] * dx * dy
    raw = opacities[g] * np.exp(-sigma)
    return min(raw, ALPHA_MAX), raw, dx, dy


@numba.njit(inline="always")
def _ray(ray_coeffs, ray_offsets, g, px, py):
    a0 = ray_coeffs[g, 0] * px + ray_coeffs[g, 1] * py + ray_coeffs[g, 2]
    a1 = ray_coeffs[g, 3] * px + ray_coeffs[g, 4] * py + ray_coeffs[g, 5]
    a2 = ray_coeffs[g, 6] * px + ray_coeffs[g, 7] * py + ray_coeffs[g, 8]
    aa = a0 * a0 + a1 * a1 + a2 * a2
    t = (a0 * ray_offsets[g, 0] + a1 * ray_offsets[g, 1] + a2 * ray_offsets[g, 2]) / aa
    return t, a0, a1, a2, aa


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _forward_kernel(
    means2d, conics, opacities, feats, ray_coeffs, ray_offsets, depth_bounds,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height,
    out, trans_final, median, last_slot, median_slot,
):
    num_tiles = tile_offsets.shape[0] - 1
    for tile in numba.prange(num_tiles):
        start, end = tile_offsets[tile], tile_offsets[tile + 1]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        for v in range(v0, min(v0 + tile_size, height)):
            py = v + 0.5
            for u in range(u0, min(u0 + tile_size, width)):
                px = u + 0.5
                trans = 1.0
                c0 = c1 = c2 = dsum = n0 = n1 = n2 = 0.0
                med_z = 0.0
                med_j = -1
                last = start
                for j in range(start, end):
                    g = gauss_ids[j]
                    alpha, raw, dx, dy = _alpha(means2d, conics, opacities, g, px, py)
                    if alpha < ALPHA_MIN:
                        continue
                    next_t = trans * (1.0 - alpha)
                    if next_t < T_MIN:
                        break
                    t, a0, a1, a2, aa = _ray(ray_coeffs, ray_offsets, g, px, py)
                    z = min(max(t, depth_bounds[g, 0]), depth_bounds[g, 1])
                    w = alpha * trans
                    c0 += w * feats[g, 0]
                    c1 += w * feats[g, 1]
                    c2 += w * feats[g, 2]
                    n0 += w * feats[g, 3]
                    n1 += w * feats[g, 4]
                    n2 += w * feats[g, 5]
                    dsum += w * z
                    if trans >= 0.5 and next_t < 0.5:
                        med_z = z
                        med_j = j
                    trans = next_t
                    last = j + 1
                out[0, v, u] = c0
                out[1, v, u] = c1
                out[2, v, u] = c2
                out[3, v, u] = dsum
                out[4, v, u] = n0
                out[5, v, u] = n1
                out[6, v, u] = n2
                out[7, v, u] = 1.0 - trans
                trans_final[v, u] = trans
                median[v, u] = med_z
                last_slot[v, u] = last
                median_slot[v, u] = med_j


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _backward_kernel(
    means2d, conics, opacities, feats, ray_coeffs, ray_offsets, depth_bounds,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height,
    trans_final, last_slot, median_slot, grad_out, grad_median, pair_grads,
):
    num_tiles = tile_offsets.shape[0] - 1
    for tile in numba.prange(num_tiles):
        start = tile_offsets[tile]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        for v in range(v0, min(v0 + tile_size, height)):
            py = v + 0.5
            for u in range(u0, min(u0 + tile_size, width)):
                px = u + 0.5
                gc0, gc1, gc2 = grad_out[0, v, u], grad_out[1, v, u], grad_out[2, v, u]
                gd = grad_out[3, v, u]
                gn0, gn1, gn2 = grad_out[4, v, u], grad_out[5, v, u], grad_out[6, v, u]
                trans = trans_final[v, u]
                # alpha_out = 1 - T_final, so the pixel's "rest" term starts at -g_alpha * T_final.
                rest = -grad_out[7, v, u] * trans
                med_j = median_slot[v, u]
                for j in range(last_slot[v, u] - 1, start - 1, -1):
                    g = gauss_ids[j]
                    alpha, raw, dx, dy = _alpha(means2d, conics, opacities, g, px, py)
                    if alpha < ALPHA_MIN:
                        continue
                    trans = trans / (1.0 - alpha)
                    t, a0, a1, a2, aa = _ray(ray_coeffs, ray_offsets, g, px, py)
                    lo, hi = depth_bounds[g, 0], depth_bounds[g, 1]
                    z = min(max(t, lo), hi)
                    fg = (
                        feats[g, 0] * gc0 + feats[g, 1] * gc1 + feats[g, 2] * gc2
                        + feats[g, 3] * gn0 + feats[g, 4] * gn1 + feats[g, 5] * gn2 + z * gd
                    )
                    w = alpha * trans
                    d_alpha = trans * fg - rest / (1.0 - alpha)
                    rest += w * fg

                    row = pair_grads[j]
                    row[6] += w * gc0
                    row[7] += w * gc1
                    row[8] += w * gc2
                    row[9] += w * gn0
                    row[10] += w * gn1
                    row[11] += w * gn2
                    dz = w * gd
                    if j == med_j:
                        dz += grad_median[v, u]
                    if t < lo:
                        row[24] += dz
                    elif t > hi:
                        row[25] += dz
                    else:
                        b0, b1, b2 = ray_offsets[g, 0], ray_offsets[g, 1], ray_offsets[g, 2]
                        s = dz / aa
                        da0 = s * (b0 - 2.0 * t * a0)
                        da1 = s * (b1 - 2.0 * t * a1)
                        da2 = s * (b2 - 2.0 * t * a2)
                        row[12] += da0 * px
                        row[13] += da0 * py
                        row[14] += da0
                        row[15] += da1 * px
                        row[16] += da1 * py
                        row[17] += da1
                        row[18] += da2 * px
                        row[19] += da2 * py
                        row[20] += da2
                        row[21] += s * a0
                        row[22] += s * a1
                        row[23] += s * a2
                    if raw <= ALPHA_MAX:
                        row[5] += d_alpha * (alpha / opacities[g])
                        d_sigma = -d_alpha * alpha
                        row[2] += d_sigma * 0.5 * dx * dx
                        row[3] += d_sigma * dx * dy
                        row[4] += d_sigma * 0.5 * dy * dy
                        row[0] -= d_sigma * (conics[g, 0] * dx + conics[g, 1] * dy)
                        row[1] -= d_sigma * (conics[g, 1] * dx + conics[g, 2] * dy)


@contextlib.contextmanager
def _scheduling() -> Iterator[None]:
    """Threads as many as torch uses (one per pytest-xdist worker, say); tiles handed out a
    few at a time, since their lists differ a lot in length."""
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    previous = numba.set_parallel_chunksize(_TILES_PER_CHUNK)
    try:
        yield
    finally:
        numba.set_parallel_chunksize(previous)


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _CompositeFunction(torch.autograd.Function):
    """Inputs: means2d, conics, opacities, feats (colour | normal), ray coefficients (N, 9),
    ray offsets, depth bounds, then the non-differentiable bins, width, height.
    Outputs: (8, H, W) sums (colour 3, depth 1, normal 3, alpha 1) and (1, H, W) median depth."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, ray_coeffs, ray_offsets, depth_bounds, bins, width, height):
        dtype = means2d.dtype
        inputs = (means2d, conics, opacities, feats, ray_coeffs, ray_offsets, depth_bounds)
        arrays = [_np(x.to(dtype)) for x in inputs]
        grid = (_np(bins.gauss_ids), _np(bins.tile_offsets), bins.tiles_x, bins.tile_size, width, height)
        np_dtype = arrays[0].dtype
        out = np.zeros((8, height, width), np_dtype)
        median = np.zeros((height, width), np_dtype)
        state = (
            np.ones((height, width), np_dtype),  # final transmittance
            np.zeros((height, width), np.int64),  # one past the last contributing list slot
            np.full((height, width), -1, np.int64),  # list slot of the median Gaussian
        )
        with _scheduling():
            _forward_kernel(*arrays, *grid, out, state[0], median, state[1], state[2])
        ctx.arrays, ctx.grid, ctx.state = arrays, grid, state
        ctx.gauss_ids, ctx.dtype = bins.gauss_ids, dtype
        return torch.from_numpy(out), torch.from_numpy(median)[None]

    @staticmethod
    def backward(ctx, grad_out, grad_median):
        dtype = ctx.dtype
        pair_grads = np.zeros((ctx.gauss_ids.shape[0], _GRAD_COLS), ctx.arrays[0].dtype)
        with _scheduling():
            _backward_kernel(
                *ctx.arrays, *ctx.grid, *ctx.state, _np(grad_out.to(dtype)), _np(grad_median[0].to(dtype)), pair_grads
            )
        num = ctx.arrays[0].shape[0]
        grads = torch.zeros(num, _GRAD_COLS, dtype=dtype).index_add_(0, ctx.gauss_ids, torch.from_numpy(pair_grads))
        d_means2d, d_conics, d_opac, d_feats, d_q, d_b, d_bounds = torch.split(grads, [2, 3, 1, 6, 9, 3, 2], dim=1)
        return d_means2d, d_conics, d_opac[:, 0], d_feats, d_q, d_b, d_bounds, None, None, None


def composite_numba(
    proj: Projection, opacities: Tensor, colors: Tensor, bins: TileBins, width: int, height: int
) -> Composite:
    """Composite on CPU with the compiled kernel; same inputs, outputs and rule as ``composite_torch``.

    Args:
        proj: :class:`Projection` of the N Gaussians (CPU tensors).
        opacities: (N,) opacities.
        colors: (N, 3) per-Gaussian colours for this view.
        bins: :class:`TileBins` from the same projection.
        width, height: image size.

    Returns:
        :class:`Composite`, differentiable through a custom autograd function.
    """
    if proj.means2d.device.type != "cpu":
        raise ValueError(f"composite_numba runs on CPU tensors only, got {proj.means2d.device}")
    feats = torch.cat([colors, proj.normals], dim=-1)
    image, median = _CompositeFunction.apply(
        proj.means2d, proj.conics, opacities, feats,
        proj.ray_coeffs.reshape(-1, 9), proj.ray_offsets, proj.depth_bounds, bins, width, height,
    )
    return Composite(
        color=image[0:3], depth=image[3:4], normal=image[4:7], alpha=image[7:8], median_depth=median
    )
