"""Per-Gaussian maths of the reference rasterizer: rotations, covariances, SH colour, EWA projection.

Everything is plain differentiable torch over (N, ...) tensors, device-agnostic. The projection
follows the usual 3DGS / gsplat semantics (EWA Jacobian of the pinhole projection, a 0.3 px^2
low-pass dilation of the screen covariance, near/far culling) and adds what the compositor needs
for per-pixel depth and the camera-frame normal.

Per-pixel depth. Each Gaussian reports, at pixel p, the camera z of the point of maximum density
along the ray through p: with r(p) = K^-1 (p_x, p_y, 1) and Sigma the camera-frame covariance,
t*(p) = r^T Sigma^-1 mu / (r^T Sigma^-1 r). For a flattened Gaussian this is the intersection of
the ray with its plane (so a planar splat renders the plane's depth exactly); for a round one it
is close to the mean's z. The value is clamped to z_mean +- DEPTH_CLAMP_SIGMAS * sigma_z so that
rays grazing an edge-on splat cannot produce depths outside the Gaussian's own extent.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

__all__ = [
    "SH_C0",
    "DEPTH_CLAMP_SIGMAS",
    "ALPHA_MIN",
    "FOV_CLAMP",
    "EXTENT_SLACK",
    "Projection",
    "quat_to_rotmat",
    "quat_scale_to_covar",
    "rgb_to_sh",
    "sh_to_rgb",
    "sh_degree_from_coeffs",
    "eval_sh",
    "shortest_axis_normals",
    "plane_distances",
    "depth_from_plane",
    "project_gaussians",
]

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the degree-0 real SH basis value
DEPTH_CLAMP_SIGMAS = 5.0
ALPHA_MIN = 1.0 / 255.0
DEFAULT_EPS2D = 0.3  # vanilla 3DGS's screen-space dilation, pixels^2
_PLANE_EPS = 1e-6  # smallest -(n . ray) of a plane a ray meets (depth_from_plane)
FOV_CLAMP = 1.3  # the EWA Jacobian is evaluated with x/z, y/z limited to 1.3x the field of view
EXTENT_SLACK = 1e-4  # relative slack of the opacity-aware extents

# Real SH basis constants (degrees 1-3) in the sign convention of 3DGS / gsplat: the real and
# imaginary parts of the Condon-Shortley complex harmonics, times sqrt(2) for m != 0.
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


class Projection(NamedTuple):
    """Screen-space quantities of N Gaussians for one camera (all differentiable).

    Attributes:
        means2d: (N, 2) projected means in pixels (pixel centres at +0.5).
        conics: (N, 3) inverse screen covariance (a, b, c) = [[a, b], [b, c]].
        depths: (N,) camera z of the means (the sort key).
        normals: (N, 3) camera-frame shortest axis, flipped so that n . mean_cam <= 0.
        ray_coeffs: (N, 3, 3) matrix Q with a(p) = Q (p_x, p_y, 1) for the per-pixel depth.
        ray_offsets: (N, 3) vector b; depth at p is (a . b) / (a . a), clamped.
        depth_bounds: (N, 2) clamp interval (low, high) of the per-pixel depth.
        extents: (N, 2) half-widths (x, y) in pixels of the box holding every pixel the Gaussian
            can reach with alpha >= 1/255 (opacity-aware); 0 where culled (no grad).
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    normals: Tensor
    ray_coeffs: Tensor
    ray_offsets: Tensor
    depth_bounds: Tensor
    extents: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from (not necessarily unit) quaternions.

    Args:
        quats: (N, 4) quaternions, wxyz.

    Returns:
        (N, 3, 3) rotation matrices; column k is the Gaussian's k-th axis.
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
    """
    rs = quat_to_rotmat(quats) * scales[..., None, :]
    return rs @ rs.transpose(-1, -2)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Degree-0 SH coefficient that :func:`eval_sh` maps back to ``rgb``."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh` (before the clamp at 0)."""
    return sh0 * SH_C0 + 0.5


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """The degree d with (d + 1)^2 == num_coeffs (d <= 3), else ValueError."""
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
    """
    degree = sh_degree_from_coeffs(sh.shape[-2])
    basis = [torch.full_like(dirs[..., 0], SH_C0)]
    if degree >= 1:
        x, y, z = torch.nn.functional.normalize(dirs, dim=-1).unbind(-1)
        basis += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [
            _C2[0] * xy,
            _C2[1] * yz,
            _C2[2] * (2 * zz - xx - yy),
            _C2[3] * xz,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    values = (torch.stack(basis, dim=-1)[..., None] * sh).sum(dim=-2)
    return torch.clamp_min(values + 0.5, 0.0)


def shortest_axis_normals(axes_cam: Tensor, scales: Tensor, means_cam: Tensor) -> Tensor:
    """Camera-frame shortest axis of each Gaussian, flipped to face the camera.

    Args:
        axes_cam: (N, 3, 3) the Gaussians' axes in the camera frame (column k = axis k).
        scales: (N, 3) positive scales along those axes.
        means_cam: (N, 3) camera-frame means.

    Returns:
        (N, 3) unit normals with ``n . mean_cam <= 0`` (towards the camera centre).

    Ties in ``scales`` pick the first axis (``torch.argmin``). The compiled projection
    (:mod:`.projection_numba`) applies the same rule; tests/test_projection_numba.py checks it.
    """
    shortest = torch.argmin(scales, dim=-1)
    normals = torch.gather(axes_cam, 2, shortest[:, None, None].expand(-1, 3, 1))[..., 0]
    facing = torch.where((normals * means_cam).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(normals)
    return normals * facing


def plane_distances(normals_cam: Tensor, means: Tensor, world_to_camera: Tensor) -> Tensor:
    """Each Gaussian's plane distance d = -n . mean_cam (PGSR's): its plane n . x = -d through
    its mean, across its shortest axis, in the camera frame; positive when n faces the camera.

    Args:
        normals_cam: (N, 3) camera-frame normals facing the camera (:func:`shortest_axis_normals`).
        means: (N, 3) world means.
        world_to_camera: (4, 4) OpenCV world-to-camera transform.

    Returns:
        (N,) distances, differentiable w.r.t. ``normals_cam`` and ``means``.
    """
    w2c = world_to_camera.to(means)
    return -(normals_cam * (means @ w2c[:3, :3].T + w2c[:3, 3])).sum(-1)


def depth_from_plane(distance: Tensor, normal: Tensor, K: Tensor, pixel_center: float = 0.5) -> Tensor:
    """Camera z from a rendered plane distance and normal (PGSR's unbiased plane depth).

    The plane n . x = -d (camera frame, n facing the camera) meets the ray r(p) = K^-1 (p, 1)
    at z = d / -(n . r).

    Args:
        distance: (1, H, W) alpha-blended plane distance d = |n . mean_cam|.
        normal: (3, H, W) alpha-blended camera-frame normal (need not be unit).
        K: (3, 3) intrinsics of the renderer.
        pixel_center: where the renderer puts the centre of pixel (u, v): 0.5 for this project's
            convention (u + 0.5, v + 0.5); 0.0 for PGSR's integer pixel rays.

    Returns:
        (1, H, W) camera z, 0 where the ray is parallel to the plane or faces away.
    """
    _, height, width = distance.shape
    K = K.to(distance)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=distance.dtype, device=distance.device) + pixel_center,
        torch.arange(width, dtype=distance.dtype, device=distance.device) + pixel_center,
        indexing="ij",
    )
    ray_x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    ray_y = (v - K[1, 2]) / K[1, 1]
    cosine = -(normal[0] * ray_x + normal[1] * ray_y + normal[2])[None]
    valid = cosine > _PLANE_EPS
    return torch.where(valid, distance / cosine.clamp_min(_PLANE_EPS), torch.zeros_like(distance))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    K: Tensor,
    world_to_camera: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 100.0,
    eps2d: float = DEFAULT_EPS2D,
) -> Projection:
    """EWA projection of 3D Gaussians into one pinhole camera.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations.
        scales: (N, 3) positive scales.
        opacities: (N,) in (0, 1), used only for the binning radius.
        K: (3, 3) intrinsics, pixel centres at +0.5, last row (0, 0, 1).
        world_to_camera: (4, 4) OpenCV world-to-camera transform.
        width, height: image size in pixels.
        near, far: Gaussians whose mean z is outside [near, far] are culled.
        eps2d: low-pass dilation added to the screen covariance diagonal (pixels^2).

    Returns:
        :class:`Projection`. Culled Gaussians have extents 0 and finite (meaningless) values.
    """
    K = K.to(means)
    w2c = world_to_camera.to(means)
    rot_w2c, t_w2c = w2c[:3, :3], w2c[:3, 3]
    mean_c = means @ rot_w2c.T + t_w2c
    z = mean_c[:, 2]
    in_range = (z >= near) & (z <= far)
    # Culled Gaussians get a harmless z so that no inf/NaN leaks into the gradients.
    z_safe = torch.where(in_range, z, torch.ones_like(z))
    x, y = mean_c[:, 0], mean_c[:, 1]

    fx, skew, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    means2d = torch.stack([(fx * x + skew * y) / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    axes_c = rot_w2c @ quat_to_rotmat(quats)  # (N, 3, 3), columns = axes in the camera frame
    rs = axes_c * scales[:, None, :]
    cov_c = rs @ rs.transpose(-1, -2)

    # The Jacobian is evaluated with x/z, y/z limited to 1.3x the field of view, as in 3DGS,
    # so that Gaussians far outside the image do not get absurd footprints.
    lim_x_hi = FOV_CLAMP * (width - cx) / fx
    lim_x_lo = -FOV_CLAMP * cx / fx
    lim_y_hi = FOV_CLAMP * (height - cy) / fy
    lim_y_lo = -FOV_CLAMP * cy / fy
    xz = torch.minimum(torch.maximum(x / z_safe, lim_x_lo), lim_x_hi)
    yz = torch.minimum(torch.maximum(y / z_safe, lim_y_lo), lim_y_hi)
    zero = torch.zeros_like(z_safe)
    inv_z = 1.0 / z_safe
    jac = torch.stack(
        [
            fx * inv_z, skew * inv_z, -(fx * xz + skew * yz) * inv_z,
            zero, fy * inv_z, -fy * yz * inv_z,
        ],
        dim=-1,
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(-1, -2)
    a = cov2d[:, 0, 0] + eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    # Opacity-aware extent: alpha >= 1/255 needs d^T conic d <= 2 ln(255 o), an ellipse whose
    # axis-aligned bounding box has half-widths sqrt(2 ln(255 o) cov_xx), sqrt(2 ln(255 o) cov_yy).
    # The 1e-4 relative slack keeps pixels exactly on the boundary despite rounding.
    with torch.no_grad():
        log_ratio = torch.log(opacities.detach().clamp_min(1e-30) / ALPHA_MIN).clamp_min(0.0)
        extents = (1 + EXTENT_SLACK) * torch.sqrt(2.0 * log_ratio[:, None] * torch.stack([a, c], dim=-1).detach())
        keep = in_range & (log_ratio > 0) & (det > 0)
        extents = torch.where(keep[:, None], extents, torch.zeros_like(extents))

    normals = shortest_axis_normals(axes_c, scales, mean_c)

    # Per-pixel depth data: Q = diag(s_min / s) R_c^T K^-1, b = diag(s_min / s) R_c^T mu_c.
    # Dividing by s_min keeps the numbers O(1) for very flat Gaussians; the ratio is unchanged.
    rel_inv_scale = scales.min(dim=-1, keepdim=True).values / scales
    m = axes_c.transpose(-1, -2) * rel_inv_scale[..., None]
    ray_coeffs = m @ torch.linalg.inv(K)
    mean_c_safe = torch.where(in_range[:, None], mean_c, torch.ones_like(mean_c))
    ray_offsets = (m @ mean_c_safe[..., None])[..., 0]
    sigma_z = torch.sqrt(cov_c[:, 2, 2].clamp_min(1e-30))
    depth_bounds = torch.stack(
        [z_safe - DEPTH_CLAMP_SIGMAS * sigma_z, z_safe + DEPTH_CLAMP_SIGMAS * sigma_z], dim=-1
    )
    return Projection(means2d, conics, z_safe, normals, ray_coeffs, ray_offsets, depth_bounds, extents)
