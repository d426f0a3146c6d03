"""EWA projection of the reference rasterizer: each Gaussian's screen footprint, depth and normal.

Everything is plain differentiable torch over (N, ...) tensors, device-agnostic; rotations,
normals and SH colour come from :mod:`polargs_plugin.geometry`. The projection
follows the usual 3DGS / gsplat semantics (EWA Jacobian of the pinhole projection, a 0.3 px^2
low-pass dilation of the screen covariance, near/far culling) and adds what the compositor needs
for per-pixel depth and the camera-frame normal.

Per-pixel depth. Each Gaussian reports, at pixel p, the camera z of the point of maximum density
along the ray through p: with r(p) = K^-1 (p_x, p_y, 1) and Sigma the camera-frame covariance,
t*(p) = r^T Sigma^-1 mu / (r^T Sigma^-1 r). For a flattened Gaussian this is the intersection of
the ray with its plane (so a planar splat renders the plane's depth exactly); for a round one it
is close to the mean's z. The value is clamped to z_mean +- DEPTH_CLAMP_SIGMAS * sigma_z so that
rays grazing an edge-on splat cannot produce depths outside the Gaussian's own extent.

Ray-order key. Ray-ordered compositing sorts by the same depth of the Gaussians thickened by the
screen-space dilation (:func:`dilated_ray_depth_data`): an edge-on splat owes its alpha to the
dilation alone, and its undilated maximum density along a ray that passes beside it is where the
ray crosses its plane, anywhere within the clamp, which at a silhouette would put it in front of
the surface it belongs to.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from polargs_plugin.geometry import quat_to_rotmat, shortest_axis_normals

__all__ = [
    "DEPTH_CLAMP_SIGMAS",
    "ALPHA_MIN",
    "FOV_CLAMP",
    "EXTENT_SLACK",
    "Projection",
    "project_gaussians",
    "dilated_ray_depth_data",
]

DEPTH_CLAMP_SIGMAS = 5.0
ALPHA_MIN = 1.0 / 255.0
DEFAULT_EPS2D = 0.3  # vanilla 3DGS's screen-space dilation, pixels^2
FOV_CLAMP = 1.3  # the EWA Jacobian is evaluated with x/z, y/z limited to 1.3x the field of view
EXTENT_SLACK = 1e-4  # relative slack of the opacity-aware extents


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
    rot_w2c, mean_c, z_safe, in_range = _camera_frame(means, world_to_camera, near, far)
    x, y = mean_c[:, 0], mean_c[:, 1]

    fx, skew, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    means2d = torch.stack([(fx * x + skew * y) / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    axes_c = rot_w2c @ quat_to_rotmat(quats)  # (N, 3, 3), columns = axes in the camera frame
    rs = axes_c * scales[:, None, :]
    cov_c = rs @ rs.transpose(-1, -2)
    a, b, c = _screen_covariance(cov_c, x, y, z_safe, (fx, skew, cx, fy, cy), width, height, eps2d)
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    extents = _extents(opacities, a, c, det, in_range)
    normals = shortest_axis_normals(axes_c, scales, mean_c)
    ray_coeffs, ray_offsets, depth_bounds = _ray_depth_data(axes_c, scales, cov_c, mean_c, z_safe, in_range, K)
    return Projection(means2d, conics, z_safe, normals, ray_coeffs, ray_offsets, depth_bounds, extents)


def _camera_frame(means: Tensor, world_to_camera: Tensor, near: float, far: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(world-to-camera rotation, camera-frame means, culling-safe mean z, in [near, far])."""
    w2c = world_to_camera.to(means)
    rot_w2c = w2c[:3, :3]
    mean_c = means @ rot_w2c.T + w2c[:3, 3]
    z = mean_c[:, 2]
    in_range = (z >= near) & (z <= far)
    # Culled Gaussians get a harmless z so that no inf/NaN leaks into the gradients.
    z_safe = torch.where(in_range, z, torch.ones_like(z))
    return rot_w2c, mean_c, z_safe, in_range


@torch.no_grad()
def dilated_ray_depth_data(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    K: Tensor,
    world_to_camera: Tensor,
    near: float = 0.01,
    far: float = 100.0,
    eps2d: float = DEFAULT_EPS2D,
) -> tuple[Tensor, Tensor, Tensor]:
    """The per-pixel depth data (ray_coeffs, ray_offsets, depth_bounds, as in :class:`Projection`)
    of the Gaussians thickened by the screen-space dilation: each scale becomes
    sqrt(s^2 + eps2d (z / f)^2), z the mean's camera depth and f the mean focal length, the 3D
    counterpart of the ``eps2d`` pixels^2 added to the screen covariance. Ray-ordered compositing
    sorts by its depth (no gradient: the order is discrete).

    Flat splats facing the ray keep their plane's depth; one within a few degrees of edge-on gets
    the depth where the ray passes nearest its centre instead of where the ray crosses its plane.
    """
    K = K.to(means)
    rot_w2c, mean_c, z_safe, in_range = _camera_frame(means, world_to_camera, near, far)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    thickness = torch.sqrt(torch.as_tensor(eps2d, dtype=means.dtype)) * z_safe / focal
    thick_scales = torch.sqrt(scales**2 + thickness[:, None] ** 2)
    axes_c = rot_w2c @ quat_to_rotmat(quats)
    rs = axes_c * thick_scales[:, None, :]
    return _ray_depth_data(axes_c, thick_scales, rs @ rs.transpose(-1, -2), mean_c, z_safe, in_range, K)


def _screen_covariance(
    cov_c: Tensor,
    x: Tensor,
    y: Tensor,
    z: Tensor,
    intrinsics: tuple[Tensor, Tensor, Tensor, Tensor, Tensor],
    width: int,
    height: int,
    eps2d: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Entries (a, b, c) of the dilated screen covariance [[a, b], [b, c]] = J cov_c J^T +
    eps2d I, J the EWA Jacobian of the pinhole projection at the camera-frame mean (x, y, z);
    ``intrinsics`` = (fx, skew, cx, fy, cy), the entries of K."""
    fx, skew, cx, fy, cy = intrinsics
    # The Jacobian is evaluated with x/z, y/z limited to 1.3x the field of view, as in 3DGS,
    # so that Gaussians far outside the image do not get absurd footprints.
    lim_x_hi = FOV_CLAMP * (width - cx) / fx
    lim_x_lo = -FOV_CLAMP * cx / fx
    lim_y_hi = FOV_CLAMP * (height - cy) / fy
    lim_y_lo = -FOV_CLAMP * cy / fy
    xz = torch.minimum(torch.maximum(x / z, lim_x_lo), lim_x_hi)
    yz = torch.minimum(torch.maximum(y / z, lim_y_lo), lim_y_hi)
    zero = torch.zeros_like(z)
    inv_z = 1.0 / z
    jac = torch.stack(
        [
            fx * inv_z, skew * inv_z, -(fx * xz + skew * yz) * inv_z,
            zero, fy * inv_z, -fy * yz * inv_z,
        ],
        dim=-1,
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(-1, -2)
    return cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d


@torch.no_grad()
def _extents(opacities: Tensor, a: Tensor, c: Tensor, det: Tensor, in_range: Tensor) -> Tensor:
    """(N, 2) opacity-aware half-widths of the box where alpha >= 1/255; 0 for culled Gaussians.

    alpha >= 1/255 needs d^T conic d <= 2 ln(255 o), an ellipse whose axis-aligned bounding box
    has half-widths sqrt(2 ln(255 o) cov_xx), sqrt(2 ln(255 o) cov_yy). The 1e-4 relative slack
    keeps pixels exactly on the boundary despite rounding."""
    log_ratio = torch.log(opacities.detach().clamp_min(1e-30) / ALPHA_MIN).clamp_min(0.0)
    extents = (1 + EXTENT_SLACK) * torch.sqrt(2.0 * log_ratio[:, None] * torch.stack([a, c], dim=-1).detach())
    keep = in_range & (log_ratio > 0) & (det > 0)
    return torch.where(keep[:, None], extents, torch.zeros_like(extents))


def _ray_depth_data(
    axes_c: Tensor, scales: Tensor, cov_c: Tensor, mean_c: Tensor, z: Tensor, in_range: Tensor, K: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel depth data of :class:`Projection`: ray_coeffs Q = diag(s_min / s) R_c^T K^-1,
    ray_offsets b = diag(s_min / s) R_c^T mu_c and the +-DEPTH_CLAMP_SIGMAS sigma_z bounds around
    the (culling-safe) mean z."""
    # Dividing by s_min keeps the numbers O(1) for very flat Gaussians; the ratio is unchanged.
    rel_inv_scale = scales.min(dim=-1, keepdim=True).values / scales
    m = axes_c.transpose(-1, -2) * rel_inv_scale[..., None]
    ray_coeffs = m @ torch.linalg.inv(K)
    mean_c_safe = torch.where(in_range[:, None], mean_c, torch.ones_like(mean_c))
    ray_offsets = (m @ mean_c_safe[..., None])[..., 0]
    sigma_z = torch.sqrt(cov_c[:, 2, 2].clamp_min(1e-30))
    depth_bounds = torch.stack([z - DEPTH_CLAMP_SIGMAS * sigma_z, z + DEPTH_CLAMP_SIGMAS * sigma_z], dim=-1)
    return ray_coeffs, ray_offsets, depth_bounds
