"""Render-side translation: per-Gaussian normals for an extra render pass, depth conversions.

Any rasterizer that can composite extra per-Gaussian channels (graphdeco's ``colors_precomp``
pass, gsplat's extra ``colors`` channels) renders the maps of the :class:`RenderOut` contract
from :func:`aux_channels`; the upstream depth flavours convert to the contract's camera z here.

Conventions (docs/conventions.md): OpenCV camera frame (x right, y down, z forward), K with
pixel centres at +0.5, depth = camera z, normals = unit camera-frame vectors facing the camera.
"""

from __future__ import annotations

import torch
from torch import Tensor

from polargs_plugin.geometry import depth_from_plane, plane_distances, quat_to_rotmat, shortest_axis_normals
from polargs_plugin.types import RenderOut

__all__ = [
    "AUX_CHANNELS",
    "gaussian_normals",
    "aux_channels",
    "render_out_from_aux",
    "clamped_aux_colors",
    "render_out_from_clamped_aux",
    "depth_from_inverse",
    "depth_from_accumulated",
]

AUX_CHANNELS = ("normal_x", "normal_y", "normal_z", "alpha", "z", "distance")
"""Order of the channels of :func:`aux_channels` (and of the image a rasterizer makes of them)."""

_EPS = 1e-6


def gaussian_normals(means: Tensor, quats: Tensor, scales: Tensor, world_to_camera: Tensor) -> Tensor:
    """Per-Gaussian camera-frame normals (shortest axis, facing the camera).

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations (any norm).
        scales: (N, 3) positive scales (activated).
        world_to_camera: (4, 4) OpenCV world-to-camera transform (not transposed).

    Returns:
        (N, 3) unit normals in the camera frame, differentiable w.r.t. ``means`` only through
        the facing sign (piecewise constant) and w.r.t. ``quats`` through the rotation.
    """
    w2c = world_to_camera.to(means)
    means_cam = means @ w2c[:3, :3].T + w2c[:3, 3]
    axes_cam = w2c[:3, :3] @ quat_to_rotmat(quats)
    return shortest_axis_normals(axes_cam, scales, means_cam)


def aux_channels(means: Tensor, quats: Tensor, scales: Tensor, world_to_camera: Tensor) -> Tensor:
    """Per-Gaussian colours for one extra render pass that yields normal, alpha and depth maps.

    Composited with background 0 and no clamp, the (6, H, W) image of these channels is
    (sum w n, sum w, sum w z, sum w d): pass it to :func:`render_out_from_aux`.

    Args:
        means: (N, 3) world positions, as :func:`gaussian_normals`.
        quats: (N, 4) wxyz rotations, as :func:`gaussian_normals`.
        scales: (N, 3) activated scales, as :func:`gaussian_normals`.
        world_to_camera: (4, 4) OpenCV world-to-camera transform, as :func:`gaussian_normals`.

    Returns:
        (N, 6) channels in :data:`AUX_CHANNELS` order: camera-frame normal n (3), 1, camera z,
        plane distance d = -n . mean_cam (the Gaussian's plane n . x = -d; PGSR's distance).
    """
    w2c = world_to_camera.to(means)
    z = means @ w2c[2, :3] + w2c[2, 3]
    normals = gaussian_normals(means, quats, scales, w2c)
    distance = plane_distances(normals, means, w2c)
    return torch.cat([normals, torch.ones_like(z)[:, None], z[:, None], distance[:, None]], dim=-1)


def render_out_from_aux(
    color: Tensor,
    aux: Tensor,
    *,
    K: Tensor | None = None,
    median_depth: Tensor | None = None,
    means2d: Tensor | None = None,
    radii: Tensor | None = None,
) -> RenderOut:
    """Assemble a :class:`RenderOut` from a colour image and the rendered :func:`aux_channels`.

    Args:
        color: (3, H, W) the trainer's rendered colour.
        aux: (6, H, W) the composited aux channels (background 0, not clamped); channel-last
            (H, W, 6) images (gsplat) must be permuted first.
        K: (3, 3) intrinsics of the render; given, the RenderOut also has the unbiased plane
            depth (:func:`~polargs_plugin.geometry.depth_from_plane`), which L_dn then uses.
        median_depth: passed through to the RenderOut.
        means2d: passed through to the RenderOut.
        radii: passed through to the RenderOut.

    Returns:
        RenderOut with depth = sum w z / alpha (0 where alpha ~ 0), the alpha-weighted normal
        (not renormalised, as the contract says), alpha and, with ``K``, plane_depth.
    """
    if aux.dim() != 3 or aux.shape[0] != len(AUX_CHANNELS) or aux.shape[-2:] != color.shape[-2:]:
        raise ValueError(
            f"aux must be ({len(AUX_CHANNELS)}, H, W) matching color {tuple(color.shape)}, got {tuple(aux.shape)}"
        )
    alpha = aux[3:4]
    return RenderOut(
        color=color,
        depth=depth_from_accumulated(aux[4:5], alpha),
        normal=aux[:3],
        alpha=alpha,
        median_depth=median_depth,
        plane_depth=None if K is None else depth_from_plane(aux[5:6], aux[:3], K),
        means2d=means2d,
        radii=radii,
    )


def clamped_aux_colors(
    means: Tensor, quats: Tensor, scales: Tensor, world_to_camera: Tensor
) -> tuple[Tensor, Tensor, float]:
    """:func:`aux_channels` encoded for a renderer that takes 3 colour channels and clamps its
    output to [0, 1] (graphdeco's ``render(..., override_color=...)``, its forks').

    Two passes with background 0: ``normal_colors`` = (n + 1) / 2 and ``alpha_depth_colors`` =
    (1, z / z_scale, d / z_scale) (d the plane distance), each in [0, 1] per Gaussian, so their
    composites (at most alpha <= 1) are never clamped and stay differentiable.
    :func:`render_out_from_clamped_aux` decodes them.

    Args:
        means: (N, 3) world positions, as :func:`gaussian_normals`.
        quats: (N, 4) wxyz rotations, as :func:`gaussian_normals`.
        scales: (N, 3) activated scales, as :func:`gaussian_normals`.
        world_to_camera: (4, 4) OpenCV world-to-camera transform, as :func:`gaussian_normals`.

    Returns:
        ``(normal_colors (N, 3), alpha_depth_colors (N, 3), z_scale)``; ``z_scale`` is just above the
        largest camera z and plane distance of the Gaussians in front of the camera (1 if there are none).
    """
    aux = aux_channels(means, quats, scales, world_to_camera)
    z, distance = aux[:, 4], aux[:, 5]
    in_front = z.detach() > 0
    largest = torch.maximum(z.detach(), distance.detach())[in_front]
    z_scale = float(largest.max()) * 1.001 if bool(in_front.any()) else 1.0
    normal_colors = (aux[:, :3] + 1) / 2
    alpha_depth_colors = torch.stack(
        [aux[:, 3], (z / z_scale).clamp(0, 1), (distance / z_scale).clamp(0, 1)], dim=-1
    )
    return normal_colors, alpha_depth_colors, z_scale


def render_out_from_clamped_aux(
    color: Tensor,
    normal_image: Tensor,
    alpha_depth_image: Tensor,
    z_scale: float,
    K: Tensor | None = None,
    **passthrough: Tensor | None,
) -> RenderOut:
    """Decode the two passes of :func:`clamped_aux_colors` into a :class:`RenderOut`.

    Args:
        color: (3, H, W) the trainer's rendered colour.
        normal_image: (3, H, W) composite of ``normal_colors`` = (sum w n + alpha) / 2.
        alpha_depth_image: (3, H, W) composite of ``alpha_depth_colors`` = (alpha, sum w z / z_scale,
            sum w d / z_scale).
        z_scale: the value :func:`clamped_aux_colors` returned.
        K: (3, 3) intrinsics: the RenderOut then has the plane depth too (:func:`render_out_from_aux`).
        **passthrough: ``median_depth``, ``means2d``, ``radii`` for the RenderOut.

    Returns:
        RenderOut as :func:`render_out_from_aux` makes it.
    """
    alpha = alpha_depth_image[0:1]
    aux = torch.cat([2 * normal_image - alpha, alpha, alpha_depth_image[1:3] * z_scale])
    return render_out_from_aux(color, aux, K=K, **passthrough)


def depth_from_accumulated(accumulated: Tensor, alpha: Tensor) -> Tensor:
    """Expected camera z from an accumulated depth sum w z (gsplat ``D``, GaussianPro).

    Args:
        accumulated: (1, H, W) sum of w z.
        alpha: (1, H, W) sum of w.

    Returns:
        (1, H, W) sum w z / sum w, 0 where alpha < 1e-6.
    """
    covered = alpha > _EPS
    return torch.where(covered, accumulated / alpha.clamp_min(_EPS), torch.zeros_like(accumulated))


def depth_from_inverse(inverse_depth: Tensor, alpha: Tensor) -> Tensor:
    """Camera z from 3DGS's accumulated inverse depth sum w / z (graphdeco ``render_pkg["depth"]``).

    sum w / z divided by alpha is the alpha-normalised mean inverse depth; its reciprocal is the
    harmonic-mean depth, which equals the expected depth for a single surface layer.

    Args:
        inverse_depth: (1, H, W) sum of w / z (not divided by alpha).
        alpha: (1, H, W) sum of w (from an extra pass: graphdeco returns no alpha).

    Returns:
        (1, H, W) alpha / sum(w / z), 0 where alpha < 1e-6 or the sum is not positive.
    """
    valid = (alpha > _EPS) & (inverse_depth > _EPS * _EPS)
    return torch.where(valid, alpha / inverse_depth.clamp_min(_EPS * _EPS), torch.zeros_like(inverse_depth))
