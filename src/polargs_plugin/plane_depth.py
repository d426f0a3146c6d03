r"""PGSR's plane distances and unbiased plane depth on the CPU, compiled, bit for bit the torch operations.

:func:`polargs_plugin.geometry.depth_from_plane` by torch operations builds about a dozen image-sized
intermediates (the rays, the (H, W, 3) products of a permuted normal, the clamp, the quotient) and
their autograd graph; a training step with the hooks pays for it twice (forward and backward). Here
each pixel's value

.. math::

    c = -((n_x r_x + n_y r_y) + n_z r_z), \qquad z = \begin{cases} d / \max(c, \epsilon) & c > \epsilon
    \\ 0 & \text{otherwise} \end{cases}

and, in the backward, the gradients the torch graph's nodes would pass (where, division, clamp,
negation, the dot product) are computed in the input's dtype, operation by operation in torch's
order, so values and gradients equal the torch path's to the last bit (tests/ check it with
``torch.equal``): a training step is the same whichever path served it. The rays come from
torch (cached per camera, :func:`polargs_plugin.geometry.depth_from_plane`).

Likewise each Gaussian's plane distance :math:`d = -((n_x m_x + n_y m_y) + n_z m_z)` with
:math:`m = R\,\mu + t` its camera-frame mean: the rotation stays a torch matrix product (its
rounding is the BLAS's), the translation, the dot product and the negation, forward and backward,
are one pass over the Gaussians instead of four operations each way.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from polargs_plugin.threads import numba_scheduling

__all__ = ["plane_depth_fused", "plane_distances_fused"]


@numba.njit(inline="always")
def _cosine(normal, rays, v, u):
    """-(n . r) at pixel (v, u): the products, their sum in x, y, z order, then the negation (torch's order)."""
    return -((normal[0, v, u] * rays[v, u, 0] + normal[1, v, u] * rays[v, u, 1]) + normal[2, v, u] * rays[v, u, 2])


@numba.njit(parallel=True, cache=True)
def _forward_kernel(distance, normal, rays, eps, depth):
    height, width = distance.shape
    zero = distance.dtype.type(0)
    for v in numba.prange(height):
        for u in range(width):
            cosine = _cosine(normal, rays, v, u)
            depth[v, u] = distance[v, u] / max(cosine, eps) if cosine > eps else zero


@numba.njit(parallel=True, cache=True)
def _backward_kernel(grad, distance, normal, rays, eps, grad_distance, grad_normal):
    height, width = distance.shape
    zero = distance.dtype.type(0)
    for v in numba.prange(height):
        for u in range(width):
            cosine = _cosine(normal, rays, v, u)
            clamped = max(cosine, eps)
            g = grad[v, u] if cosine > eps else zero  # where's backward
            d = distance[v, u]
            grad_distance[v, u] = g / clamped  # division's, numerator
            g_clamped = -g * ((d / clamped) / clamped)  # division's, denominator
            g_dot = -(g_clamped if cosine >= eps else zero)  # clamp_min's (passes at equality), negation's
            for c in range(3):
                grad_normal[c, v, u] = g_dot * rays[v, u, c]


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _PlaneDepth(torch.autograd.Function):
    """(1, H, W) distance, (3, H, W) normal, (H, W, 3) rays, eps -> (1, H, W) depth."""

    @staticmethod
    def forward(ctx, distance: Tensor, normal: Tensor, rays: Tensor, eps: float) -> Tensor:
        arrays = (_np(distance[0]), _np(normal), _np(rays))
        eps_typed = arrays[0].dtype.type(eps)  # torch compares and clamps with the scalar in the tensor's dtype
        depth = np.empty_like(arrays[0])
        with numba_scheduling():
            _forward_kernel(*arrays, eps_typed, depth)
        ctx.arrays, ctx.eps, ctx.dtype = arrays, eps_typed, distance.dtype
        return torch.from_numpy(depth)[None]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        distance, normal, rays = ctx.arrays
        grad_distance, grad_normal = np.empty_like(distance), np.empty_like(normal)
        with numba_scheduling():
            _backward_kernel(_np(grad[0].to(ctx.dtype)), distance, normal, rays, ctx.eps,
                             grad_distance, grad_normal)
        return torch.from_numpy(grad_distance)[None], torch.from_numpy(grad_normal), None, None


def plane_depth_fused(distance: Tensor, normal: Tensor, rays: Tensor, eps: float) -> Tensor:
    """:func:`polargs_plugin.geometry.depth_from_plane` on CPU float tensors of one dtype.

    Args:
        distance: (1, H, W) plane distances.
        normal: (3, H, W) camera-frame normals (need not be unit).
        rays: (H, W, 3) pixel rays ``K^-1 (u + c, v + c, 1)``.
        eps: smallest -(n . r) of a plane a ray meets; 0 depth (and gradient) below it.

    Returns:
        (1, H, W) camera z, differentiable w.r.t. ``distance`` and ``normal`` (once).
    """
    return _PlaneDepth.apply(distance, normal, rays, eps)


@numba.njit(parallel=True, cache=True)
def _distance_forward_kernel(normals, rotated, translation, distances):
    for i in numba.prange(normals.shape[0]):
        m0, m1, m2 = rotated[i, 0] + translation[0], rotated[i, 1] + translation[1], rotated[i, 2] + translation[2]
        distances[i] = -((normals[i, 0] * m0 + normals[i, 1] * m1) + normals[i, 2] * m2)


@numba.njit(parallel=True, cache=True)
def _distance_backward_kernel(grad, normals, rotated, translation, grad_normals, grad_rotated):
    for i in numba.prange(normals.shape[0]):
        g = -grad[i]  # negation's; the sum passes it to each product
        for c in range(3):
            grad_normals[i, c] = g * (rotated[i, c] + translation[c])  # product's, w.r.t. the normal
            grad_rotated[i, c] = g * normals[i, c]  # product's, w.r.t. the mean (the sum with t passes it)


class _PlaneDistances(torch.autograd.Function):
    """(N, 3) camera-frame normals, (N, 3) rotated means R mu, (3,) translation -> (N,) distances."""

    @staticmethod
    def forward(ctx, normals: Tensor, rotated: Tensor, translation: Tensor) -> Tensor:
        arrays = (_np(normals), _np(rotated), _np(translation))
        distances = np.empty(arrays[0].shape[0], arrays[0].dtype)
        with numba_scheduling():
            _distance_forward_kernel(*arrays, distances)
        ctx.arrays, ctx.dtype = arrays, normals.dtype
        return torch.from_numpy(distances)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        normals, rotated, translation = ctx.arrays
        grad_normals, grad_rotated = np.empty_like(normals), np.empty_like(rotated)
        with numba_scheduling():
            _distance_backward_kernel(_np(grad.to(ctx.dtype)), normals, rotated, translation,
                                      grad_normals, grad_rotated)
        return torch.from_numpy(grad_normals), torch.from_numpy(grad_rotated), None


def plane_distances_fused(normals_cam: Tensor, rotated_means: Tensor, translation: Tensor) -> Tensor:
    """:func:`polargs_plugin.geometry.plane_distances` after its rotation, on CPU float tensors of
    one dtype.

    Args:
        normals_cam: (N, 3) camera-frame normals.
        rotated_means: (N, 3) world means times the world-to-camera rotation's transpose.
        translation: (3,) the world-to-camera translation (no gradient).

    Returns:
        (N,) plane distances, differentiable w.r.t. ``normals_cam`` and ``rotated_means`` (once).
    """
    return _PlaneDistances.apply(normals_cam, rotated_means, translation)
