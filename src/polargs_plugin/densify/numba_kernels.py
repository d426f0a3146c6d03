"""Numba CPU kernels of the PatchMatch search (the fast path; the torch code is the reference).

``half_step_kernel`` is one call per checkerboard half-step: parallel over the active pixels of one colour, each
pixel builds its candidates (propagated neighbour planes, random refinements), scores them with
the full cost ``S_c + lambda1 S_a + lambda2 S_nd`` and keeps the cheapest, reading only pixels of
the other colour (race-free). No full-map intermediate is materialised. The arithmetic mirrors
patchmatch.py / ncc.py step by step (float64 inside, float32 state), so both backends give the
same costs to ~1e-5 for the same hypotheses and the same random draws.

Array conventions (all C-contiguous numpy views of the torch tensors):

- ``src`` (S, Hs + 4, Ws + 4) float32 source grey images with a 2-pixel zero border;
  ``A`` (S, 3, 3) = ``K_s R K_ref^-1``, ``b`` (S, 3) = ``K_s t`` (float64);
- ``rays`` (3, H, W) ``K_ref^-1 p~``; ``kinv`` (3, 3) float64;
- ``gray`` (H, W) float32 reference grey image; its bilateral windows on the grid
  ``range(-radius, radius + 1, step)`` squared (Q samples, rows outer) are built per pixel inside
  the search kernels (``_reference_window``: normalised weights ``ref_w`` (Q,), ``w (r - mean)``
  ``ref_wc`` (Q,), the variance) instead of being stored, which would take 2 Q floats a pixel;
  ``reference_kernel`` gives them for every pixel as (P, Q) arrays (``ncc_kernel``'s input);
- ``phi`` (H, W) AoLP, ``omega`` (H, W) DoLP weight; ``params`` float64
  ``[lambda1 (0 = off), tau, lambda2 (0 = off), perspective (0/1), lo, hi]``;
- state ``depth`` (H, W), ``normal`` (3, H, W), ``photo`` (H, W), ``total`` (H, W) float32;
  ``active`` (H, W) bool; ``idx`` (N,) int64 flat pixel indices to update.

One *evaluation* is one admissible hypothesis scored against one source over the window, at a
pixel whose reference window has texture (variance >= 1e-5; otherwise S_c = 2 with no sampling).

The kernels are compiled on first use and cached next to this file (``cache=True``): the first
run after a change of this file pays the compilation (~10 s of CPU).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["reference_kernel", "ncc_kernel", "init_kernel", "half_step_kernel"]

_MAX_COST = 2.0
_MIN_VAR = 1e-5
# no "nnan"/"ninf": the admissibility tests rely on isfinite and on inf costs
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
_OPTS = dict(fastmath=_FAST, cache=True, nogil=True)


@nb.njit(**_OPTS)
def _reference_window(gray, y, x, radius, step, sigma_spatial, sigma_color, ref_w, ref_wc):
    """Bilateral weights ``ref_w`` (Q,), ``w (r - mean)`` ``ref_wc`` (Q,) of the reference window
    at pixel (y, x), written in place; returns its variance (float32 precision, as stored).

    Same definition as ncc.reference_windows (replicated border, weights normalised to sum to 1).
    """
    h, w = gray.shape
    n1 = (2 * radius) // step + 1
    centre = gray[y, x]
    total = 0.0
    q = 0
    for jy in range(n1):
        oy = -radius + jy * step
        yy = min(max(y + oy, 0), h - 1)
        for jx in range(n1):
            ox = -radius + jx * step
            d = gray[yy, min(max(x + ox, 0), w - 1)] - centre
            wt = math.exp(-(ox * ox + oy * oy) / (2.0 * sigma_spatial**2) - d * d / (2.0 * sigma_color**2))
            ref_w[q] = wt
            total += wt
            q += 1
    mean = 0.0
    sq = 0.0
    for jy in range(n1):
        yy = min(max(y - radius + jy * step, 0), h - 1)
        for jx in range(n1):
            q = jy * n1 + jx
            r = gray[yy, min(max(x - radius + jx * step, 0), w - 1)]
            wt = ref_w[q] / total
            ref_w[q] = wt
            mean += wt * r
            sq += wt * r * r
    for jy in range(n1):
        yy = min(max(y - radius + jy * step, 0), h - 1)
        for jx in range(n1):
            q = jy * n1 + jx
            ref_wc[q] = ref_w[q] * (gray[yy, min(max(x - radius + jx * step, 0), w - 1)] - mean)
    return np.float64(np.float32(sq - mean * mean))


@nb.njit(parallel=True, **_OPTS)
def reference_kernel(gray, radius, step, sigma_spatial, sigma_color, ref_w, ref_wc, ref_var):
    """Bilateral weights ``ref_w`` (P, Q), ``w (r - mean)`` and variance of every reference window
    (:func:`_reference_window` at each of the P = H * W pixels)."""
    h, w = gray.shape
    for i in nb.prange(h * w):
        ref_var[i] = _reference_window(gray, i // w, i % w, radius, step, sigma_spatial, sigma_color,
                                       ref_w[i], ref_wc[i])


@nb.njit(**_OPTS)
def _ncc(src, s, hx, hy, hz, cxx, cxy, cxz, cyx, cyy, cyz, radius, step, n1, ref_w, ref_wc, rv):
    """Bilateral NCC cost of the homography ``(H p~, H e_x, H e_y)`` against source ``s``, for the
    reference window ``ref_w``, ``ref_wc`` (Q,) of variance ``rv``."""
    width = src.shape[2] - 4
    height = src.shape[1] - 4
    # z is affine in the offset, so its minimum over the window is at a corner sample
    far = -radius + (n1 - 1) * step
    for ex in (-radius, far):
        for ey in (-radius, far):
            if hz + ex * cxz + ey * cyz <= 1e-8:
                return _MAX_COST
    sw = 0.0
    sww = 0.0
    swr = 0.0
    q = 0
    for jy in range(n1):
        oy = -radius + jy * step
        rx = hx + oy * cyx - radius * cxx
        ry = hy + oy * cyy - radius * cxy
        rz = hz + oy * cyz - radius * cxz
        for _ in range(n1):
            inv_z = 1.0 / rz
            # -0.5 pixel centre, +2 zero border; clamping keeps all four taps in the border
            x = min(max(rx * inv_z + 1.5, 0.0), width + 2.0)
            y = min(max(ry * inv_z + 1.5, 0.0), height + 2.0)
            x0 = int(x)
            y0 = int(y)
            fx = x - x0
            fy = y - y0
            a = src[s, y0, x0]
            c = src[s, y0 + 1, x0]
            top = a + fx * (src[s, y0, x0 + 1] - a)
            bot = c + fx * (src[s, y0 + 1, x0 + 1] - c)
            val = top + fy * (bot - top)
            wv = ref_w[q] * val
            sw += wv
            sww += wv * val
            swr += ref_wc[q] * val
            q += 1
            rx += step * cxx
            ry += step * cxy
            rz += step * cxz
    svar = sww - sw * sw
    if svar < _MIN_VAR:
        return _MAX_COST
    cost = 1.0 - swr / math.sqrt(rv * svar)
    return min(max(cost, 0.0), _MAX_COST)


@nb.njit(parallel=True, **_OPTS)
def ncc_kernel(src, A, b, pix, invd, mxy, radius, step, ref_w, ref_wc, ref_var, out):
    """(P, M, S) costs of hypotheses ``(1/d, m_xy)`` (P, M), (P, M, 2) at pixel centres ``pix`` (P, 2)."""
    num_p, num_m = invd.shape
    num_s = src.shape[0]
    n1 = (2 * radius) // step + 1
    for i in nb.prange(num_p):
        for s in range(num_s):
            ax = A[s, 0, 0] * pix[i, 0] + A[s, 0, 1] * pix[i, 1] + A[s, 0, 2]
            ay = A[s, 1, 0] * pix[i, 0] + A[s, 1, 1] * pix[i, 1] + A[s, 1, 2]
            az = A[s, 2, 0] * pix[i, 0] + A[s, 2, 1] * pix[i, 1] + A[s, 2, 2]
            for m in range(num_m):
                k, mx, my = invd[i, m], mxy[i, m, 0], mxy[i, m, 1]
                if ref_var[i] < _MIN_VAR:
                    out[i, m, s] = _MAX_COST
                    continue
                out[i, m, s] = _ncc(
                    src, s, ax + b[s, 0] * k, ay + b[s, 1] * k, az + b[s, 2] * k,
                    A[s, 0, 0] + b[s, 0] * mx, A[s, 1, 0] + b[s, 1] * mx, A[s, 2, 0] + b[s, 2] * mx,
                    A[s, 0, 1] + b[s, 0] * my, A[s, 1, 1] + b[s, 1] * my, A[s, 2, 1] + b[s, 2] * my,
                    radius, step, n1, ref_w[i], ref_wc[i], ref_var[i],
                )


@nb.njit(**_OPTS)
def _photometric(src, A, b, kinv, ax, ay, az, vx, vy, vz, d, nx, ny, nz, radius, step, n1, top_k,
                 ref_w, ref_wc, rv, scratch):
    """S_c of plane (d, n) at a pixel of reference window ``ref_w``, ``ref_wc`` (Q,) and variance
    ``rv``: mean of the ``top_k`` lowest per-source costs."""
    num_s = src.shape[0]
    dpl = -d * (nx * vx + ny * vy + nz * vz)
    # m = -K^-T n / d_plane; only its x, y components enter the homography
    mx = -(kinv[0, 0] * nx + kinv[1, 0] * ny + kinv[2, 0] * nz) / dpl
    my = -(kinv[0, 1] * nx + kinv[1, 1] * ny + kinv[2, 1] * nz) / dpl
    k = 1.0 / d
    for s in range(num_s):
        c = _ncc(
            src, s, ax[s] + b[s, 0] * k, ay[s] + b[s, 1] * k, az[s] + b[s, 2] * k,
            A[s, 0, 0] + b[s, 0] * mx, A[s, 1, 0] + b[s, 1] * mx, A[s, 2, 0] + b[s, 2] * mx,
            A[s, 0, 1] + b[s, 0] * my, A[s, 1, 1] + b[s, 1] * my, A[s, 2, 1] + b[s, 2] * my,
            radius, step, n1, ref_w, ref_wc, rv,
        )
        j = s  # insertion sort: scratch[:s + 1] ascending
        while j > 0 and scratch[j - 1] > c:
            scratch[j] = scratch[j - 1]
            j -= 1
        scratch[j] = c
    acc = 0.0
    for j in range(top_k):
        acc += scratch[j]
    return acc / top_k


@nb.njit(**_OPTS)
def _depth_gradient_normal(depth, rays, active, x, y):
    """Unit normal through the four direct neighbours' depths (facing the camera) and whether it exists."""
    h, w = depth.shape
    if x < 1 or y < 1 or x > w - 2 or y > h - 2:
        return False, 0.0, 0.0, 0.0
    if not (active[y, x - 1] and active[y, x + 1] and active[y - 1, x] and active[y + 1, x]):
        return False, 0.0, 0.0, 0.0
    ux = depth[y, x + 1] * rays[0, y, x + 1] - depth[y, x - 1] * rays[0, y, x - 1]
    uy = depth[y, x + 1] * rays[1, y, x + 1] - depth[y, x - 1] * rays[1, y, x - 1]
    uz = depth[y, x + 1] * rays[2, y, x + 1] - depth[y, x - 1] * rays[2, y, x - 1]
    vx = depth[y + 1, x] * rays[0, y + 1, x] - depth[y - 1, x] * rays[0, y - 1, x]
    vy = depth[y + 1, x] * rays[1, y + 1, x] - depth[y - 1, x] * rays[1, y - 1, x]
    vz = depth[y + 1, x] * rays[2, y + 1, x] - depth[y - 1, x] * rays[2, y - 1, x]
    gx = vy * uz - vz * uy
    gy = vz * ux - vx * uz
    gz = vx * uy - vy * ux
    norm = max(math.sqrt(gx * gx + gy * gy + gz * gz), 1e-12)
    return True, gx / norm, gy / norm, gz / norm


@nb.njit(**_OPTS)
def _prior(nx, ny, nz, vx, vy, vz, phi, omega, params, has_dg, gx, gy, gz):
    """lambda1 S_a + lambda2 S_nd of normal n at a pixel with ray v."""
    out = 0.0
    if params[0] > 0.0:
        if params[3] > 0.0:
            alpha = math.atan2(vy * nz - vz * ny, vz * nx - vx * nz)
        else:
            alpha = math.atan2(-ny, nx)
        # distance to the nearest of the four candidates phi + k pi/2
        quarter = 0.5 * math.pi
        t = alpha - phi
        t -= math.floor(t / quarter) * quarter
        near = min(t, quarter - t)
        out += params[0] * omega * math.exp(near * near / params[1])
    if params[2] > 0.0 and has_dg:
        out += params[2] * (1.0 - (gx * nx + gy * ny + gz * nz))
    return out


@nb.njit(**_OPTS)
def _admissible(d, nx, ny, nz, vx, vy, vz, lo, hi):
    return math.isfinite(d) and d >= lo and d <= hi and (nx * vx + ny * vy + nz * vz) < -1e-3


@nb.njit(**_OPTS)
def _pixel_setup(src, A, x, y):
    """Per-source ``A p~`` of pixel (x, y) (pixel centre at +0.5)."""
    num_s = src.shape[0]
    ax = np.empty(num_s)
    ay = np.empty(num_s)
    az = np.empty(num_s)
    px = x + 0.5
    py = y + 0.5
    for s in range(num_s):
        ax[s] = A[s, 0, 0] * px + A[s, 0, 1] * py + A[s, 0, 2]
        ay[s] = A[s, 1, 0] * px + A[s, 1, 1] * py + A[s, 1, 2]
        az[s] = A[s, 2, 0] * px + A[s, 2, 1] * py + A[s, 2, 2]
    return ax, ay, az


@nb.njit(**_OPTS)
def _pixel_context(i, src, A, rays, gray, radius, step, n1, sigma_spatial, sigma_color, depth, active):
    """What both search kernels need of the flat pixel ``i`` before scoring its hypotheses.

    Returns ``(y, x, vx, vy, vz, ref_w, ref_wc, rv, textured, ax, ay, az, scratch, has_dg, gx, gy,
    gz)``: the pixel, its ray, its reference window (built per pixel and call rather than stored:
    2 Q floats a pixel) with its variance and whether that counts as texture, the per-source
    ``A p~``, a scratch array of one cost per source, and the depth-gradient normal.
    """
    w = depth.shape[1]
    y, x = i // w, i % w
    vx, vy, vz = rays[0, y, x], rays[1, y, x], rays[2, y, x]
    ref_w, ref_wc = np.empty(n1 * n1, np.float32), np.empty(n1 * n1, np.float32)
    rv = _reference_window(gray, y, x, radius, step, sigma_spatial, sigma_color, ref_w, ref_wc)
    ax, ay, az = _pixel_setup(src, A, x, y)
    scratch = np.empty(src.shape[0])
    has_dg, gx, gy, gz = _depth_gradient_normal(depth, rays, active, x, y)
    return y, x, vx, vy, vz, ref_w, ref_wc, rv, rv >= _MIN_VAR, ax, ay, az, scratch, has_dg, gx, gy, gz


@nb.njit(parallel=True, **_OPTS)
def init_kernel(idx, cand_d, cand_n, src, A, b, kinv, rays, radius, step, top_k, gray, sigma_spatial,
                sigma_color, phi, omega, params, active, depth, out_depth, out_normal, out_photo, out_total,
                best_total):
    """Score the M initial hypotheses ``cand_d`` (M, H, W), ``cand_n`` (M, 3, H, W) at ``idx``.

    Reads ``depth`` (for S_nd), writes the cheapest admissible hypothesis into the ``out_*``
    arrays (copies of the state, so that neighbours see the old depths) where it costs less than
    ``best_total`` (H, W) float64 holds, and lowers that: called group after group with one
    ``best_total`` (inf at first), it keeps the first cheapest of all groups, compared at the
    precision of the costs rather than of the float32 state. Returns the number of evaluations.
    """
    num_m = cand_d.shape[0]
    num_s = src.shape[0]
    n1 = (2 * radius) // step + 1
    lo, hi = params[4], params[5]
    count = 0
    for j in nb.prange(idx.shape[0]):
        (y, x, vx, vy, vz, ref_w, ref_wc, rv, textured, ax, ay, az, scratch, has_dg, gx, gy,
         gz) = _pixel_context(idx[j], src, A, rays, gray, radius, step, n1, sigma_spatial, sigma_color,
                              depth, active)
        best = best_total[y, x]
        best_m = -1
        best_photo = _MAX_COST
        for m in range(num_m):
            d = cand_d[m, y, x]
            nx, ny, nz = cand_n[m, 0, y, x], cand_n[m, 1, y, x], cand_n[m, 2, y, x]
            if not _admissible(d, nx, ny, nz, vx, vy, vz, lo, hi):
                continue
            c_photo = _MAX_COST
            if textured:
                c_photo = _photometric(src, A, b, kinv, ax, ay, az, vx, vy, vz, d, nx, ny, nz, radius,
                                       step, n1, top_k, ref_w, ref_wc, rv, scratch)
                count += num_s
            c = c_photo + _prior(nx, ny, nz, vx, vy, vz, phi[y, x], omega[y, x], params, has_dg, gx, gy, gz)
            if c < best:
                best, best_m, best_photo = c, m, c_photo
        if best_m >= 0:
            out_depth[y, x] = cand_d[best_m, y, x]
            for a in range(3):
                out_normal[a, y, x] = cand_n[best_m, a, y, x]
            out_photo[y, x] = best_photo
            out_total[y, x] = best
            best_total[y, x] = best
    return count



@nb.njit(parallel=True, **_OPTS)
def half_step_kernel(idx, src, A, b, kinv, rays, radius, step, top_k, gray, sigma_spatial, sigma_color, phi,
                     omega, params, active, dists, rel, ang, uni, noise, depth, normal, photo, total):
    """One checkerboard half-step over the pixels ``idx`` (all of one colour), in place.

    Candidates after the current plane (whose total is re-scored with the current neighbours):
    per direction (+x, -x, +y, -y) the neighbour at a distance in ``dists`` with the lowest
    total, its plane re-intersected with the pixel ray; then ``(d_a, n)``, ``(d, n_a)``,
    ``(d_b, n_b)`` with ``d_k = d (1 + rel (2 uni[k] - 1))`` and
    ``n_k = normalize(n + ang noise[k])``. Returns the number of evaluations.
    """
    h, w = depth.shape
    num_s = src.shape[0]
    n1 = (2 * radius) // step + 1
    lo, hi = params[4], params[5]
    count = 0
    for j in nb.prange(idx.shape[0]):
        (y, x, vx, vy, vz, ref_w, ref_wc, rv, textured, ax, ay, az, scratch, has_dg, gx, gy,
         gz) = _pixel_context(idx[j], src, A, rays, gray, radius, step, n1, sigma_spatial, sigma_color,
                              depth, active)
        d0 = np.float64(depth[y, x])
        n0x, n0y, n0z = np.float64(normal[0, y, x]), np.float64(normal[1, y, x]), np.float64(normal[2, y, x])
        best_photo = np.float64(photo[y, x])
        best = best_photo + _prior(n0x, n0y, n0z, vx, vy, vz, phi[y, x], omega[y, x], params, has_dg, gx, gy, gz)
        best_d, best_nx, best_ny, best_nz = d0, n0x, n0y, n0z
        for cand in range(7):
            if cand < 4:  # propagation from direction (+x, -x, +y, -y)
                dx = 1 if cand == 0 else (-1 if cand == 1 else 0)
                dy = 1 if cand == 2 else (-1 if cand == 3 else 0)
                pick = np.inf
                qx, qy = -1, -1
                for k in dists:
                    xx, yy = x + k * dx, y + k * dy
                    if 0 <= xx < w and 0 <= yy < h and active[yy, xx] and total[yy, xx] < pick:
                        pick, qx, qy = total[yy, xx], xx, yy
                if qx < 0:
                    continue
                nx, ny, nz = normal[0, qy, qx], normal[1, qy, qx], normal[2, qy, qx]
                dpl = -depth[qy, qx] * (nx * rays[0, qy, qx] + ny * rays[1, qy, qx] + nz * rays[2, qy, qx])
                d = -dpl / (nx * vx + ny * vy + nz * vz)
            else:
                r = cand - 4  # 0: (d_a, n), 1: (d, n_a), 2: (d_b, n_b)
                ku = 1 if r == 2 else 0
                d = d0 if r == 1 else d0 * (1.0 + rel * (2.0 * uni[ku, y, x] - 1.0))
                if r == 0:
                    nx, ny, nz = n0x, n0y, n0z
                else:
                    kn = r - 1
                    nx = n0x + noise[kn, 0, y, x] * ang
                    ny = n0y + noise[kn, 1, y, x] * ang
                    nz = n0z + noise[kn, 2, y, x] * ang
                    norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
                    nx, ny, nz = nx / norm, ny / norm, nz / norm
            if not _admissible(d, nx, ny, nz, vx, vy, vz, lo, hi):
                continue
            c_photo = _MAX_COST
            if textured:
                c_photo = _photometric(src, A, b, kinv, ax, ay, az, vx, vy, vz, d, nx, ny, nz, radius,
                                       step, n1, top_k, ref_w, ref_wc, rv, scratch)
                count += num_s
            c = c_photo + _prior(nx, ny, nz, vx, vy, vz, phi[y, x], omega[y, x], params, has_dg, gx, gy, gz)
            if c < best:
                best, best_photo = c, c_photo
                best_d, best_nx, best_ny, best_nz = d, nx, ny, nz
        depth[y, x] = best_d
        normal[0, y, x] = best_nx
        normal[1, y, x] = best_ny
        normal[2, y, x] = best_nz
        photo[y, x] = best_photo
        total[y, x] = best
    return count

