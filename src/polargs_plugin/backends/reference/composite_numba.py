"""Compiled CPU compositing (Numba) with a hand-written backward, same rule as :mod:`.composite_torch`.

Threads over tiles (``prange``). Within a tile the forward walks the tile's list once, front to
back, and each Gaussian updates only the tile's pixels inside its footprint box (from the conic
actually composited, with margins far above rounding, so that no pixel that could pass the exact
alpha >= 1/255 test is left out; per-pixel early termination, rows whose pixels have all stopped
are skipped). Along each row of the box, exp(-sigma) comes from one exponential at the row's
peak and a multiplication a pixel (:func:`_row_falloffs`), which also bounds the row to the span
where alpha >= 1/255 (a fifth of a box's pixels lie outside it). Forward and backward get the
same values from it. Each pixel sees its Gaussians in list order with the same arithmetic as a
pixel-by-pixel walk, so the sums are bit for bit those of a pixel-major loop. The backward walks
the same list back to front from each pixel's final transmittance (T_i = T_{i+1} / (1 - alpha_i),
alpha <= 0.99 keeps this stable) and sums each (tile, Gaussian) pair's gradient over its pixels
(row by row, in float64) into its own row, so threads never share a row; a serial kernel then
sums the rows per Gaussian. Gradients match the torch path (tests/).

What is composited besides the per-pixel depth and the alpha is a matrix of per-Gaussian feature
columns (:func:`composite_features_numba`): the reference rasterizer's colour, normal and plane
distance (:func:`composite_numba`), or the dry-run stand-ins' colours or all-maps, normal and
inverse depth. Its column count reaches the kernels as the length of a tuple, which numba types
(and caches) as a constant, so that the per-column loops are unrolled as the fixed columns were.
On request the same walk gives what the upstream CUDA rasterizers add: their median depth (the
last Gaussian blended while T > 0.5), 2DGS's depth distortion with its gradient (from the
pixel's sums A = sum w, M1 = sum w m, M2 = sum w m^2 over NDC-mapped depths m, since the
distortion is A M2 - M1^2), the pixels where each Gaussian was blended while T > 0.5, and the
sum over a Gaussian's pixels of |dL/d mean2d| (AbsGS).
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Literal, NamedTuple, get_args

import numba
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.threads import numba_scheduling

from .binning import TileBins, tile_centres
from .composite_torch import ALPHA_MAX, T_MIN, Composite
from .projection import ALPHA_MIN, Projection

__all__ = ["FeatureComposite", "MedianRule", "composite_features_numba", "composite_numba", "ray_ordered_numba"]

# Columns of the per-pair gradient rows besides the feature columns: means2d 2, conics 3,
# opacity 1, ray_coeffs 9, ray_offsets 3, depth_bounds 2, |dL/d mean| 2.
_GRAD_COLS = 22
_TILES_PER_CHUNK = 4  # tiles handed to a thread at a time: their lists differ a lot in length


@numba.njit(inline="always")
def _coeffs(ray_coeffs, g):
    """Gaussian g's 9 ray coefficients as a tuple of float64 (held in registers)."""
    return (
        float(ray_coeffs[g, 0]), float(ray_coeffs[g, 1]), float(ray_coeffs[g, 2]),
        float(ray_coeffs[g, 3]), float(ray_coeffs[g, 4]), float(ray_coeffs[g, 5]),
        float(ray_coeffs[g, 6]), float(ray_coeffs[g, 7]), float(ray_coeffs[g, 8]),
    )


@numba.njit(inline="always")
def _gaussian(g, means2d, conics, opacities, ray_offsets, depth_bounds, features, feat):
    """Gaussian g's values (its ray coefficients: :func:`_coeffs`) as locals of the input dtype
    (numba's ``float`` keeps a float32 a float32) and its feature columns copied into the tile's
    scratch ``feat``, read once before its pixel loop:
    numba cannot prove that the stores into the pixel state do not alias the inputs, and would
    reload every input at every pixel otherwise."""
    for c in range(feat.shape[0]):
        feat[c] = features[g, c]
    return (
        float(means2d[g, 0]), float(means2d[g, 1]),
        float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]), float(opacities[g]),
        float(ray_offsets[g, 0]), float(ray_offsets[g, 1]), float(ray_offsets[g, 2]),
        float(depth_bounds[g, 0]), float(depth_bounds[g, 1]),
    )


@numba.njit(inline="always")
def _row(c1, c2, q, py, dy):
    """The parts of a pixel's sigma and ray that are constant along pixel row ``py``:
    (c1 dy, c2 dy^2 / 2, and the three ray components' q_i1 py + q_i2), so that the pixel loop
    does the x-dependent half only. Forward and backward use the same expressions (same alpha)."""
    return c1 * dy, 0.5 * c2 * dy * dy, q[1] * py + q[2], q[4] * py + q[5], q[7] * py + q[8]


@numba.njit(inline="always")
def _sigma(c0, k1, k0, dx):
    """sigma = d^T C d / 2 at offset (dx, dy) from the row's constants (:func:`_row`)."""
    return (0.5 * c0 * dx + k1) * dx + k0


@numba.njit(inline="always")
def _row_falloffs(falloff, c0, k1, k0, mx, opacity, ulo, uhi):
    """exp(-sigma) along a pixel row (constants k1, k0: :func:`_row`) into falloff[u - ulo] for the
    span [first, last] of the row's pixels u in [ulo, uhi] where alpha = opacity exp(-sigma) reaches
    ALPHA_MIN; returns (first, last), first > last when none.

    sigma(dx) = (c0 dx / 2 + k1) dx + k0 is convex along the row (c0 > 0), smallest at the pixel
    nearest dx = -k1 / c0; from there exp(-sigma) only falls both ways, and the step
    sigma(dx + h) - sigma(dx) = h (c0 dx + k1) + c0 / 2 (h = +-1) changes by c0 a pixel, so one
    exponential starts each way and two multiplications a pixel go on (relative error a few ulps
    over a tile's row). Where c0 > 0 fails (a conic that is not positive definite is never binned)
    or the peak is not finite (NaN inputs), every pixel of the box gets its own exponential."""
    centre = mx - k1 / c0  # pixel coordinate of the smallest sigma
    if not (c0 > 0.0 and abs(centre) < 1e9):
        for u in range(ulo, uhi + 1):
            falloff[u - ulo] = np.exp(-_sigma(c0, k1, k0, u + 0.5 - mx))
        return ulo, uhi
    peak = min(max(int(math.floor(centre)), ulo), uhi)
    dx = peak + 0.5 - mx
    f = np.exp(-_sigma(c0, k1, k0, dx))
    if opacity * f < ALPHA_MIN:
        return peak + 1, peak
    falloff[peak - ulo] = f
    step = np.exp(-c0)
    slope = c0 * dx + k1
    last = _sweep(falloff, f, np.exp(-(slope + 0.5 * c0)), step, opacity, peak + 1, uhi + 1, 1, ulo)
    first = _sweep(falloff, f, np.exp(slope - 0.5 * c0), step, opacity, peak - 1, ulo - 1, -1, ulo)
    return first, last


@numba.njit(inline="always")
def _sweep(falloff, f, ratio, step, opacity, start, stop, direction, ulo):
    """One way of :func:`_row_falloffs`: from the value ``f`` next to ``start``, exp(-sigma) at
    the pixels ``range(start, stop, direction)`` (``ratio`` to the first, times ``step`` a pixel)
    until alpha falls under ALPHA_MIN; returns the last pixel written (``start - direction``: none)."""
    reached = start - direction
    for u in range(start, stop, direction):
        f *= ratio
        if opacity * f < ALPHA_MIN:
            break
        falloff[u - ulo] = f
        reached = u
        ratio *= step
    return reached


@numba.njit(inline="always")
def _ray(q, e0, e1, e2, b0, b1, b2, px):
    """Ray-Gaussian depth t = a.b / a.a at pixel centre (px, py), a = Q [px, py, 1] (``q`` the
    9 ray coefficients, row-major; ``e`` the row's constants, :func:`_row`), and 1 / a.a."""
    a0 = q[0] * px + e0
    a1 = q[3] * px + e1
    a2 = q[6] * px + e2
    inv_aa = 1.0 / (a0 * a0 + a1 * a1 + a2 * a2)
    t = (a0 * b0 + a1 * b1 + a2 * b2) * inv_aa
    return t, inv_aa


@numba.njit(inline="always")
def _ray_gradients(q, b0, b1, b2, s_x, s_y, s_1, m_xx, m_xy, m_x, m_yy, m_y, m_1, row, col):
    """Gradients of the ray coefficients Q (3x3, row-major ``q``) into ``row[col:col + 9]`` and of
    the offsets b into ``row[col + 9:col + 12]`` from a pair's pixel moments.

    Per pixel p = (px, py, 1), a = Q p and t = a.b / a.a, so with s = dL/dt / a.a:
    dL/db = sum s a = Q S and dL/dQ = sum s (b - 2 t a) p^T = b S^T - 2 Q M, where S = sum s p and
    M = sum s t p p^T (symmetric). Accumulating S and M (9 sums) instead of the 12 gradient
    entries per pixel saves the per-pixel products with b and a."""
    bs = (b0, b1, b2)
    for i in range(3):
        qx, qy, q1 = q[3 * i], q[3 * i + 1], q[3 * i + 2]
        row[col + 3 * i] = bs[i] * s_x - 2.0 * (qx * m_xx + qy * m_xy + q1 * m_x)
        row[col + 1 + 3 * i] = bs[i] * s_y - 2.0 * (qx * m_xy + qy * m_yy + q1 * m_y)
        row[col + 2 + 3 * i] = bs[i] * s_1 - 2.0 * (qx * m_x + qy * m_y + q1 * m_1)
        row[col + 9 + i] = qx * s_x + qy * s_y + q1 * s_1


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _footprint_kernel(means2d, conics, opacities, width, height, boxes):
    """Per Gaussian: the pixel box (u_lo, u_hi, v_lo, v_hi) holding every pixel centre where
    o exp(-sigma) >= 1/255 could hold.

    It comes from the conic actually composited (not the projection's extents), with relative
    margins far above float64 rounding, so skipping pixels outside the box never changes which
    pairs pass the exact test alpha >= 1/255."""
    for g in numba.prange(means2d.shape[0]):
        c0, c1, c2 = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
        det = c0 * c2 - c1 * c1
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        if not (det > 0.0 and c0 > 0.0 and c2 > 0.0 and abs(mx) < 1e9 and abs(my) < 1e9):
            # Not positive definite (never binned: extents 0) or non-finite: test every pixel.
            boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = 0, width - 1, 0, height - 1
            continue
        o = float(opacities[g])
        level = math.log(o / ALPHA_MIN) if o > 0.0 else -1.0
        if level < 0.0:  # sigma >= 0, so alpha <= o < 1/255: never contributes
            boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = 0, -1, 0, -1
            continue
        level = level * (1.0 + 1e-6) + 1e-9
        # sigma = 0.5 d^T C d <= level bounds |dx| by sqrt(2 level (C^-1)_xx) = sqrt(2 level c2 / det).
        hx = math.sqrt(2.0 * level * c2 / det) * (1.0 + 1e-6) + 1e-6
        hy = math.sqrt(2.0 * level * c0 / det) * (1.0 + 1e-6) + 1e-6
        boxes[g, 0] = max(int(math.ceil(mx - hx - 0.5)), 0)
        boxes[g, 1] = min(int(math.floor(mx + hx - 0.5)), width - 1)
        boxes[g, 2] = max(int(math.ceil(my - hy - 0.5)), 0)
        boxes[g, 3] = min(int(math.floor(my + hy - 0.5)), height - 1)


@numba.njit(inline="always")
def _clip_box(boxes, g, u0, v0, tile_size, width, height):
    return (
        max(boxes[g, 0], u0), min(boxes[g, 1], u0 + tile_size - 1, width - 1),
        max(boxes[g, 2], v0), min(boxes[g, 3], v0 + tile_size - 1, height - 1),
    )


@numba.njit(inline="always")
def _ndc_depth(z, ndc_near, ndc_scale):
    """The distortion's NDC-mapped depth m = scale (1 - near / max(z, near)) and dm/dz."""
    if z >= ndc_near:
        return ndc_scale * (1.0 - ndc_near / z), ndc_scale * ndc_near / (z * z)
    return 0.0, 0.0


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _forward_kernel(
    means2d, conics, opacities, features, ray_coeffs, ray_offsets, depth_bounds, boxes,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height, median_above, ndc_near, ndc_far, columns,
    out_features, out_depth, out_alpha, out_distortion, trans_final, median, moments, last_slot, median_slot,
    observe_slot,
):
    num_tiles = tile_offsets.shape[0] - 1
    nf = len(columns)  # a compile-time constant (the tuple's length is its type): the feature loops unroll
    with_distortion = ndc_far > ndc_near
    ndc_scale = ndc_far / (ndc_far - ndc_near) if with_distortion else 0.0
    for tile in numba.prange(num_tiles):
        start, end = tile_offsets[tile], tile_offsets[tile + 1]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        tw = min(u0 + tile_size, width) - u0
        th = min(v0 + tile_size, height) - v0
        # Per-pixel state of the tile, pixel p = (v - v0) * tile_size + (u - u0).
        npix = tile_size * tile_size
        trans = np.ones(npix)
        acc = np.zeros((npix, nf + 1))  # feature columns, depth sum
        dist = np.zeros((npix, 3))  # distortion, sum w m, sum w m^2 (m: NDC-mapped depth)
        med_z = np.zeros(npix)
        med_j = np.full(npix, -1, np.int64)
        last = np.full(npix, start, np.int64)
        done = np.zeros(npix, np.bool_)
        row_active = np.full(tile_size, tw, np.int64)  # pixels of each row still compositing
        active = tw * th
        row_falloff = np.empty(tile_size)  # exp(-sigma) along a row (_row_falloffs)
        feat = np.empty(nf, features.dtype)  # the current Gaussian's feature columns (input dtype)
        for j in range(start, end):
            if active == 0:
                break
            g = gauss_ids[j]
            ulo, uhi, vlo, vhi = _clip_box(boxes, g, u0, v0, tile_size, width, height)
            if ulo > uhi or vlo > vhi:
                continue
            (mx, my, c0, c1, c2, opacity, b0, b1, b2, lo, hi) = _gaussian(
                g, means2d, conics, opacities, ray_offsets, depth_bounds, features, feat)
            q = _coeffs(ray_coeffs, g)
            observed = 0
            for v in range(vlo, vhi + 1):
                if row_active[v - v0] == 0:
                    continue
                py = v + 0.5
                dy = py - my
                k1, k0, e0, e1, e2 = _row(c1, c2, q, py, dy)
                first, last_u = _row_falloffs(row_falloff, c0, k1, k0, mx, opacity, ulo, uhi)
                for u in range(first, last_u + 1):
                    p = (v - v0) * tile_size + (u - u0)
                    if done[p]:
                        continue
                    px = u + 0.5
                    alpha = min(opacity * row_falloff[u - ulo], ALPHA_MAX)
                    if alpha < ALPHA_MIN:
                        continue
                    tp = trans[p]
                    next_t = tp * (1.0 - alpha)
                    if next_t < T_MIN:
                        done[p] = True
                        row_active[v - v0] -= 1
                        active -= 1
                        continue
                    t = _ray(q, e0, e1, e2, b0, b1, b2, px)[0]
                    z = min(max(t, lo), hi)
                    w = alpha * tp
                    for c in range(nf):
                        acc[p, c] += w * feat[c]
                    acc[p, nf] += w * z
                    if with_distortion:
                        # 2DGS's per-pair form w (m^2 A + M2 - 2 m M1), A = 1 - T the earlier weights
                        m = _ndc_depth(z, ndc_near, ndc_scale)[0]
                        m1, m2 = dist[p, 1], dist[p, 2]
                        dist[p, 0] += (m * m * (1.0 - tp) + m2 - 2.0 * m * m1) * w
                        dist[p, 1] = m1 + w * m
                        dist[p, 2] = m2 + w * m * m
                    if tp > 0.5:
                        observed += 1
                        if median_above:
                            med_z[p] = z
                            med_j[p] = j
                    if not median_above and tp >= 0.5 and next_t < 0.5:
                        med_z[p] = z
                        med_j[p] = j
                    trans[p] = next_t
                    last[p] = j + 1
            observe_slot[j] = observed
        for v in range(v0, v0 + th):
            for u in range(u0, u0 + tw):
                p = (v - v0) * tile_size + (u - u0)
                for c in range(nf):
                    out_features[c, v, u] = acc[p, c]
                out_depth[0, v, u] = acc[p, nf]
                out_alpha[0, v, u] = 1.0 - trans[p]
                out_distortion[0, v, u] = dist[p, 0]
                moments[0, v, u] = dist[p, 1]
                moments[1, v, u] = dist[p, 2]
                trans_final[v, u] = trans[p]
                median[v, u] = med_z[p]
                last_slot[v, u] = last[p]
                median_slot[v, u] = med_j[p]


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _backward_kernel(
    means2d, conics, opacities, features, ray_coeffs, ray_offsets, depth_bounds, boxes,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height, median_above, ndc_near, ndc_far, columns,
    trans_final, moments, last_slot, median_slot, grad_features, grad_depth, grad_alpha, grad_median,
    grad_distortion, with_abs, pair_grads,
):
    num_tiles = tile_offsets.shape[0] - 1
    nf = len(columns)  # a compile-time constant (the tuple's length is its type): the feature loops unroll
    with_distortion = ndc_far > ndc_near
    ndc_scale = ndc_far / (ndc_far - ndc_near) if with_distortion else 0.0
    col_q = 6 + nf  # pair_grads columns: means2d 2, conics 3, opacity, features, Q 9, b 3, bounds 2, |mean| 2
    col_bounds = col_q + 12
    for tile in numba.prange(num_tiles):
        start = tile_offsets[tile]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        tw = min(u0 + tile_size, width) - u0
        th = min(v0 + tile_size, height) - v0
        npix = tile_size * tile_size
        trans = np.ones(npix)
        rest = np.zeros(npix)
        # features, depth, median, distortion (input dtype)
        grads = np.zeros((npix, nf + 3), grad_features.dtype)
        totals = np.zeros((npix, 3))  # the distortion's A = sum w, M1 = sum w m, M2 = sum w m^2
        last = np.full(npix, start, np.int64)
        med_j = np.full(npix, -1, np.int64)
        row_end = np.full(tile_size, start, np.int64)  # one past the last slot any pixel of the row uses
        end = start
        row_falloff = np.empty(tile_size)  # the forward's exp(-sigma) along a row
        feat = np.empty(nf, features.dtype)  # the current Gaussian's feature columns (input dtype)
        d_feat = np.empty(nf)  # and their gradient, summed over the pair's pixels
        for v in range(v0, v0 + th):
            for u in range(u0, u0 + tw):
                p = (v - v0) * tile_size + (u - u0)
                for c in range(nf):
                    grads[p, c] = grad_features[c, v, u]
                grads[p, nf] = grad_depth[0, v, u]
                grads[p, nf + 1] = grad_median[0, v, u]
                if with_distortion:
                    grads[p, nf + 2] = grad_distortion[0, v, u]
                    totals[p, 0] = 1.0 - trans_final[v, u]
                    totals[p, 1] = moments[0, v, u]
                    totals[p, 2] = moments[1, v, u]
                trans[p] = trans_final[v, u]
                # alpha_out = 1 - T_final, so the pixel's "rest" term starts at -g_alpha * T_final.
                rest[p] = -grad_alpha[0, v, u] * trans_final[v, u]
                last[p] = last_slot[v, u]
                med_j[p] = median_slot[v, u]
                row_end[v - v0] = max(row_end[v - v0], last_slot[v, u])
            end = max(end, row_end[v - v0])
        pair_grads[end : tile_offsets[tile + 1], :] = 0.0  # slots no pixel reaches
        for j in range(end - 1, start - 1, -1):
            g = gauss_ids[j]
            ulo, uhi, vlo, vhi = _clip_box(boxes, g, u0, v0, tile_size, width, height)
            if ulo > uhi or vlo > vhi:
                pair_grads[j, :] = 0.0
                continue
            (mx, my, c0, c1, c2, opacity, b0, b1, b2, lo, hi) = _gaussian(
                g, means2d, conics, opacities, ray_offsets, depth_bounds, features, feat)
            q = _coeffs(ray_coeffs, g)
            # This pair's gradient, summed in float64 locals (registers, not memory) over the
            # pixels in row-major order and written once (each pair belongs to one tile).
            d_mx = d_my = d_c0 = d_c1 = d_c2 = d_op = 0.0
            d_feat[:] = 0.0
            abs_x = abs_y = 0.0  # sums over the pixels of |dL/d mean| (AbsGS)
            # Depth terms as moments over the pixels (see _ray_gradients): S = sum s p, M = sum s t p p^T.
            s_x = s_y = s_1 = m_xx = m_xy = m_x = m_yy = m_y = m_1 = 0.0
            d_lo = d_hi = 0.0
            for v in range(vlo, vhi + 1):
                if j >= row_end[v - v0]:
                    continue
                py = v + 0.5
                dy = py - my
                k1, k0, e0, e1, e2 = _row(c1, c2, q, py, dy)
                # The row's sums over its pixels; what multiplies them is constant along the row
                # (dy, py), so it is applied once at the row's end: d_sigma sums for the conic and
                # the mean, s and s t sums for the ray moments.
                r_ds = r_dsx = r_dsxx = 0.0
                r_s = r_sx = r_st = r_stx = r_stxx = 0.0
                first, last_u = _row_falloffs(row_falloff, c0, k1, k0, mx, opacity, ulo, uhi)
                for u in range(first, last_u + 1):
                    p = (v - v0) * tile_size + (u - u0)
                    if j >= last[p]:
                        continue
                    px = u + 0.5
                    dx = px - mx
                    falloff = row_falloff[u - ulo]
                    raw = opacity * falloff
                    alpha = min(raw, ALPHA_MAX)
                    if alpha < ALPHA_MIN:
                        continue
                    keep = 1.0 / (1.0 - alpha)
                    tp = trans[p] * keep
                    trans[p] = tp
                    gd, g_dist = grads[p, nf], grads[p, nf + 2]
                    # dL/d(this pair's weight). The feature products and their sum stay in the
                    # input dtype, as the reference rasterizer has always computed them: a float64
                    # sum would change a float32 training in its last bits.
                    feature_sum = feat[0] * grads[p, 0]
                    for c in range(1, nf):
                        feature_sum += feat[c] * grads[p, c]
                    fg = feature_sum
                    # The depth terms only where the pixel's depth, median depth or distortion has
                    # a gradient (never in a colour-only loss): skipping them adds nothing but zeros.
                    median_here = j == med_j[p]
                    geometric = gd != 0.0 or median_here or g_dist != 0.0
                    dz_dw = 0.0  # dL/dz per unit weight
                    if geometric:
                        t, inv_aa = _ray(q, e0, e1, e2, b0, b1, b2, px)
                        z = min(max(t, lo), hi)
                        fg += z * gd
                        dz_dw = gd
                        if g_dist != 0.0:
                            # D = A M2 - M1^2 over the pixel's totals: dD/dw = M2 + A m^2 - 2 M1 m
                            # and dD/dm = 2 w (A m - M1).
                            m, dm_dz = _ndc_depth(z, ndc_near, ndc_scale)
                            a_tot, m1, m2 = totals[p, 0], totals[p, 1], totals[p, 2]
                            fg += g_dist * (m2 + a_tot * m * m - 2.0 * m1 * m)
                            dz_dw += g_dist * 2.0 * (a_tot * m - m1) * dm_dz
                    w = alpha * tp
                    rp = rest[p]
                    d_alpha = tp * fg - rp * keep
                    rest[p] = rp + w * fg

                    for c in range(nf):
                        d_feat[c] += w * grads[p, c]
                    if geometric:
                        dz = w * dz_dw
                        if median_here:
                            dz += grads[p, nf + 1]
                        if t < lo:
                            d_lo += dz
                        elif t > hi:
                            d_hi += dz
                        else:
                            s = dz * inv_aa
                            r_s += s
                            r_sx += s * px
                            st = s * t
                            r_st += st
                            stx = st * px
                            r_stx += stx
                            r_stxx += stx * px
                    if raw <= ALPHA_MAX:
                        d_op += d_alpha * falloff  # alpha / opacity, unclamped here
                        d_sigma = -d_alpha * alpha
                        r_ds += d_sigma
                        dsx = d_sigma * dx
                        r_dsx += dsx
                        r_dsxx += dsx * dx
                        if with_abs:
                            abs_x += abs(d_sigma * (c0 * dx + c1 * dy))
                            abs_y += abs(d_sigma * (c1 * dx + c2 * dy))
                # sigma = c0 dx^2 / 2 + c1 dx dy + c2 dy^2 / 2; d sigma / d mean = -C d
                d_c0 += 0.5 * r_dsxx
                d_c1 += dy * r_dsx
                d_c2 += 0.5 * dy * dy * r_ds
                d_mx -= c0 * r_dsx + c1 * dy * r_ds
                d_my -= c1 * r_dsx + c2 * dy * r_ds
                # S = sum s p and M = sum s t p p^T with p = (px, py, 1)
                s_x += r_sx
                s_y += py * r_s
                s_1 += r_s
                m_xx += r_stxx
                m_xy += py * r_stx
                m_x += r_stx
                m_yy += py * py * r_st
                m_y += py * r_st
                m_1 += r_st
            row = pair_grads[j]
            row[0], row[1], row[2], row[3], row[4], row[5] = d_mx, d_my, d_c0, d_c1, d_c2, d_op
            for c in range(nf):
                row[6 + c] = d_feat[c]
            _ray_gradients(q, b0, b1, b2, s_x, s_y, s_1, m_xx, m_xy, m_x, m_yy, m_y, m_1, row, col_q)
            row[col_bounds], row[col_bounds + 1] = d_lo, d_hi
            row[col_bounds + 2], row[col_bounds + 3] = abs_x, abs_y


@numba.njit(cache=True)
def _sum_pairs(gauss_ids, pair_grads, grads):
    """grads[g] += pair_grads[j] for every pair j of Gaussian g, in pair order (what
    ``index_add_`` did; serial, so the sums do not depend on the thread count)."""
    for j in range(gauss_ids.shape[0]):
        g = gauss_ids[j]
        for c in range(pair_grads.shape[1]):
            grads[g, c] += pair_grads[j, c]


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _Rules(NamedTuple):
    """What :class:`_CompositeFunction` composites besides the feature columns."""

    median_above: bool  # median depth: the last Gaussian blended while T > 0.5 (else the one crossing 0.5)
    ndc_near: float  # the distortion's NDC depth mapping (no distortion when ndc_far <= ndc_near)
    ndc_far: float
    abs_factors: tuple[float, float]  # units of the absolute mean gradient (per pixel of x, y)


class _CompositeFunction(torch.autograd.Function):
    """Inputs: means2d, conics, opacities, the feature columns (N, F), ray coefficients (N, 9),
    ray offsets, depth bounds, the absolute-gradient target (None, (N, 1) or (N, 2)), then the
    non-differentiable bins, width, height, the column counts of the feature groups and the
    :class:`_Rules`. Outputs: one (F_k, H, W) sum per feature group, depth (1, H, W), alpha
    (1, H, W), median depth (1, H, W), distortion (1, H, W) and the observe counts (N,), each
    its own tensor (no slicing, so no slice backward)."""

    @staticmethod
    def forward(
        ctx, means2d, conics, opacities, features, ray_coeffs, ray_offsets, depth_bounds, abs_target, bins,
        width, height, groups, rules,
    ):
        dtype = means2d.dtype
        inputs = (means2d, conics, opacities, features, ray_coeffs, ray_offsets, depth_bounds)
        arrays = [_np(x.to(dtype)) for x in inputs]
        grid = (_np(bins.gauss_ids), _np(bins.tile_offsets), bins.tiles_x, bins.tile_size, width, height)
        options = (rules.median_above, rules.ndc_near, rules.ndc_far, (0,) * features.shape[1])
        np_dtype = arrays[0].dtype
        # Every pixel belongs to one tile, so the kernel writes every entry of these.
        image = np.empty((features.shape[1], height, width), np_dtype)
        outs = tuple(np.empty((1, height, width), np_dtype) for _ in range(4))  # depth, alpha, median, distortion
        state = (
            np.empty((height, width), np_dtype),  # final transmittance
            np.empty((2, height, width), np.float64),  # the distortion's sums of w m and w m^2
            np.empty((height, width), np.int64),  # one past the last contributing list slot
            np.empty((height, width), np.int64),  # list slot of the median Gaussian (-1: none)
        )
        observe_slot = np.zeros(bins.gauss_ids.shape[0], np.int64)
        num = arrays[0].shape[0]
        boxes = np.empty((num, 4), np.int64)
        with numba_scheduling(chunksize=_TILES_PER_CHUNK):
            _footprint_kernel(arrays[0], arrays[1], arrays[2], width, height, boxes)
            arrays = (*arrays, boxes)
            _forward_kernel(*arrays, *grid, *options, image, outs[0], outs[1], outs[3], state[0], outs[2][0],
                            *state[1:], observe_slot)
        observe = np.bincount(grid[0], weights=observe_slot, minlength=num)  # exact: integer counts
        ctx.arrays, ctx.grid, ctx.options, ctx.state = arrays, grid, options, state
        ctx.dtype, ctx.groups, ctx.rules = dtype, groups, rules
        ctx.abs_shape = None if abs_target is None else abs_target.shape
        observe_t = torch.from_numpy(observe.astype(np.int32))
        ctx.mark_non_differentiable(observe_t)
        bounds = np.cumsum((0, *groups))
        images = tuple(torch.from_numpy(image[a:b]) for a, b in itertools.pairwise(bounds))
        return (*images, *(torch.from_numpy(o) for o in outs), observe_t)

    @staticmethod
    def backward(ctx, *output_grads):
        dtype, nf = ctx.dtype, sum(ctx.groups)
        gauss_ids = ctx.grid[0]
        image_grads, rest_grads = output_grads[: len(ctx.groups)], output_grads[len(ctx.groups) : -1]
        grad_features = _np(torch.cat(image_grads).to(dtype))
        grad_depth, grad_alpha, grad_median, grad_distortion = (_np(g.to(dtype)) for g in rest_grads)
        with_abs = ctx.abs_shape is not None and ctx.needs_input_grad[7]
        pair_grads = np.empty((gauss_ids.shape[0], nf + _GRAD_COLS), np.float64)
        with numba_scheduling(chunksize=_TILES_PER_CHUNK):
            _backward_kernel(*ctx.arrays, *ctx.grid, *ctx.options, *ctx.state, grad_features,
                             grad_depth, grad_alpha, grad_median, grad_distortion, with_abs, pair_grads)
        grads = np.zeros((ctx.arrays[0].shape[0], pair_grads.shape[1]), np.float64)
        _sum_pairs(gauss_ids, pair_grads, grads)
        grads = torch.from_numpy(grads).to(dtype)
        d_means2d, d_conics, d_opac, d_features, d_q, d_b, d_bounds, d_abs = torch.split(
            grads, [2, 3, 1, nf, 9, 3, 2, 2], dim=1
        )
        if with_abs:
            d_abs = d_abs * d_abs.new_tensor(ctx.rules.abs_factors)
            d_abs = d_abs.sum(dim=1, keepdim=True) if ctx.abs_shape[1] == 1 else d_abs
        return (d_means2d, d_conics, d_opac[:, 0], d_features, d_q, d_b, d_bounds, d_abs if with_abs else None,
                None, None, None, None, None)


MedianRule = Literal["crossing", "last_above"]


class FeatureComposite(NamedTuple):
    """What :func:`composite_features_numba` composites for one image (channel-first).

    Attributes:
        features: one (C_k, H, W) sum of weight * column per feature group, in the given order.
        depth: (1, H, W) sum of weight * per-pixel depth (not normalised).
        alpha: (1, H, W) sum of weights = 1 - final transmittance.
        median_depth: (1, H, W) per-pixel depth of the median Gaussian (``median``), else 0.
        distortion: (1, H, W) depth distortion sum_ij w_i w_j (m_i - m_j)^2 / 2 over NDC-mapped
            depths m (0 without ``distortion_planes``).
        observe: (N,) int32, pixels where each Gaussian was blended while T > 0.5.
    """

    features: tuple[Tensor, ...]
    depth: Tensor
    alpha: Tensor
    median_depth: Tensor
    distortion: Tensor
    observe: Tensor


def composite_features_numba(
    proj: Projection, opacities: Tensor, features: Sequence[Tensor], bins: TileBins, width: int, height: int, *,
    median: MedianRule = "crossing", distortion_planes: tuple[float, float] | None = None,
    screen_abs: Tensor | None = None, abs_factors: tuple[float, float] = (1.0, 1.0),
) -> FeatureComposite:
    """Composite any number of per-Gaussian feature columns with the compiled kernel (the rule of
    :mod:`.composite_torch`), with the depth, alpha and median depth, and optionally the depth
    distortion and the absolute screen-space gradient; differentiable (hand-written backward).

    Args:
        proj: :class:`Projection` of the N Gaussians (CPU tensors).
        opacities: (N,) opacities.
        features: groups of (N, C_k) columns, composited with the colour weights; each group
            comes back as its own image.
        bins: :class:`TileBins` from the same projection.
        width, height: image size.
        median: "crossing": the depth of the Gaussian at which T first drops below 0.5 (the
            reference rasterizer's rule); "last_above": of the last Gaussian blended while T > 0.5
            (the upstream CUDA rasterizers').
        distortion_planes: (near, far) of the NDC depth mapping m = far / (far - near)
            (1 - near / max(z, near)) of 2DGS's distortion; None: no distortion (zeros).
        screen_abs: (N, 1) or (N, 2) zero tensor whose ``.grad`` receives, per Gaussian, the sum
            over its pixels of |dL/d mean2d| (|x| + |y|, or per axis), times ``abs_factors``.
        abs_factors: (x, y) factors of that absolute gradient (e.g. the NDC factors W/2, H/2).
    """
    if proj.means2d.device.type != "cpu":
        raise ValueError(f"composite_numba runs on CPU tensors only, got {proj.means2d.device}")
    if median not in get_args(MedianRule):
        raise ValueError(f"median must be one of {get_args(MedianRule)}, got {median!r}")
    if screen_abs is not None and (screen_abs.dim() != 2 or screen_abs.shape[1] not in (1, 2)):
        raise ValueError(f"screen_abs must be (N, 1) or (N, 2), got {tuple(screen_abs.shape)}")
    near, far = (0.0, 0.0) if distortion_planes is None else (float(distortion_planes[0]), float(distortion_planes[1]))
    if distortion_planes is not None and not 0.0 < near < far:
        raise ValueError(f"distortion_planes must be 0 < near < far, got {distortion_planes}")
    groups = tuple(int(f.shape[1]) for f in features)
    if not groups or min(groups) < 1:
        raise ValueError(f"features must be one or more (N, C) groups with C >= 1, got columns {groups}")
    dtype = proj.means2d.dtype
    columns = torch.cat([f.to(dtype) for f in features], dim=1)
    rules = _Rules(median == "last_above", near, far, (float(abs_factors[0]), float(abs_factors[1])))
    *images, depth, alpha, median_depth, distortion, observe = _CompositeFunction.apply(
        proj.means2d, proj.conics, opacities, columns, proj.ray_coeffs.reshape(-1, 9), proj.ray_offsets,
        proj.depth_bounds, screen_abs, bins, width, height, groups, rules,
    )
    return FeatureComposite(tuple(images), depth, alpha, median_depth, distortion, observe)


def composite_numba(
    proj: Projection, opacities: Tensor, colors: Tensor, bins: TileBins, width: int, height: int,
    distances: Tensor | None = None,
) -> Composite:
    """Composite on CPU with the compiled kernel; same inputs, outputs and rule as ``composite_torch``.

    Args:
        proj: :class:`Projection` of the N Gaussians (CPU tensors).
        opacities: (N,) opacities.
        colors: (N, 3) per-Gaussian colours for this view.
        bins: :class:`TileBins` from the same projection.
        width, height: image size.
        distances: optional (N,) per-Gaussian plane distances, composited like a colour channel.

    Returns:
        :class:`Composite`, differentiable through a custom autograd function.
    """
    features = [colors, proj.normals] + ([] if distances is None else [distances[:, None]])
    out = composite_features_numba(proj, opacities, features, bins, width, height)
    return Composite(color=out.features[0], depth=out.depth, normal=out.features[1], alpha=out.alpha,
                     median_depth=out.median_depth, distance=None if distances is None else out.features[2])


def ray_ordered_numba(bins: TileBins, keys: tuple[Tensor, Tensor, Tensor]) -> TileBins:
    """:func:`~.rasterizer.ray_ordered` compiled, with the same arithmetic in the keys' dtype and
    the same stable sort (the same lists): each tile's list sorted in a copy, a tile per thread,
    with no pair-sized temporaries (one-pixel tiles hold each Gaussian once per pixel it covers:
    tens of millions of pairs in a megapixel image)."""
    ray_coeffs, ray_offsets, depth_bounds = (k.detach() for k in keys)
    gauss_ids = bins.gauss_ids.clone()
    _sort_tiles_by_ray_depth(gauss_ids.numpy(), bins.tile_offsets.numpy(), tile_centres(bins, ray_coeffs.dtype).numpy(),
                             ray_coeffs.reshape(-1, 9).numpy(), ray_offsets.numpy(), depth_bounds.numpy())
    return bins._replace(gauss_ids=gauss_ids)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _sort_tiles_by_ray_depth(gauss_ids, tile_offsets, centres, ray_coeffs, ray_offsets, depth_bounds):
    """Sort each tile's slice of ``gauss_ids`` (stable) by the clamped depth of maximum density
    on the ray through the tile's centre, as :func:`~.composite_torch.pixel_depth` computes it
    (in the dtype of ``centres`` and the ray data)."""
    for tile in numba.prange(tile_offsets.shape[0] - 1):
        start, end = tile_offsets[tile], tile_offsets[tile + 1]
        if end - start < 2:
            continue
        px, py = centres[tile, 0], centres[tile, 1]
        keys = np.empty(end - start, centres.dtype)
        for j in range(start, end):
            g = gauss_ids[j]
            q, b = ray_coeffs[g], ray_offsets[g]
            a0 = q[0] * px + q[1] * py + q[2]
            a1 = q[3] * px + q[4] * py + q[5]
            a2 = q[6] * px + q[7] * py + q[8]
            t = (a0 * b[0] + a1 * b[1] + a2 * b[2]) / (a0 * a0 + a1 * a1 + a2 * a2)
            keys[j - start] = min(max(t, depth_bounds[g, 0]), depth_bounds[g, 1])
        order = np.argsort(keys, kind="mergesort")
        listed = gauss_ids[start:end].copy()
        for j in range(end - start):
            gauss_ids[start + j] = listed[order[j]]
