"""Choose source views for a reference view from camera geometry (viewing angle and baseline).

Score of a source ``j`` for the reference ``i`` looking at a scene point ``X``: the triangulation
angle ``theta`` between the rays ``X - c_i`` and ``X - c_j`` must lie in
``[min_angle, max_angle]`` (too small: no depth resolution; too large: the patch distorts and
occludes), and the source must look the same way (optical axes within 90 degrees). Inside that
range the score is ``exp(-(theta - target)^2 / (2 * spread^2))``, so views near the target
baseline come first (COLMAP and Gipuma select by the same two quantities).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["scene_center", "select_sources"]


def _centres_and_axes(world_to_camera: Tensor) -> tuple[Tensor, Tensor]:
    rot = world_to_camera[..., :3, :3]
    trans = world_to_camera[..., :3, 3]
    centres = -(rot.transpose(-1, -2) @ trans.unsqueeze(-1)).squeeze(-1)
    axes = rot[..., 2, :]  # camera +z in world coordinates
    return centres, axes


def scene_center(world_to_camera: Tensor) -> Tensor:
    """(3,) least-squares point closest to every camera's optical axis.

    Args:
        world_to_camera: (V, 4, 4) cameras.
    """
    centres, axes = _centres_and_axes(world_to_camera.to(torch.float64))
    eye = torch.eye(3, dtype=torch.float64, device=centres.device)
    proj = eye - axes.unsqueeze(-1) * axes.unsqueeze(-2)  # (V, 3, 3) orthogonal to each axis
    lhs = proj.sum(0)
    rhs = (proj @ centres.unsqueeze(-1)).sum(0).squeeze(-1)
    return torch.linalg.lstsq(lhs, rhs.unsqueeze(-1)).solution.squeeze(-1)


def select_sources(
    ref_world_to_camera: Tensor,
    world_to_cameras: Tensor,
    num_sources: int,
    point: Tensor,
    *,
    exclude: int | None = None,
    target_angle_deg: float = 15.0,
    spread_deg: float = 10.0,
    min_angle_deg: float = 2.0,
    max_angle_deg: float = 60.0,
) -> list[int]:
    """Indices of up to ``num_sources`` source views, best first.

    Args:
        ref_world_to_camera: (4, 4) reference camera.
        world_to_cameras: (V, 4, 4) candidate cameras (the reference may be among them).
        num_sources: how many to return.
        point: (3,) world point the reference looks at (e.g. :func:`scene_center` or the
            back-projected median rendered depth).
        exclude: index to skip (the reference itself).
        target_angle_deg, spread_deg: preferred triangulation angle and its tolerance.
        min_angle_deg, max_angle_deg: hard limits on the triangulation angle.

    Returns:
        list of indices; empty if no view qualifies.
    """
    c_ref, a_ref = _centres_and_axes(ref_world_to_camera.to(torch.float64))
    centres, axes = _centres_and_axes(world_to_cameras.to(torch.float64))
    point = point.to(torch.float64)
    ray_ref = torch.nn.functional.normalize(point - c_ref, dim=-1)
    rays = torch.nn.functional.normalize(point - centres, dim=-1)
    theta = torch.rad2deg(torch.arccos((rays @ ray_ref).clamp(-1.0, 1.0)))
    ok = (theta >= min_angle_deg) & (theta <= max_angle_deg) & ((axes @ a_ref) > 0)
    if exclude is not None:
        ok[exclude] = False
    score = torch.exp(-((theta - target_angle_deg) ** 2) / (2 * spread_deg**2))
    score = torch.where(ok, score, torch.full_like(score, -math.inf))
    order = torch.argsort(score, descending=True)
    return [int(i) for i in order[:num_sources] if torch.isfinite(score[i])]
