"""Plane-induced homographies between a reference and a source camera (OpenCV frames).

Sign conventions (derived here, pinned by tests/test_patchmatch_homography.py):

- ``(R, t)`` is the reference-to-source pose: a reference-camera point ``X_r`` maps to
  ``X_s = R X_r + t``, so ``R = R_s R_r^T`` and ``t = t_s - R t_r`` for world-to-camera
  ``[R_r | t_r]`` and ``[R_s | t_s]``.
- The plane through the reference pixel ``p`` at camera-z depth ``d`` with unit normal ``n``
  (facing the camera, ``n . K^-1 p~ < 0``) is ``{X : n . X = -d_plane}`` with
  ``d_plane = -d (n . K_ref^-1 p~) > 0``, the camera-to-plane distance
  (:func:`~polargs_plugin.geometry.ray_plane_distance`; :func:`~polargs_plugin.geometry.ray_plane_depth`
  goes back).
- A pixel ``q`` on that plane back-projects to ``X_r = -d_plane K^-1 q~ / (n . K^-1 q~)``, hence
  ``X_s ~ (R - t n^T / d_plane) K_ref^-1 q~`` and
  ``H = K_s (R - t n^T / d_plane) K_ref^-1`` maps reference pixels to source pixels (COLMAP writes
  the same matrix with ``+`` under its opposite plane-offset sign).

Pixel centres are at ``+0.5`` (docs/conventions.md): pixel ``(u, v)`` is ``p~ = (u + 0.5, v + 0.5, 1)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "relative_pose",
    "pixel_grid",
    "pixel_rays",
    "plane_homography",
]


def relative_pose(world_to_ref: Tensor, world_to_src: Tensor) -> tuple[Tensor, Tensor]:
    """Reference-to-source rotation and translation.

    Args:
        world_to_ref: (4, 4) world-to-camera of the reference view.
        world_to_src: (..., 4, 4) world-to-camera of the source views.

    Returns:
        R: (..., 3, 3) and t: (..., 3) with ``X_s = R X_r + t``.
    """
    r_ref, t_ref = world_to_ref[:3, :3], world_to_ref[:3, 3]
    r_src, t_src = world_to_src[..., :3, :3], world_to_src[..., :3, 3]
    rot = r_src @ r_ref.T
    trans = t_src - (rot @ t_ref.unsqueeze(-1)).squeeze(-1)
    return rot, trans


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """(3, H, W) homogeneous pixel-centre coordinates ``(u + 0.5, v + 0.5, 1)``."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype) + 0.5,
        torch.arange(width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v, torch.ones_like(u)])


def pixel_rays(K: Tensor, height: int, width: int) -> Tensor:
    """(3, H, W) rays ``K^-1 p~`` with unit z, so that ``X = depth * ray``."""
    grid = pixel_grid(height, width, device=K.device, dtype=K.dtype)
    return torch.einsum("ij,jhw->ihw", torch.linalg.inv(K), grid)


def plane_homography(
    K_ref: Tensor, K_src: Tensor, R: Tensor, t: Tensor, normal: Tensor, d_plane: Tensor
) -> Tensor:
    """``H = K_s (R - t n^T / d_plane) K_ref^-1`` (reference pixels -> source pixels).

    Args:
        K_ref: (3, 3) reference intrinsics.
        K_src: (..., 3, 3) source intrinsics.
        R: (..., 3, 3), t: (..., 3) reference-to-source pose (:func:`relative_pose`).
        normal: (..., 3) plane normal in the reference camera frame.
        d_plane: (...,) positive plane distance (:func:`~polargs_plugin.geometry.ray_plane_distance`).

    Returns:
        (..., 3, 3) homographies acting on homogeneous pixel coordinates.
    """
    outer = t.unsqueeze(-1) * normal.unsqueeze(-2) / d_plane[..., None, None]
    return K_src @ (R - outer) @ torch.linalg.inv(K_ref)
