"""Gaussian geometry shared by the adapter kit and the reference backend: SH colour, quaternion
rotations, shortest-axis normals, plane distances and plane depths.

Conventions (docs/conventions.md): OpenCV camera frame (x right, y down, z forward), ``K`` 3x3
with pixel centres at +0.5, ``world_to_camera`` 4x4 (not transposed), depth = camera z, normals
= camera-frame vectors facing the camera (n . mean_cam <= 0). Quaternions are wxyz and need not
be unit. Everything is plain differentiable torch over leading batch dimensions, device- and
dtype-agnostic (results keep the inputs' dtype and device).

Planes. A Gaussian's plane passes through its mean across its shortest axis n: in the camera
frame it is n . x = -d with d = -n . mean_cam (PGSR's plane distance), positive when n faces the
camera. A camera ray r (any point of it is z r; r = K^-1 (u, v, 1) has unit z) meets that plane
at camera z = d / -(n . r); conversely the plane through the point at depth z along r has
d = -z (n . r). :func:`ray_plane_depth` and :func:`ray_plane_distance` are these two formulas
over any batch of rays; :func:`depth_from_plane` applies the first to every pixel of an image.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import torch
from torch import Tensor

from polargs_plugin.plane_depth import plane_depth_fused, plane_distances_fused
from polargs_plugin.threads import numba_path

__all__ = [
    "SH_C0",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "rgb_to_sh",
    "sh_to_rgb",
    "sh_degree_from_coeffs",
    "eval_sh",
    "quat_to_rotmat",
    "quat_scale_to_covar",
    "shortest_axis_normals",
    "plane_distances",
    "ray_plane_distance",
    "ray_plane_depth",
    "depth_from_plane",
]

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the degree-0 real SH basis value
# Real SH basis constants (degrees 1-3) in the sign convention of 3DGS / gsplat: the real and
# imaginary parts of the Condon-Shortley complex harmonics, times sqrt(2) for m != 0.
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

_PLANE_EPS = 1e-6  # smallest -(n . ray) of a plane a ray meets (depth_from_plane)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Degree-0 SH coefficient that :func:`eval_sh` maps back to ``rgb``.

    Args:
        rgb: (...) colour values (any shape).

    Returns:
        (...) coefficients (rgb - 0.5) / SH_C0.

    Example:
        >>> rgb_to_sh(torch.tensor([0.5, 1.0]))
        tensor([0.0000, 1.7725])
    """
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh` (before the clamp at 0 of :func:`eval_sh`).

    Example:
        >>> sh_to_rgb(rgb_to_sh(torch.tensor([0.25, -0.5], dtype=torch.float64)))
        tensor([ 0.2500, -0.5000], dtype=torch.float64)
    """
    return sh0 * SH_C0 + 0.5


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """The degree d with (d + 1)^2 == num_coeffs (d <= 3), else ValueError.

    Example:
        >>> sh_degree_from_coeffs(16)
        3
        >>> sh_degree_from_coeffs(5)
        Traceback (most recent call last):
        ...
        ValueError: SH colours need K = (d+1)^2 coefficients with d <= 3, got K = 5
    """
    degree = math.isqrt(num_coeffs) - 1
    if (degree + 1) ** 2 != num_coeffs or not 0 <= degree <= 3:
        raise ValueError(f"SH colours need K = (d+1)^2 coefficients with d <= 3, got K = {num_coeffs}")
    return degree


def eval_sh(sh: Tensor, dirs: Tensor) -> Tensor:
    """Colour of real spherical harmonics (3DGS convention), offset by 0.5 and clamped at 0.

    Args:
        sh: (N, K, 3) coefficients, K = (d + 1)^2 with d in 0..3.
        dirs: (N, 3) viewing directions (camera centre -> Gaussian), any length.

    Returns:
        (N, 3) RGB, max(sum_k Y_k(dir) sh_k + 0.5, 0).

    Example:
        The degree-1 band along +z adds SH_C1 times its z coefficient:

        >>> sh = torch.zeros(1, 4, 3)
        >>> sh[0, 0] = rgb_to_sh(torch.tensor([0.2, 0.4, 0.6]))
        >>> sh[0, 2] = torch.tensor([0.0, 0.0, 0.5])  # the coefficient of Y_1,0 ~ z
        >>> eval_sh(sh, torch.tensor([[0.0, 0.0, 2.0]]))
        tensor([[0.2000, 0.4000, 0.8443]])
    """
    degree = sh_degree_from_coeffs(sh.shape[-2])
    basis = [torch.full_like(dirs[..., 0], SH_C0)]
    if degree >= 1:
        x, y, z = torch.nn.functional.normalize(dirs, dim=-1).unbind(-1)
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    values = (torch.stack(basis, dim=-1)[..., None] * sh).sum(dim=-2)
    return torch.clamp_min(values + 0.5, 0.0)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from (not necessarily unit) quaternions.

    Args:
        quats: (N, 4) quaternions, wxyz.

    Returns:
        (N, 3, 3) rotation matrices; column k is the Gaussian's k-th axis.

    Example:
        A quarter turn about z (w = cos 45 deg, z = sin 45 deg; any scale) takes x to y:

        >>> quat_to_rotmat(torch.tensor([[2.0, 0.0, 0.0, 2.0]])).round(decimals=6)
        tensor([[[ 0., -1.,  0.],
                 [ 1.,  0.,  0.],
                 [ 0.,  0.,  1.]]])
    """
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances R diag(s^2) R^T.

    Args:
        quats: (N, 4) wxyz quaternions.
        scales: (N, 3) positive standard deviations along the Gaussian's axes.

    Returns:
        (N, 3, 3) covariance matrices.

    Example:
        >>> quat_scale_to_covar(torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.tensor([[1.0, 2.0, 3.0]]))
        tensor([[[1., 0., 0.],
                 [0., 4., 0.],
                 [0., 0., 9.]]])
    """
    rs = quat_to_rotmat(quats) * scales[..., None, :]
    return rs @ rs.transpose(-1, -2)


def shortest_axis_normals(axes_cam: Tensor, scales: Tensor, means_cam: Tensor) -> Tensor:
    """Camera-frame shortest axis of each Gaussian, flipped to face the camera.

    Args:
        axes_cam: (N, 3, 3) the Gaussians' axes in the camera frame (column k = axis k).
        scales: (N, 3) positive scales along those axes.
        means_cam: (N, 3) camera-frame means.

    Returns:
        (N, 3) unit normals with ``n . mean_cam <= 0`` (towards the camera centre).

    Ties in ``scales`` pick the first axis (``torch.argmin``); the compiled projection of the
    reference backend applies the same rule.

    Example:
        A disc flat in the z axis, in front of the camera, faces it with -z:

        >>> shortest_axis_normals(torch.eye(3)[None], torch.tensor([[1.0, 1.0, 0.1]]),
        ...                       torch.tensor([[0.0, 0.0, 2.0]]))
        tensor([[-0., -0., -1.]])
    """
    shortest = torch.argmin(scales, dim=-1)
    normals = torch.gather(axes_cam, 2, shortest[:, None, None].expand(-1, 3, 1))[..., 0]
    facing = torch.where((normals * means_cam).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(normals)
    return normals * facing


def _negative_dot(a: Tensor, b: Tensor) -> Tensor:
    """-(a . b) over the last axis: the plane formulas' one dot product (summed x, y, z in order)."""
    return -(a * b).sum(-1)


def plane_distances(normals_cam: Tensor, means: Tensor, world_to_camera: Tensor) -> Tensor:
    """Each Gaussian's plane distance d = -n . mean_cam (PGSR's): its plane n . x = -d through
    its mean, across its shortest axis, in the camera frame; positive when n faces the camera.

    Args:
        normals_cam: (N, 3) camera-frame normals facing the camera (:func:`shortest_axis_normals`).
        means: (N, 3) world means.
        world_to_camera: (4, 4) OpenCV world-to-camera transform.

    Returns:
        (N,) distances, differentiable w.r.t. ``normals_cam`` and ``means`` (and
        ``world_to_camera`` where it requires a gradient: then by torch operations, as on CUDA;
        otherwise, on CPU float tensors, the compiled pass of :mod:`polargs_plugin.plane_depth`,
        the same values and gradients to the last bit).

    Example:
        The camera 5 units behind the world origin, a Gaussian at world z = 1 facing it:

        >>> w2c = torch.eye(4)
        >>> w2c[2, 3] = 5.0
        >>> plane_distances(torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.3, 0.0, 1.0]]), w2c)
        tensor([6.])
    """
    w2c = world_to_camera.to(means)
    if numba_path(means) and normals_cam.dtype == means.dtype and not w2c.requires_grad:
        return plane_distances_fused(normals_cam, means @ w2c[:3, :3].T, w2c[:3, 3])
    return _negative_dot(normals_cam, means @ w2c[:3, :3].T + w2c[:3, 3])


def ray_plane_distance(depth: Tensor, normal: Tensor, rays: Tensor) -> Tensor:
    """Distance d = -depth (n . r) of the plane n . x = -d through the point at camera z
    ``depth`` along each ray r; positive for planes facing the camera.

    Args:
        depth: (...) camera z of the point on each ray.
        normal: (..., 3) camera-frame plane normals (unit for d to be a distance).
        rays: (..., 3) camera-frame rays with unit z (``K^-1 (u, v, 1)``).

    Returns:
        (...) plane distances; :func:`ray_plane_depth` inverts this.

    Example:
        >>> ray_plane_distance(torch.tensor([2.0]), torch.tensor([[0.0, -0.6, -0.8]]),
        ...                    torch.tensor([[0.5, 0.5, 1.0]]))
        tensor([2.2000])
    """
    return depth * _negative_dot(normal, rays)


def ray_plane_depth(distance: Tensor, normal: Tensor, rays: Tensor, min_cosine: float | None = None) -> Tensor:
    """Camera z = d / -(n . r) where each ray r meets its plane n . x = -d.

    Args:
        distance: (...) plane distances d.
        normal: (..., 3) camera-frame plane normals (need not be unit).
        rays: (..., 3) camera-frame rays with unit z (``K^-1 (u, v, 1)``).
        min_cosine: ``None``: the plain quotient, negative where the plane is met behind the
            camera and infinite where the ray is parallel to it. A positive value: 0 where
            -(n . r) <= min_cosine, and a division whose gradient stays finite there.

    Returns:
        (...) camera z of the intersections.

    Example:
        Back to the depth :func:`ray_plane_distance` started from; a plane seen edge-on:

        >>> normal, ray = torch.tensor([[0.0, -0.6, -0.8]]), torch.tensor([[0.5, 0.5, 1.0]])
        >>> ray_plane_depth(ray_plane_distance(torch.tensor([2.0]), normal, ray), normal, ray)
        tensor([2.])
        >>> ray_plane_depth(torch.tensor([1.0]), torch.tensor([[1.0, 0.0, 0.0]]),
        ...                 torch.tensor([[0.0, 0.0, 1.0]]), min_cosine=1e-6)
        tensor([0.])
    """
    cosine = _negative_dot(normal, rays)
    if min_cosine is None:
        return distance / cosine
    valid = cosine > min_cosine
    return torch.where(valid, distance / cosine.clamp_min(min_cosine), torch.zeros_like(distance))


def _image_rays(K: Tensor, height: int, width: int, pixel_center: float) -> Tensor:
    """(H, W, 3) rays K^-1 (u + c, v + c, 1) of every pixel, c = ``pixel_center``, in closed
    form for an upper-triangular K (dtype and device of ``K``)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=K.dtype, device=K.device) + pixel_center,
        torch.arange(width, dtype=K.dtype, device=K.device) + pixel_center,
        indexing="ij",
    )
    ray_x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    ray_y = (v - K[1, 2]) / K[1, 1]
    return torch.stack([ray_x, ray_y, torch.ones_like(ray_x)], dim=-1)


_RAYS_CACHED = 16  # cameras whose pixel rays _cached_image_rays keeps (a training's views, or most of them)
_rays_cache: OrderedDict[tuple, Tensor] = OrderedDict()


def _cached_image_rays(K: Tensor, height: int, width: int, pixel_center: float) -> Tensor:
    """:func:`_image_rays` of a CPU ``K``, kept for the last few cameras: a training renders the
    same few cameras over and over, and the rays are a dozen image-sized operations. Keyed by
    K's values (a CPU read, no device sync), so an edited K never finds stale rays."""
    key = (tuple(K.reshape(-1).tolist()), K.dtype, height, width, pixel_center)
    rays = _rays_cache.get(key)
    if rays is None:
        rays = _image_rays(K, height, width, pixel_center)
        _rays_cache[key] = rays
        if len(_rays_cache) > _RAYS_CACHED:
            _rays_cache.popitem(last=False)
    else:
        _rays_cache.move_to_end(key)
    return rays


def depth_from_plane(distance: Tensor, normal: Tensor, K: Tensor, pixel_center: float = 0.5) -> Tensor:
    """Camera z from a rendered plane distance and normal (PGSR's unbiased plane depth).

    The plane n . x = -d (camera frame, n facing the camera) meets the ray r(p) = K^-1 (p, 1)
    at z = d / -(n . r) (:func:`ray_plane_depth`).

    Args:
        distance: (1, H, W) alpha-blended plane distance d = |n . mean_cam|.
        normal: (3, H, W) alpha-blended camera-frame normal (need not be unit).
        K: (3, 3) intrinsics of the renderer.
        pixel_center: where the renderer puts the centre of pixel (u, v): 0.5 for this project's
            convention (u + 0.5, v + 0.5); 0.0 for PGSR's integer pixel rays.

    Returns:
        (1, H, W) camera z, 0 where the ray is parallel to the plane or faces away.

    Note:
        On CPU float32/float64 tensors the compiled pass of :mod:`polargs_plugin.plane_depth`
        runs (the same values and gradients to the last bit, no gradient w.r.t. ``K``);
        elsewhere (CUDA, under ``torch.func`` transforms or tracing) these torch operations.

    Example:
        The plane z = 2 seen head-on (n = -z, d = 2) is at depth 2 at every pixel:

        >>> K = torch.tensor([[4.0, 0.0, 1.0], [0.0, 4.0, 1.0], [0.0, 0.0, 1.0]])
        >>> normal = torch.tensor([0.0, 0.0, -1.0])[:, None, None].expand(3, 2, 2)
        >>> depth_from_plane(torch.full((1, 2, 2), 2.0), normal, K)
        tensor([[[2., 2.],
                 [2., 2.]]])
    """
    _, height, width = distance.shape
    fused = numba_path(distance) and normal.dtype == distance.dtype
    rays = _cached_image_rays(K.detach().to(distance), height, width, pixel_center) if fused else \
        _image_rays(K.to(distance), height, width, pixel_center)
    if fused:
        return plane_depth_fused(distance, normal, rays, _PLANE_EPS)
    return ray_plane_depth(distance[0], normal.permute(1, 2, 0), rays, min_cosine=_PLANE_EPS)[None]
