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
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.threads import numba_scheduling

from .binning import TileBins, tile_centres
from .composite_torch import ALPHA_MAX, T_MIN, Composite
from .projection import ALPHA_MIN, Projection

__all__ = ["composite_numba", "ray_ordered_numba"]

# Columns of the per-pair gradient rows: means2d 2, conics 3, opacity 1, colour 3, normal 3,
# ray_coeffs 9, ray_offsets 3, depth_bounds 2, plane distance 1.
_GRAD_COLS = 27
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
def _gaussian(g, means2d, conics, opacities, colors, normals, ray_offsets, depth_bounds, distances):
    """Gaussian g's values (its ray coefficients: :func:`_coeffs`) as float64 locals, read once
    before its pixel loop: numba cannot prove that the stores into the pixel state do not alias the
    inputs, and would reload every input at every pixel otherwise."""
    return (
        float(means2d[g, 0]), float(means2d[g, 1]),
        float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]), float(opacities[g]),
        float(colors[g, 0]), float(colors[g, 1]), float(colors[g, 2]),
        float(normals[g, 0]), float(normals[g, 1]), float(normals[g, 2]),
        float(ray_offsets[g, 0]), float(ray_offsets[g, 1]), float(ray_offsets[g, 2]),
        float(depth_bounds[g, 0]), float(depth_bounds[g, 1]), float(distances[g]),
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
def _ray_gradients(q, b0, b1, b2, s_x, s_y, s_1, m_xx, m_xy, m_x, m_yy, m_y, m_1, row):
    """Gradients of the ray coefficients Q (3x3, row-major ``q``) and offsets b into ``row[12:24]``
    from a pair's pixel moments.

    Per pixel p = (px, py, 1), a = Q p and t = a.b / a.a, so with s = dL/dt / a.a:
    dL/db = sum s a = Q S and dL/dQ = sum s (b - 2 t a) p^T = b S^T - 2 Q M, where S = sum s p and
    M = sum s t p p^T (symmetric). Accumulating S and M (9 sums) instead of the 12 gradient
    entries per pixel saves the per-pixel products with b and a."""
    bs = (b0, b1, b2)
    for i in range(3):
        qx, qy, q1 = q[3 * i], q[3 * i + 1], q[3 * i + 2]
        row[12 + 3 * i] = bs[i] * s_x - 2.0 * (qx * m_xx + qy * m_xy + q1 * m_x)
        row[13 + 3 * i] = bs[i] * s_y - 2.0 * (qx * m_xy + qy * m_yy + q1 * m_y)
        row[14 + 3 * i] = bs[i] * s_1 - 2.0 * (qx * m_x + qy * m_y + q1 * m_1)
        row[21 + i] = qx * s_x + qy * s_y + q1 * s_1


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


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _forward_kernel(
    means2d, conics, opacities, colors, normals, ray_coeffs, ray_offsets, depth_bounds, distances, boxes,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height,
    out_color, out_depth, out_normal, out_alpha, out_distance, trans_final, median, last_slot, median_slot,
):
    num_tiles = tile_offsets.shape[0] - 1
    for tile in numba.prange(num_tiles):
        start, end = tile_offsets[tile], tile_offsets[tile + 1]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        tw = min(u0 + tile_size, width) - u0
        th = min(v0 + tile_size, height) - v0
        # Per-pixel state of the tile, pixel p = (v - v0) * tile_size + (u - u0).
        npix = tile_size * tile_size
        trans = np.ones(npix)
        acc = np.zeros((npix, 8))  # colour 3, depth sum, normal 3, plane distance
        med_z = np.zeros(npix)
        med_j = np.full(npix, -1, np.int64)
        last = np.full(npix, start, np.int64)
        done = np.zeros(npix, np.bool_)
        row_active = np.full(tile_size, tw, np.int64)  # pixels of each row still compositing
        active = tw * th
        row_falloff = np.empty(tile_size)  # exp(-sigma) along a row (_row_falloffs)
        for j in range(start, end):
            if active == 0:
                break
            g = gauss_ids[j]
            ulo, uhi, vlo, vhi = _clip_box(boxes, g, u0, v0, tile_size, width, height)
            if ulo > uhi or vlo > vhi:
                continue
            (mx, my, c0, c1, c2, opacity, col0, col1, col2, n0, n1, n2, b0, b1, b2, lo, hi, dist) = _gaussian(
                g, means2d, conics, opacities, colors, normals, ray_offsets, depth_bounds, distances)
            q = _coeffs(ray_coeffs, g)
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
                    acc[p, 0] += w * col0
                    acc[p, 1] += w * col1
                    acc[p, 2] += w * col2
                    acc[p, 3] += w * z
                    acc[p, 4] += w * n0
                    acc[p, 5] += w * n1
                    acc[p, 6] += w * n2
                    acc[p, 7] += w * dist
                    if tp >= 0.5 and next_t < 0.5:
                        med_z[p] = z
                        med_j[p] = j
                    trans[p] = next_t
                    last[p] = j + 1
        for v in range(v0, v0 + th):
            for u in range(u0, u0 + tw):
                p = (v - v0) * tile_size + (u - u0)
                out_color[0, v, u] = acc[p, 0]
                out_color[1, v, u] = acc[p, 1]
                out_color[2, v, u] = acc[p, 2]
                out_depth[0, v, u] = acc[p, 3]
                out_normal[0, v, u] = acc[p, 4]
                out_normal[1, v, u] = acc[p, 5]
                out_normal[2, v, u] = acc[p, 6]
                out_distance[0, v, u] = acc[p, 7]
                out_alpha[0, v, u] = 1.0 - trans[p]
                trans_final[v, u] = trans[p]
                median[v, u] = med_z[p]
                last_slot[v, u] = last[p]
                median_slot[v, u] = med_j[p]


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _backward_kernel(
    means2d, conics, opacities, colors, normals, ray_coeffs, ray_offsets, depth_bounds, distances, boxes,
    gauss_ids, tile_offsets, tiles_x, tile_size, width, height,
    trans_final, last_slot, median_slot, grad_color, grad_depth, grad_normal, grad_alpha, grad_median,
    grad_distance, pair_grads,
):
    num_tiles = tile_offsets.shape[0] - 1
    for tile in numba.prange(num_tiles):
        start = tile_offsets[tile]
        u0 = (tile % tiles_x) * tile_size
        v0 = (tile // tiles_x) * tile_size
        tw = min(u0 + tile_size, width) - u0
        th = min(v0 + tile_size, height) - v0
        npix = tile_size * tile_size
        trans = np.ones(npix)
        rest = np.zeros(npix)
        grads = np.zeros((npix, 9), grad_color.dtype)  # colour 3, depth, normal 3, median, distance (input dtype)
        last = np.full(npix, start, np.int64)
        med_j = np.full(npix, -1, np.int64)
        row_end = np.full(tile_size, start, np.int64)  # one past the last slot any pixel of the row uses
        end = start
        row_falloff = np.empty(tile_size)  # the forward's exp(-sigma) along a row
        for v in range(v0, v0 + th):
            for u in range(u0, u0 + tw):
                p = (v - v0) * tile_size + (u - u0)
                for c in range(3):
                    grads[p, c] = grad_color[c, v, u]
                    grads[p, 4 + c] = grad_normal[c, v, u]
                grads[p, 3] = grad_depth[0, v, u]
                grads[p, 7] = grad_median[0, v, u]
                grads[p, 8] = grad_distance[0, v, u]
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
            (mx, my, c0, c1, c2, opacity, col0, col1, col2, n0, n1, n2, b0, b1, b2, lo, hi, dist) = _gaussian(
                g, means2d, conics, opacities, colors, normals, ray_offsets, depth_bounds, distances)
            q = _coeffs(ray_coeffs, g)
            # This pair's gradient, summed in float64 locals (registers, not memory) over the
            # pixels in row-major order and written once (each pair belongs to one tile).
            d_mx = d_my = d_c0 = d_c1 = d_c2 = d_op = 0.0
            d_col0 = d_col1 = d_col2 = d_n0 = d_n1 = d_n2 = d_dist = 0.0
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
                    gc0, gc1, gc2, gd = grads[p, 0], grads[p, 1], grads[p, 2], grads[p, 3]
                    gn0, gn1, gn2, gdist = grads[p, 4], grads[p, 5], grads[p, 6], grads[p, 8]
                    fg = col0 * gc0 + col1 * gc1 + col2 * gc2 + n0 * gn0 + n1 * gn1 + n2 * gn2 + dist * gdist
                    # The depth terms only where the pixel's depth or median depth has a gradient
                    # (never in a colour-only loss): skipping them adds nothing but zeros.
                    median_here = j == med_j[p]
                    geometric = gd != 0.0 or median_here
                    if geometric:
                        t, inv_aa = _ray(q, e0, e1, e2, b0, b1, b2, px)
                        z = min(max(t, lo), hi)
                        fg += z * gd
                    w = alpha * tp
                    rp = rest[p]
                    d_alpha = tp * fg - rp * keep
                    rest[p] = rp + w * fg

                    d_col0 += w * gc0
                    d_col1 += w * gc1
                    d_col2 += w * gc2
                    d_n0 += w * gn0
                    d_n1 += w * gn1
                    d_n2 += w * gn2
                    d_dist += w * gdist
                    if geometric:
                        dz = w * gd
                        if median_here:
                            dz += grads[p, 7]
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
            row[6], row[7], row[8], row[9], row[10], row[11] = d_col0, d_col1, d_col2, d_n0, d_n1, d_n2
            _ray_gradients(q, b0, b1, b2, s_x, s_y, s_1, m_xx, m_xy, m_x, m_yy, m_y, m_1, row)
            row[24], row[25], row[26] = d_lo, d_hi, d_dist


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


class _CompositeFunction(torch.autograd.Function):
    """Inputs: means2d, conics, opacities, colours, normals, ray coefficients (N, 9),
    ray offsets, depth bounds, plane distances (N,), then the non-differentiable bins, width, height.
    Outputs: the sums colour (3, H, W), depth (1, H, W), normal (3, H, W), alpha (1, H, W), the
    median depth (1, H, W) and the plane distance sum (1, H, W), each its own tensor (no
    slicing, so no slice backward)."""

    @staticmethod
    def forward(
        ctx, means2d, conics, opacities, colors, normals, ray_coeffs, ray_offsets, depth_bounds, distances, bins,
        width, height,
    ):
        dtype = means2d.dtype
        inputs = (means2d, conics, opacities, colors, normals, ray_coeffs, ray_offsets, depth_bounds, distances)
        arrays = [_np(x.to(dtype)) for x in inputs]
        grid = (_np(bins.gauss_ids), _np(bins.tile_offsets), bins.tiles_x, bins.tile_size, width, height)
        np_dtype = arrays[0].dtype
        # Every pixel belongs to one tile, so the kernel writes every entry of these.
        outs = tuple(np.empty((c, height, width), np_dtype) for c in (3, 1, 3, 1, 1, 1))  # colour .. distance
        state = (
            np.empty((height, width), np_dtype),  # final transmittance
            np.empty((height, width), np.int64),  # one past the last contributing list slot
            np.empty((height, width), np.int64),  # list slot of the median Gaussian (-1: none)
        )
        num = arrays[0].shape[0]
        boxes = np.empty((num, 4), np.int64)
        with numba_scheduling(chunksize=_TILES_PER_CHUNK):
            _footprint_kernel(arrays[0], arrays[1], arrays[2], width, height, boxes)
            arrays = (*arrays, boxes)
            _forward_kernel(*arrays, *grid, *outs[:4], outs[5], state[0], outs[4][0], state[1], state[2])
        ctx.arrays, ctx.grid, ctx.state = arrays, grid, state
        ctx.dtype = dtype
        return tuple(torch.from_numpy(o) for o in outs)

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_normal, grad_alpha, grad_median, grad_distance):
        dtype = ctx.dtype
        gauss_ids = ctx.grid[0]
        pair_grads = np.empty((gauss_ids.shape[0], _GRAD_COLS), np.float64)
        output_grads = (_np(g.to(dtype)) for g in
                        (grad_color, grad_depth, grad_normal, grad_alpha, grad_median, grad_distance))
        with numba_scheduling(chunksize=_TILES_PER_CHUNK):
            _backward_kernel(*ctx.arrays, *ctx.grid, *ctx.state, *output_grads, pair_grads)
        grads = np.zeros((ctx.arrays[0].shape[0], _GRAD_COLS), np.float64)
        _sum_pairs(gauss_ids, pair_grads, grads)
        grads = torch.from_numpy(grads).to(dtype)
        d_means2d, d_conics, d_opac, d_colors, d_normals, d_q, d_b, d_bounds, d_dist = torch.split(
            grads, [2, 3, 1, 3, 3, 9, 3, 2, 1], dim=1
        )
        return (d_means2d, d_conics, d_opac[:, 0], d_colors, d_normals, d_q, d_b, d_bounds, d_dist[:, 0],
                None, None, None)


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
    if proj.means2d.device.type != "cpu":
        raise ValueError(f"composite_numba runs on CPU tensors only, got {proj.means2d.device}")
    plane = proj.depths.new_zeros(proj.depths.shape) if distances is None else distances
    color, depth, normal, alpha, median, distance = _CompositeFunction.apply(
        proj.means2d, proj.conics, opacities, colors, proj.normals,
        proj.ray_coeffs.reshape(-1, 9), proj.ray_offsets, proj.depth_bounds, plane, bins, width, height,
    )
    return Composite(color=color, depth=depth, normal=normal, alpha=alpha, median_depth=median,
                     distance=None if distances is None else distance)


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
