r"""Fused depth-normal consistency loss (L_dn) with a hand-written backward, compiled for the CPU.

The value is that of :func:`polargs_plugin.losses.depth_normal_loss`:

.. math::

    L_{dn} = \frac{\sum_p w_p \, (1 - \hat N_d(p) \cdot \hat N(p))}{\max(\sum_p w_p,\ 10^{-8})},
    \qquad w_p = \alpha_p \, \mathrm{valid}_p \ \text{(detached)}

with :math:`\hat N` the rendered normal made unit length (``safe_normalize``), and
:math:`\hat N_d` the normal of the back-projected depth: points
:math:`P = z\,K^{-1}[u + 0.5, v + 0.5, 1]^T`, central differences
:math:`d_u = P_{u+1} - P_{u-1}`, :math:`d_v = P_{v+1} - P_{v-1}`, then
:math:`c = (d_v \times d_u)\, f_x f_y / \max(z^2, 10^{-12})` made unit length. A pixel is valid
where it and its four neighbours have positive depth (never on the border).

The torch version builds about thirty (3, H, W) intermediates and their autograd graph; here one
pass per row forms the per-row sums (rows run in parallel; the rows' sums are added in row order,
so the value does not depend on the thread count). When a gradient will be needed, the same pass
writes each pixel's gradient terms and the gradients of its two differences, and a second pass
gathers those into the depth gradient of each pixel from its four neighbours (so that rows never
write to each other); the backward only scales them by the incoming gradient over the weights' sum.
Arithmetic is float64 whatever the input dtype; the result has the input's dtype.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from polargs_plugin.threads import numba_scheduling

__all__ = ["depth_normal_loss_fused"]

_EPS_NORM = 1e-12  # floor on squared norms (safe_normalize)
_EPS_DEPTH = 1e-12  # floor on z^2 in the scale
_EPS_WEIGHT = 1e-8  # floor on the weight sum


@numba.njit(inline="always")
def _ray_y(v, k):
    """y of the pixel ray K^-1 [u + 0.5, v + 0.5, 1] (its z is 1)."""
    return (v + 0.5 - k[4]) * k[6]


@numba.njit(inline="always")
def _ray_x(u, v, k):
    """x of the pixel ray K^-1 [u + 0.5, v + 0.5, 1]."""
    return (u + 0.5 - k[2] - k[1] * _ray_y(v, k)) * k[5]


@numba.njit(inline="always")
def _point(depth, u, v, k):
    z = float(depth[v, u])
    return z * _ray_x(u, v, k), z * _ray_y(v, k), z


@numba.njit(inline="always")
def _valid(depth, u, v):
    return depth[v, u] > 0 and depth[v, u + 1] > 0 and depth[v, u - 1] > 0 and depth[v + 1, u] > 0 and depth[v - 1, u] > 0


@numba.njit(inline="always")
def _pixel(depth, normal, u, v, k):
    """Differences, cross product, scale and both unit normals of one valid pixel."""
    ax, ay, az = _point(depth, u + 1, v, k)
    bx, by, bz = _point(depth, u - 1, v, k)
    dux, duy, duz = ax - bx, ay - by, az - bz
    ax, ay, az = _point(depth, u, v + 1, k)
    bx, by, bz = _point(depth, u, v - 1, k)
    dvx, dvy, dvz = ax - bx, ay - by, az - bz
    # k = d_v x d_u points towards the camera (x right, y down, z forward).
    kx = dvy * duz - dvz * duy
    ky = dvz * dux - dvx * duz
    kz = dvx * duy - dvy * dux
    z = float(depth[v, u])
    z2 = z * z
    scale = k[0] * k[3] / max(z2, _EPS_DEPTH)
    cx, cy, cz = kx * scale, ky * scale, kz * scale
    cc = cx * cx + cy * cy + cz * cz
    rc = 1.0 / math.sqrt(max(cc, _EPS_NORM))
    nx, ny, nz = float(normal[0, v, u]), float(normal[1, v, u]), float(normal[2, v, u])
    nn = nx * nx + ny * ny + nz * nz
    rn = 1.0 / math.sqrt(max(nn, _EPS_NORM))
    return (dux, duy, duz, dvx, dvy, dvz, kx, ky, kz, z, z2, scale, cx * rc, cy * rc, cz * rc, cc, rc,
            nx * rn, ny * rn, nz * rn, nn, rn)


@numba.njit(inline="always")
def _unit_backward(gx, gy, gz, hx, hy, hz, sq, r):
    """Gradient through x -> x / sqrt(max(x.x, eps)) given the unit vector h, x.x and 1/sqrt(.)."""
    if sq >= _EPS_NORM:
        dot = hx * gx + hy * gy + hz * gz
        return r * (gx - hx * dot), r * (gy - hy * dot), r * (gz - hz * dot)
    return r * gx, r * gy, r * gz


@numba.njit(inline="always")
def _gather(g_du, g_dv, u, v, c):
    height, width = g_du.shape[1], g_du.shape[2]
    total = 0.0
    if u >= 1:
        total += g_du[c, v, u - 1]
    if u + 1 < width:
        total -= g_du[c, v, u + 1]
    if v >= 1:
        total += g_dv[c, v - 1, u]
    if v + 1 < height:
        total -= g_dv[c, v + 1, u]
    return total


@numba.njit(inline="always")
def _pixel_gradients(q, w, u, v, grad_depth, grad_normal, g_du, g_dv):
    """Gradients of w (1 - cosine) at one valid pixel (``q`` from :func:`_pixel`): the normal's,
    the depth's through the scale, and those of the differences d_u and d_v."""
    (dux, duy, duz, dvx, dvy, dvz, kx, ky, kz, z, z2, scale, ndx, ndy, ndz, cc, rc,
     nhx, nhy, nhz, nn, rn) = q
    g_cos = -w
    gnx, gny, gnz = _unit_backward(g_cos * ndx, g_cos * ndy, g_cos * ndz, nhx, nhy, nhz, nn, rn)
    grad_normal[0, v, u], grad_normal[1, v, u], grad_normal[2, v, u] = gnx, gny, gnz
    gcx, gcy, gcz = _unit_backward(g_cos * nhx, g_cos * nhy, g_cos * nhz, ndx, ndy, ndz, cc, rc)
    g_scale = gcx * kx + gcy * ky + gcz * kz
    if z2 >= _EPS_DEPTH:
        grad_depth[v, u] = -2.0 * scale / z * g_scale
    gkx, gky, gkz = gcx * scale, gcy * scale, gcz * scale
    # k = d_v x d_u: dL/dd_u = g_k x d_v, dL/dd_v = d_u x g_k.
    g_du[0, v, u] = gky * dvz - gkz * dvy
    g_du[1, v, u] = gkz * dvx - gkx * dvz
    g_du[2, v, u] = gkx * dvy - gky * dvx
    g_dv[0, v, u] = duy * gkz - duz * gky
    g_dv[1, v, u] = duz * gkx - dux * gkz
    g_dv[2, v, u] = dux * gky - duy * gkx


@numba.njit(parallel=True, cache=True)
def _kernel(depth, normal, alpha, k, row_loss, row_weight, with_gradient, grad_depth, grad_normal, g_du, g_dv):
    """Per row, the sums of w (1 - cosine) and of w; with ``with_gradient`` also the gradient of
    the whole sum sum_p w_p (1 - cosine_p) (not yet divided by the weights' sum) in the same pass:
    pass 1 writes each valid pixel's normal gradient, its depth gradient through the scale and
    the gradients of d_u and d_v (zero elsewhere); pass 2 adds to each pixel's depth gradient
    the differences' gradients of its four neighbours."""
    height, width = depth.shape
    for v in numba.prange(height):
        acc_loss = 0.0
        acc_weight = 0.0
        for u in range(width):
            if with_gradient:
                grad_depth[v, u] = 0.0
                for c in range(3):
                    grad_normal[c, v, u] = 0.0
                    g_du[c, v, u] = 0.0
                    g_dv[c, v, u] = 0.0
            if v == 0 or v == height - 1 or u == 0 or u == width - 1 or not _valid(depth, u, v):
                continue
            q = _pixel(depth, normal, u, v, k)
            w = float(alpha[v, u])
            cosine = q[12] * q[17] + q[13] * q[18] + q[14] * q[19]
            acc_loss += w * (1.0 - cosine)
            acc_weight += w
            if with_gradient:
                _pixel_gradients(q, w, u, v, grad_depth, grad_normal, g_du, g_dv)
        row_loss[v] = acc_loss
        row_weight[v] = acc_weight
    if not with_gradient:
        return
    for v in numba.prange(height):
        ry = _ray_y(v, k)
        for u in range(width):
            # dL/dP of this pixel: it is the + end of d_u at u - 1 and of d_v at v - 1, the - end at u + 1, v + 1.
            g_point = _gather(g_du, g_dv, u, v, 0) * _ray_x(u, v, k) + _gather(g_du, g_dv, u, v, 1) * ry
            grad_depth[v, u] += g_point + _gather(g_du, g_dv, u, v, 2)


_workspace = threading.local()


def _difference_workspace(shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's (3, H, W) float64 buffers for the differences' gradients, kept per thread for
    the last image size: they live only during one kernel call, and fresh image-sized buffers
    cost the kernel a page fault every 4 KiB (a fifth of its time at 128 x 128)."""
    buffers = getattr(_workspace, "buffers", None)
    if buffers is None or buffers[0].shape != shape:
        buffers = (np.empty(shape, np.float64), np.empty(shape, np.float64))
        _workspace.buffers = buffers
    return buffers


def _intrinsics(K: Tensor) -> np.ndarray:
    """fx, skew, cx, fy, cy, 1 / fx, 1 / fy (float64)."""
    (fx, skew, cx), (_, fy, cy) = K.detach().cpu().tolist()[:2]  # one host read; Python floats are float64
    return np.array([fx, skew, cx, fy, cy, 1.0 / fx, 1.0 / fy], np.float64)


class _FusedDepthNormal(torch.autograd.Function):
    """(1, H, W) depth, (3, H, W) normal, (1, H, W) alpha (no gradient), K -> scalar L_dn.

    When a gradient will be asked for, the forward computes it too (one pass over the pixels
    instead of two); the backward only scales it by the incoming gradient."""

    @staticmethod
    def forward(ctx, depth: Tensor, normal: Tensor, alpha: Tensor, K: Tensor) -> Tensor:
        d = depth.detach()[0].contiguous().numpy()
        n = normal.detach().contiguous().numpy()
        a = alpha.detach()[0].contiguous().numpy()
        height = d.shape[0]
        row_loss, row_weight = np.zeros(height), np.zeros(height)
        with_gradient = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        shape = n.shape if with_gradient else (3, 0, 0)
        grad_depth = np.empty(shape[1:], np.float64)
        grad_normal = np.empty(shape, np.float64)
        g_du, g_dv = _difference_workspace(shape)
        with numba_scheduling():
            _kernel(d, n, a, _intrinsics(K), row_loss, row_weight, with_gradient, grad_depth, grad_normal, g_du, g_dv)
        denominator = max(float(row_weight.sum()), _EPS_WEIGHT)
        ctx.gradients = (grad_depth, grad_normal)
        ctx.denominator = denominator
        ctx.dtype = depth.dtype
        return torch.tensor(float(row_loss.sum()) / denominator, dtype=depth.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        grad_depth, grad_normal = ctx.gradients
        scale = float(grad) / ctx.denominator
        return (torch.from_numpy(grad_depth * scale)[None].to(ctx.dtype),
                torch.from_numpy(grad_normal * scale).to(ctx.dtype), None, None)


def depth_normal_loss_fused(depth: Tensor, normal: Tensor, alpha: Tensor, K: Tensor) -> Tensor:
    r"""L_dn on CPU float tensors (see the module docstring); differentiable w.r.t. ``depth`` and
    ``normal`` (once: no double backward), ``alpha`` is a weight (no gradient).

    Args:
        depth: :math:`(1, H, W)` rendered camera-z depth, H, W >= 3.
        normal: :math:`(3, H, W)` rendered normal (any length).
        alpha: :math:`(1, H, W)` rendered opacity.
        K: :math:`(3, 3)` intrinsics.

    Returns:
        Scalar of ``depth``'s dtype, 0 where no pixel is valid or alpha is 0.

    Example:
        >>> K = torch.tensor([[50.0, 0, 8], [0, 50.0, 8], [0, 0, 1]])
        >>> plane = torch.ones(1, 16, 16)  # fronto-parallel, its normal facing the camera
        >>> facing = torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1).expand(3, 16, 16)
        >>> round(float(depth_normal_loss_fused(plane, facing, torch.ones(1, 16, 16), K)), 6)
        0.0
    """
    return _FusedDepthNormal.apply(depth, normal, alpha, K)
