"""Compiled CPU projection (Numba): :func:`~.projection.project_gaussians` and the SH colour
:func:`~polargs_plugin.geometry.eval_sh` as one forward kernel and one hand-written backward kernel.

Same rules and outputs as the torch functions (which stay the reference and the CUDA path):
near/far culling with a harmless z = 1 for culled Gaussians, the 1.3x field-of-view clamp of
the EWA Jacobian, the ``eps2d`` dilation, the opacity-aware extents, the +-5 sigma_z depth clamp,
the shortest-axis normal flipped to face the camera
(:func:`~polargs_plugin.geometry.shortest_axis_normals`), the SH basis of
:func:`~polargs_plugin.geometry.eval_sh` (+0.5, clamped at 0). The constants come from
:mod:`.projection` and :mod:`polargs_plugin.geometry`; tests/test_projection_numba.py checks
values and gradients against the torch functions, ties and culled Gaussians included.

Everything is computed in float64 inside the kernels and stored in the inputs' dtype. The
camera (K, world_to_camera) gets no gradient here: :func:`project_numba` is only used when
neither requires one.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.geometry import SH_C0, SH_C1, SH_C2, SH_C3, sh_degree_from_coeffs
from polargs_plugin.threads import numba_scheduling

from .projection import ALPHA_MIN, DEFAULT_EPS2D, DEPTH_CLAMP_SIGMAS, EXTENT_SLACK, FOV_CLAMP, Projection

__all__ = ["project_numba"]

_CHUNK = 64  # Gaussians per parallel work item (scratch matrices are allocated once per item)
_LOG_ALPHA_MIN = math.log(ALPHA_MIN)

C20, C21, C22, C23, C24 = SH_C2
C30, C31, C32, C33, C34, C35, C36 = SH_C3


@numba.njit(inline="always")
def _rotmat(q, i, rot):
    """Rotation of the normalised quaternion q[i] (wxyz) into ``rot``; returns w, x, y, z, |q|."""
    q0, q1, q2, q3 = float(q[i, 0]), float(q[i, 1]), float(q[i, 2]), float(q[i, 3])
    nrm = max(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12)
    w, x, y, z = q0 / nrm, q1 / nrm, q2 / nrm, q3 / nrm
    rot[0, 0] = 1 - 2 * (y * y + z * z)
    rot[0, 1] = 2 * (x * y - w * z)
    rot[0, 2] = 2 * (x * z + w * y)
    rot[1, 0] = 2 * (x * y + w * z)
    rot[1, 1] = 1 - 2 * (x * x + z * z)
    rot[1, 2] = 2 * (y * z - w * x)
    rot[2, 0] = 2 * (x * z - w * y)
    rot[2, 1] = 2 * (y * z + w * x)
    rot[2, 2] = 1 - 2 * (x * x + y * y)
    return w, x, y, z, nrm


@numba.njit(inline="always")
def _geometry(i, means, quats, scales, w2c, rot, axes, cov):
    """Camera-frame mean, axes (R_w2c R_q, columns) and covariance of Gaussian i; returns
    (x, y, z, quaternion w, x, y, z, |q|, index of the shortest axis)."""
    m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
    x = w2c[0, 0] * m0 + w2c[0, 1] * m1 + w2c[0, 2] * m2 + w2c[0, 3]
    y = w2c[1, 0] * m0 + w2c[1, 1] * m1 + w2c[1, 2] * m2 + w2c[1, 3]
    z = w2c[2, 0] * m0 + w2c[2, 1] * m1 + w2c[2, 2] * m2 + w2c[2, 3]
    qw, qx, qy, qz, nrm = _rotmat(quats, i, rot)
    for r in range(3):
        for c in range(3):
            axes[r, c] = w2c[r, 0] * rot[0, c] + w2c[r, 1] * rot[1, c] + w2c[r, 2] * rot[2, c]
    s0, s1, s2 = float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2])
    v0, v1, v2 = s0 * s0, s1 * s1, s2 * s2
    for r in range(3):
        for c in range(3):
            cov[r, c] = axes[r, 0] * v0 * axes[c, 0] + axes[r, 1] * v1 * axes[c, 1] + axes[r, 2] * v2 * axes[c, 2]
    # argmin with the first index on ties, as torch.argmin / torch.min(dim) on CPU.
    k = 0
    if s1 < s0:
        k = 1
    if s2 < (s1 if k == 1 else s0):
        k = 2
    return x, y, z, qw, qx, qy, qz, nrm, k


@numba.njit(inline="always")
def _sh_basis(degree, dx, dy, dz, basis):
    """Real SH basis of :func:`~polargs_plugin.geometry.eval_sh` at the unit direction (dx, dy, dz)."""
    basis[0] = SH_C0
    if degree >= 1:
        basis[1] = -SH_C1 * dy
        basis[2] = SH_C1 * dz
        basis[3] = -SH_C1 * dx
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = dx * dx, dy * dy, dz * dz, dx * dy, dy * dz, dx * dz
        basis[4] = C20 * xy
        basis[5] = C21 * yz
        basis[6] = C22 * (2 * zz - xx - yy)
        basis[7] = C23 * xz
        basis[8] = C24 * (xx - yy)
        if degree >= 3:
            basis[9] = C30 * dy * (3 * xx - yy)
            basis[10] = C31 * xy * dz
            basis[11] = C32 * dy * (4 * zz - xx - yy)
            basis[12] = C33 * dz * (2 * zz - 3 * xx - 3 * yy)
            basis[13] = C34 * dx * (4 * zz - xx - yy)
            basis[14] = C35 * dz * (xx - yy)
            basis[15] = C36 * dx * (xx - 3 * yy)


@numba.njit(inline="always")
def _sh_basis_grad(degree, x, y, z, gb):
    """d(sum_k gb_k Y_k)/d(x, y, z) at the unit direction (x, y, z)."""
    gx = -SH_C1 * gb[3]
    gy = -SH_C1 * gb[1]
    gz = SH_C1 * gb[2]
    if degree >= 2:
        gx += C20 * y * gb[4] - 2 * C22 * x * gb[6] + C23 * z * gb[7] + 2 * C24 * x * gb[8]
        gy += C20 * x * gb[4] + C21 * z * gb[5] - 2 * C22 * y * gb[6] - 2 * C24 * y * gb[8]
        gz += C21 * y * gb[5] + 4 * C22 * z * gb[6] + C23 * x * gb[7]
        if degree >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (
                C30 * 6 * x * y * gb[9] + C31 * y * z * gb[10] - 2 * C32 * x * y * gb[11]
                - 6 * C33 * x * z * gb[12] + C34 * (4 * zz - 3 * xx - yy) * gb[13]
                + 2 * C35 * x * z * gb[14] + C36 * (3 * xx - 3 * yy) * gb[15]
            )
            gy += (
                C30 * (3 * xx - 3 * yy) * gb[9] + C31 * x * z * gb[10] + C32 * (4 * zz - xx - 3 * yy) * gb[11]
                - 6 * C33 * y * z * gb[12] - 2 * C34 * x * y * gb[13] - 2 * C35 * y * z * gb[14]
                - 6 * C36 * x * y * gb[15]
            )
            gz += (
                C31 * x * y * gb[10] + 8 * C32 * y * z * gb[11] + C33 * (6 * zz - 3 * xx - 3 * yy) * gb[12]
                + 8 * C34 * x * z * gb[13] + C35 * (xx - yy) * gb[14]
            )
    return gx, gy, gz


@numba.njit(inline="always")
def _clamp_grad(v, lo, hi):
    """d min(max(v, lo), hi) / dv with torch's half-and-half rule at ties."""
    f = 1.0 if v > lo else (0.5 if v == lo else 0.0)
    r = max(v, lo)
    return f * (1.0 if r < hi else (0.5 if r == hi else 0.0))


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _forward_kernel(
    means, quats, scales, opacities, colors, degree, w2c, kmat, kinv, cam_center,
    width, height, near, far, eps2d,
    means2d, conics, depths, colors_out, normals, ray_coeffs, ray_offsets, depth_bounds, extents,
):
    n = means.shape[0]
    fx, skew, cx, fy, cy = kmat[0, 0], kmat[0, 1], kmat[0, 2], kmat[1, 1], kmat[1, 2]
    lim_x_hi, lim_x_lo = FOV_CLAMP * (width - cx) / fx, -FOV_CLAMP * cx / fx
    lim_y_hi, lim_y_lo = FOV_CLAMP * (height - cy) / fy, -FOV_CLAMP * cy / fy
    num_coeffs = colors.shape[1] if degree >= 0 else 0
    for chunk in numba.prange((n + _CHUNK - 1) // _CHUNK):
        rot = np.empty((3, 3))
        axes = np.empty((3, 3))
        cov = np.empty((3, 3))
        basis = np.empty(16)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            x, y, z, _, _, _, _, _, k = _geometry(i, means, quats, scales, w2c, rot, axes, cov)
            in_range = z >= near and z <= far
            zs = z if in_range else 1.0
            inv_z = 1.0 / zs
            means2d[i, 0] = (fx * x + skew * y) / zs + cx
            means2d[i, 1] = fy * y / zs + cy
            depths[i] = zs
            xz = min(max(x / zs, lim_x_lo), lim_x_hi)
            yz = min(max(y / zs, lim_y_lo), lim_y_hi)
            j00, j01, j02 = fx * inv_z, skew * inv_z, -(fx * xz + skew * yz) * inv_z
            j11, j12 = fy * inv_z, -fy * yz * inv_z
            # rows of J C
            t00 = j00 * cov[0, 0] + j01 * cov[1, 0] + j02 * cov[2, 0]
            t01 = j00 * cov[0, 1] + j01 * cov[1, 1] + j02 * cov[2, 1]
            t02 = j00 * cov[0, 2] + j01 * cov[1, 2] + j02 * cov[2, 2]
            t11 = j11 * cov[1, 1] + j12 * cov[2, 1]
            t12 = j11 * cov[1, 2] + j12 * cov[2, 2]
            a = t00 * j00 + t01 * j01 + t02 * j02 + eps2d
            b = t01 * j11 + t02 * j12
            c = t11 * j11 + t12 * j12 + eps2d
            det = a * c - b * b
            conics[i, 0] = c / det
            conics[i, 1] = -b / det
            conics[i, 2] = a / det

            log_ratio = max(math.log(max(float(opacities[i]), 1e-30)) - _LOG_ALPHA_MIN, 0.0)
            if in_range and log_ratio > 0 and det > 0:
                extents[i, 0] = (1 + EXTENT_SLACK) * math.sqrt(2.0 * log_ratio * a)
                extents[i, 1] = (1 + EXTENT_SLACK) * math.sqrt(2.0 * log_ratio * c)
            else:
                extents[i, 0] = 0.0
                extents[i, 1] = 0.0

            # shortest_axis_normals: axis k, flipped so that n . mean_cam <= 0.
            facing = -1.0 if axes[0, k] * x + axes[1, k] * y + axes[2, k] * z > 0 else 1.0
            normals[i, 0] = axes[0, k] * facing
            normals[i, 1] = axes[1, k] * facing
            normals[i, 2] = axes[2, k] * facing

            s_min = float(scales[i, k])
            mx, my, mz = (x, y, z) if in_range else (1.0, 1.0, 1.0)
            for r in range(3):
                rel = s_min / float(scales[i, r])
                ar0, ar1, ar2 = axes[0, r] * rel, axes[1, r] * rel, axes[2, r] * rel
                for c2 in range(3):
                    ray_coeffs[i, r, c2] = ar0 * kinv[0, c2] + ar1 * kinv[1, c2] + ar2 * kinv[2, c2]
                ray_offsets[i, r] = ar0 * mx + ar1 * my + ar2 * mz
            sigma_z = math.sqrt(max(cov[2, 2], 1e-30))
            depth_bounds[i, 0] = zs - DEPTH_CLAMP_SIGMAS * sigma_z
            depth_bounds[i, 1] = zs + DEPTH_CLAMP_SIGMAS * sigma_z

            if degree < 0:
                for ch in range(3):
                    colors_out[i, ch] = colors[i, 0, ch]
                continue
            dx = float(means[i, 0]) - cam_center[0]
            dy = float(means[i, 1]) - cam_center[1]
            dz = float(means[i, 2]) - cam_center[2]
            dn = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            _sh_basis(degree, dx / dn, dy / dn, dz / dn, basis)
            for ch in range(3):
                v = 0.0
                for kk in range(num_coeffs):
                    v += basis[kk] * colors[i, kk, ch]
                colors_out[i, ch] = max(v + 0.5, 0.0)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _backward_kernel(
    means, quats, scales, colors, degree, w2c, kmat, kinv, cam_center, width, height, near, far, eps2d,
    g_means2d, g_conics, g_depths, g_colors, g_normals, g_ray_coeffs, g_ray_offsets, g_depth_bounds,
    d_means, d_quats, d_scales, d_colors,
):
    n = means.shape[0]
    fx, skew, cx, fy, cy = kmat[0, 0], kmat[0, 1], kmat[0, 2], kmat[1, 1], kmat[1, 2]
    lim_x_hi, lim_x_lo = FOV_CLAMP * (width - cx) / fx, -FOV_CLAMP * cx / fx
    lim_y_hi, lim_y_lo = FOV_CLAMP * (height - cy) / fy, -FOV_CLAMP * cy / fy
    num_coeffs = colors.shape[1] if degree >= 0 else 0
    for chunk in numba.prange((n + _CHUNK - 1) // _CHUNK):
        rot = np.empty((3, 3))
        axes = np.empty((3, 3))
        cov = np.empty((3, 3))
        g_axes = np.empty((3, 3))
        g_cov = np.empty((3, 3))
        g_rot = np.empty((3, 3))
        basis = np.empty(16)
        g_basis = np.empty(16)
        g_s = np.empty(3)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            x, y, z, qw, qx, qy, qz, qn, k = _geometry(i, means, quats, scales, w2c, rot, axes, cov)
            s0, s1, s2 = float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2])
            in_range = z >= near and z <= far
            zs = z if in_range else 1.0
            inv_z = 1.0 / zs
            tx, ty = x / zs, y / zs
            xz = min(max(tx, lim_x_lo), lim_x_hi)
            yz = min(max(ty, lim_y_lo), lim_y_hi)
            j00, j01, j02 = fx * inv_z, skew * inv_z, -(fx * xz + skew * yz) * inv_z
            j11, j12 = fy * inv_z, -fy * yz * inv_z
            t00 = j00 * cov[0, 0] + j01 * cov[1, 0] + j02 * cov[2, 0]
            t01 = j00 * cov[0, 1] + j01 * cov[1, 1] + j02 * cov[2, 1]
            t02 = j00 * cov[0, 2] + j01 * cov[1, 2] + j02 * cov[2, 2]
            t11 = j11 * cov[1, 1] + j12 * cov[2, 1]
            t12 = j11 * cov[1, 2] + j12 * cov[2, 2]
            a = t00 * j00 + t01 * j01 + t02 * j02 + eps2d
            b = t01 * j11 + t02 * j12
            c = t11 * j11 + t12 * j12 + eps2d
            det = a * c - b * b

            g_x = g_y = g_z_safe = 0.0
            for r in range(3):
                for c2 in range(3):
                    g_axes[r, c2] = 0.0
                    g_cov[r, c2] = 0.0
            g_s[0] = g_s[1] = g_s[2] = 0.0

            # means2d and depths
            gu, gv = float(g_means2d[i, 0]), float(g_means2d[i, 1])
            g_x += gu * fx / zs
            g_y += gu * skew / zs + gv * fy / zs
            g_z_safe -= (gu * (fx * x + skew * y) + gv * fy * y) / (zs * zs)
            g_z_safe += float(g_depths[i])

            # conics -> a, b, c
            gc0, gc1, gc2 = float(g_conics[i, 0]), float(g_conics[i, 1]), float(g_conics[i, 2])
            g_det = -(gc0 * c - gc1 * b + gc2 * a) / (det * det)
            g_a = gc2 / det + g_det * c
            g_c = gc0 / det + g_det * a
            g_b = -gc1 / det - 2.0 * b * g_det
            # cov2d = J C J^T with G = [[g_a, g_b], [0, g_c]]: dJ = (G + G^T) J C, dC = J^T G J.
            h00, h01, h11 = 2.0 * g_a, g_b, 2.0 * g_c
            # J C rows: (t00, t01, t02), (t10, t11, t12) with t10 = j11 C10 + j12 C20
            t10 = j11 * cov[1, 0] + j12 * cov[2, 0]
            gj00 = h00 * t00 + h01 * t10
            gj01 = h00 * t01 + h01 * t11
            gj02 = h00 * t02 + h01 * t12
            gj11 = h01 * t01 + h11 * t11
            gj12 = h01 * t02 + h11 * t12
            jrow0 = (j00, j01, j02)
            jrow1 = (0.0, j11, j12)
            for r in range(3):
                for c2 in range(3):
                    g_cov[r, c2] += (
                        jrow0[r] * (g_a * jrow0[c2] + g_b * jrow1[c2]) + jrow1[r] * g_c * jrow1[c2]
                    )
            # J -> inv_z, xz, yz
            g_inv_z = gj00 * fx + gj01 * skew - gj02 * (fx * xz + skew * yz) + gj11 * fy - gj12 * fy * yz
            g_xz = -gj02 * fx * inv_z
            g_yz = -(gj02 * skew + gj12 * fy) * inv_z
            g_z_safe -= g_inv_z * inv_z * inv_z
            g_tx = g_xz * _clamp_grad(tx, lim_x_lo, lim_x_hi)
            g_ty = g_yz * _clamp_grad(ty, lim_y_lo, lim_y_hi)
            g_x += g_tx / zs
            g_y += g_ty / zs
            g_z_safe -= (g_tx * x + g_ty * y) / (zs * zs)

            # depth bounds
            gb0, gb1 = float(g_depth_bounds[i, 0]), float(g_depth_bounds[i, 1])
            g_z_safe += gb0 + gb1
            if cov[2, 2] >= 1e-30:
                g_cov[2, 2] += DEPTH_CLAMP_SIGMAS * (gb1 - gb0) * 0.5 / math.sqrt(cov[2, 2])

            # normals
            facing = -1.0 if axes[0, k] * x + axes[1, k] * y + axes[2, k] * z > 0 else 1.0
            for r in range(3):
                g_axes[r, k] += facing * float(g_normals[i, r])

            # ray coefficients / offsets: M[r, :] = rel_r axes[:, r], Q = M K^-1, b = M mean_safe
            s_min = float(scales[i, k])
            mx, my, mz = (x, y, z) if in_range else (1.0, 1.0, 1.0)
            g_smin = 0.0
            g_mx = g_my = g_mz = 0.0
            for r in range(3):
                s_r = float(scales[i, r])
                rel = s_min / s_r
                go = float(g_ray_offsets[i, r])
                gm0 = go * mx
                gm1 = go * my
                gm2 = go * mz
                for c2 in range(3):
                    gq = float(g_ray_coeffs[i, r, c2])
                    gm0 += gq * kinv[0, c2]
                    gm1 += gq * kinv[1, c2]
                    gm2 += gq * kinv[2, c2]
                g_mx += go * rel * axes[0, r]
                g_my += go * rel * axes[1, r]
                g_mz += go * rel * axes[2, r]
                g_axes[0, r] += gm0 * rel
                g_axes[1, r] += gm1 * rel
                g_axes[2, r] += gm2 * rel
                g_rel = gm0 * axes[0, r] + gm1 * axes[1, r] + gm2 * axes[2, r]
                g_smin += g_rel / s_r
                g_s[r] -= g_rel * s_min / (s_r * s_r)
            g_s[k] += g_smin
            if in_range:
                g_x += g_mx
                g_y += g_my
                g_z_safe += g_mz

            # covariance C = axes diag(s^2) axes^T: d axes[:, j] = (G + G^T) axes[:, j] s_j^2,
            # d s_j = 2 s_j axes[:, j]^T G axes[:, j].
            sv = (s0, s1, s2)
            for j in range(3):
                sj = sv[j]
                quad = 0.0
                for r in range(3):
                    sym = 0.0
                    for c2 in range(3):
                        sym += (g_cov[r, c2] + g_cov[c2, r]) * axes[c2, j]
                    g_axes[r, j] += sym * sj * sj
                    quad += axes[r, j] * sym
                g_s[j] += quad * sj  # 2 s_j a_j^T G a_j
            for j in range(3):
                d_scales[i, j] = g_s[j]

            # camera-frame mean -> world mean
            g_z = g_z_safe if in_range else 0.0
            gm_w0 = w2c[0, 0] * g_x + w2c[1, 0] * g_y + w2c[2, 0] * g_z
            gm_w1 = w2c[0, 1] * g_x + w2c[1, 1] * g_y + w2c[2, 1] * g_z
            gm_w2 = w2c[0, 2] * g_x + w2c[1, 2] * g_y + w2c[2, 2] * g_z

            # axes = R_w2c rot -> rot -> normalised quaternion -> quaternion
            for r in range(3):
                for c2 in range(3):
                    g_rot[r, c2] = w2c[0, r] * g_axes[0, c2] + w2c[1, r] * g_axes[1, c2] + w2c[2, r] * g_axes[2, c2]
            w, xq, yq, zq = qw, qx, qy, qz
            g00, g01, g02 = g_rot[0, 0], g_rot[0, 1], g_rot[0, 2]
            g10, g11, g12 = g_rot[1, 0], g_rot[1, 1], g_rot[1, 2]
            g20, g21, g22 = g_rot[2, 0], g_rot[2, 1], g_rot[2, 2]
            gw = 2 * (-zq * g01 + yq * g02 + zq * g10 - xq * g12 - yq * g20 + xq * g21)
            gx = 2 * (yq * g01 + zq * g02 + yq * g10 - 2 * xq * g11 - w * g12 + zq * g20 + w * g21 - 2 * xq * g22)
            gy = 2 * (-2 * yq * g00 + xq * g01 + w * g02 + xq * g10 + zq * g12 - w * g20 + zq * g21 - 2 * yq * g22)
            gz = 2 * (-2 * zq * g00 - w * g01 + xq * g02 + w * g10 - 2 * zq * g11 + yq * g12 + xq * g20 + yq * g21)
            dot = w * gw + xq * gx + yq * gy + zq * gz
            raw_norm = math.sqrt(
                float(quats[i, 0]) ** 2 + float(quats[i, 1]) ** 2 + float(quats[i, 2]) ** 2 + float(quats[i, 3]) ** 2
            )
            if raw_norm > 1e-12:
                d_quats[i, 0] = (gw - w * dot) / qn
                d_quats[i, 1] = (gx - xq * dot) / qn
                d_quats[i, 2] = (gy - yq * dot) / qn
                d_quats[i, 3] = (gz - zq * dot) / qn
            else:
                d_quats[i, 0] = gw / qn
                d_quats[i, 1] = gx / qn
                d_quats[i, 2] = gy / qn
                d_quats[i, 3] = gz / qn

            # colours
            if degree < 0:
                for ch in range(3):
                    d_colors[i, 0, ch] = g_colors[i, ch]
            else:
                dx = float(means[i, 0]) - cam_center[0]
                dy = float(means[i, 1]) - cam_center[1]
                dz = float(means[i, 2]) - cam_center[2]
                d_len = math.sqrt(dx * dx + dy * dy + dz * dz)
                dn = max(d_len, 1e-12)
                ux, uy, uz = dx / dn, dy / dn, dz / dn
                _sh_basis(degree, ux, uy, uz, basis)
                for kk in range(num_coeffs):
                    g_basis[kk] = 0.0
                for ch in range(3):
                    v = 0.0
                    for kk in range(num_coeffs):
                        v += basis[kk] * colors[i, kk, ch]
                    g_val = float(g_colors[i, ch]) if v + 0.5 >= 0.0 else 0.0
                    for kk in range(num_coeffs):
                        d_colors[i, kk, ch] = basis[kk] * g_val
                        g_basis[kk] += colors[i, kk, ch] * g_val
                if degree >= 1:
                    gux, guy, guz = _sh_basis_grad(degree, ux, uy, uz, g_basis)
                    if d_len > 1e-12:
                        udot = ux * gux + uy * guy + uz * guz
                        gm_w0 += (gux - ux * udot) / dn
                        gm_w1 += (guy - uy * udot) / dn
                        gm_w2 += (guz - uz * udot) / dn
                    else:
                        gm_w0 += gux / dn
                        gm_w1 += guy / dn
                        gm_w2 += guz / dn
            d_means[i, 0] = gm_w0
            d_means[i, 1] = gm_w1
            d_means[i, 2] = gm_w2


def _camera_arrays(K: Tensor, world_to_camera: Tensor, dtype: torch.dtype):
    """K, K^-1, world_to_camera and the camera centre as float64 arrays, after rounding the
    camera to ``dtype`` as the torch path does."""
    kmat = K.detach().to(dtype).to(torch.float64).cpu().numpy()
    w2c = world_to_camera.detach().to(dtype).to(torch.float64).cpu().numpy()
    kinv = np.linalg.inv(kmat)
    cam_center = -w2c[:3, :3].T @ w2c[:3, 3]
    return np.ascontiguousarray(kmat), np.ascontiguousarray(w2c), kinv, cam_center


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _ProjectFunction(torch.autograd.Function):
    """Inputs: means, quats, scales, colours (N, K, 3) SH (``degree`` >= 0) or (N, 1, 3) RGB
    (``degree`` = -1), then the non-differentiable opacities and camera. Outputs: means2d,
    conics, depths, colours (N, 3), normals, ray_coeffs, ray_offsets, depth_bounds, extents
    (not differentiable)."""

    @staticmethod
    def forward(ctx, means, quats, scales, colors, opacities, degree, camera, width, height, near, far, eps2d):
        n, dtype = means.shape[0], means.dtype
        arrays = tuple(_np(t) for t in (means, quats, scales, colors))
        outs = (
            torch.empty(n, 2, dtype=dtype),
            torch.empty(n, 3, dtype=dtype),
            torch.empty(n, dtype=dtype),
            torch.empty(n, 3, dtype=dtype),
            torch.empty(n, 3, dtype=dtype),
            torch.empty(n, 3, 3, dtype=dtype),
            torch.empty(n, 3, dtype=dtype),
            torch.empty(n, 2, dtype=dtype),
            torch.empty(n, 2, dtype=dtype),
        )
        scalars = (float(width), float(height), float(near), float(far), float(eps2d))
        with numba_scheduling():
            kmat, w2c, kinv, cam_center = camera
            _forward_kernel(*arrays[:3], _np(opacities), arrays[3], degree, w2c, kmat, kinv, cam_center,
                            *scalars, *(o.numpy() for o in outs))
        ctx.mark_non_differentiable(outs[-1])
        ctx.arrays, ctx.degree, ctx.camera, ctx.scalars, ctx.dtype = arrays, degree, camera, scalars, dtype
        return outs

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_colors, g_normals, g_ray_coeffs, g_ray_offsets, g_bounds, _g_ext):
        means, quats, scales, colors = ctx.arrays
        dtype = ctx.dtype
        d = [torch.empty(a.shape, dtype=dtype) for a in ctx.arrays]
        grads = (g_means2d, g_conics, g_depths, g_colors, g_normals, g_ray_coeffs, g_ray_offsets, g_bounds)
        kmat, w2c, kinv, cam_center = ctx.camera
        with numba_scheduling():
            _backward_kernel(
                means, quats, scales, colors, ctx.degree, w2c, kmat, kinv, cam_center, *ctx.scalars,
                *(_np(g.to(dtype)) for g in grads), *(t.numpy() for t in d),
            )
        return (*d, None, None, None, None, None, None, None, None)


def project_numba(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor | None,
    K: Tensor,
    world_to_camera: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 100.0,
    eps2d: float = DEFAULT_EPS2D,
) -> tuple[Projection, Tensor | None]:
    """:func:`~.projection.project_gaussians` plus the per-view colour, in one compiled kernel.

    Args:
        means, quats, scales, opacities, K, world_to_camera, width, height, near, far, eps2d: as
            for :func:`~.projection.project_gaussians` (CPU tensors; K and world_to_camera get no
            gradient).
        colors: (N, 3) RGB, passed through, or (N, K, 3) SH coefficients evaluated as
            :func:`~polargs_plugin.geometry.eval_sh` does at the direction camera centre -> mean,
            or None (the projection alone: a caller with colours of its own).

    Returns:
        (projection, colours (N, 3) or None), both differentiable through one custom autograd function.
    """
    if means.device.type != "cpu":
        raise ValueError(f"project_numba runs on CPU tensors only, got {means.device}")
    dtype = means.dtype
    given = colors is not None
    if colors is None:
        degree = -1
        sh = means.new_zeros(means.shape[0], 1, 3)  # passed through and dropped
    elif colors.dim() == 3:
        degree = sh_degree_from_coeffs(colors.shape[-2])
        sh = colors.to(dtype)
    else:
        degree = -1
        sh = colors.to(dtype)[:, None, :]
    camera = _camera_arrays(K, world_to_camera, dtype)
    means2d, conics, depths, view_colors, normals, ray_coeffs, ray_offsets, bounds, extents = _ProjectFunction.apply(
        means, quats.to(dtype), scales.to(dtype), sh, opacities.detach().to(dtype), degree, camera,
        width, height, near, far, eps2d,
    )
    proj = Projection(means2d, conics, depths, normals, ray_coeffs, ray_offsets, bounds, extents)
    return proj, view_colors if given else None
