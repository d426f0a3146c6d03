"""Back-project PatchMatch pixels into new Gaussians (PolarGS Dense seeding).

Each seed is a flat Gaussian on the estimated surface: its shortest axis is the PatchMatch normal
(world frame), its two tangent scales are the pixel footprint ``depth / focal`` times the
sampling stride (so neighbouring seeds overlap), its normal scale ``thin_ratio`` times that; the
colour is the observed training colour s0 / 2 at the pixel; the opacity is a finite constant.
Seeds are placed only where the current model is missing (rendered alpha below a threshold) or
wrong (rendered depth disagrees with PatchMatch), and at most ``max_new`` per call.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from torch import Tensor

from polargs_plugin.densify.homography import pixel_rays
from polargs_plugin.types import NewGaussians

__all__ = ["seed_mask", "seed_relative_depth", "plane_deviation", "frames_from_normals", "seed_gaussians"]


def seed_mask(
    keep: Tensor, depth: Tensor, rendered_depth: Tensor, rendered_alpha: Tensor, *,
    alpha_threshold: float = 0.5, relative_depth: float = 0.02,
    normal: Tensor | None = None, K: Tensor | None = None, max_plane_deviation: float | None = None,
    behind: bool = False,
) -> Tensor:
    """Filtered pixels where the render has a hole or a wrong surface, on a locally planar depth.

    Args:
        keep: (1, H, W) bool pixels that passed the filters; depth: (1, H, W) PatchMatch depth.
        rendered_depth, rendered_alpha: (1, H, W) from the current model.
        alpha_threshold: below it the render counts as a hole.
        relative_depth: |rendered - PatchMatch| / PatchMatch above it counts as a wrong surface.
        normal, K: (3, H, W) PatchMatch normal and (3, 3) intrinsics, for the planarity test.
        max_plane_deviation: seeds only where the 3x3 neighbours' PatchMatch depths stay within
            this fraction of the depth of the pixel's own plane (:func:`plane_deviation`); None =
            no such test. PatchMatch's patches straddle occlusion edges there and its depth lands
            between the surfaces; the multi-view filters, which compare against the renders, let
            such pixels through (docs/patchmatch.md "Seeding").
        behind: whether a PatchMatch depth *behind* an opaque rendered surface counts as a wrong
            surface too (``DensifyConfig.seed_behind_surface``, False by default as there). False
            seeds only holes and where PatchMatch's surface lies in front of the rendered one:
            behind an opaque surface a seed is hidden in this view, and there PatchMatch on a
            glossy surface has matched the mirror image of what it reflects.

    Returns:
        (1, H, W) bool.
    """
    hole = rendered_alpha < alpha_threshold
    gap = rendered_depth - depth
    wrong = (gap.abs() if behind else gap) > relative_depth * depth
    seeds = keep & (depth > 0) & (hole | wrong)
    if max_plane_deviation is not None:
        if normal is None or K is None:
            raise ValueError("seed_mask: max_plane_deviation needs the PatchMatch normal and K")
        seeds &= plane_deviation(depth, normal, K) <= max_plane_deviation
    return seeds


def seed_relative_depth(footprints: float, K: Tensor) -> float:
    """``footprints`` pixel footprints as a fraction of the depth (``seed_mask``'s ``relative_depth``):
    a pixel at depth z spans z / f, f the mean of f_x and f_y as in :func:`seed_gaussians`' scales."""
    return footprints / (0.5 * float(K[0, 0] + K[1, 1]))


def plane_deviation(depth: Tensor, normal: Tensor, K: Tensor) -> Tensor:
    """(1, H, W) how far the 3x3 neighbours' depths leave each pixel's own plane: the largest
    |D_q - z_q| / D_p over the neighbours q with a depth, where z_q is the depth at which q's ray
    meets the plane through the pixel's point with the pixel's normal (0 where the pixel has no
    depth; inf where a neighbour's ray is parallel to the plane; NaN for a zero normal).

    A tilted surface keeps its neighbours on its plane at any resolution and angle; an occlusion
    edge (a second surface in the neighbourhood) or a noisy depth does not.

    Args:
        depth: (1, H, W) camera-z depth (0 = none); normal: (3, H, W) camera-frame normal;
        K: (3, 3) intrinsics (pixel centres at +0.5).
    """
    height, width = depth.shape[-2:]
    rays = pixel_rays(K.to(depth), height, width)  # (3, H, W), X = depth * ray
    offset = depth[0] * (normal * rays).sum(0)  # n . X of the pixel's plane
    padded_depth = F.pad(depth, (1, 1, 1, 1))[0]
    padded_rays = F.pad(rays, (1, 1, 1, 1))
    worst = torch.zeros_like(offset)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            rows, cols = slice(1 + dy, 1 + dy + height), slice(1 + dx, 1 + dx + width)
            neighbour = padded_depth[rows, cols]
            on_plane = offset / (normal * padded_rays[:, rows, cols]).sum(0)
            deviation = torch.where(neighbour > 0, (neighbour - on_plane).abs() / depth[0], torch.zeros_like(offset))
            worst = torch.maximum(worst, deviation)
    return torch.where(depth[0] > 0, worst, torch.zeros_like(worst))[None]


def frames_from_normals(normals: Tensor) -> Tensor:
    """(N, 3, 3) right-handed rotations whose third column is the unit normal (N, 3)."""
    n = F.normalize(normals, dim=-1)
    # helper axis: the world axis least aligned with n keeps the cross product well conditioned
    helper = torch.zeros_like(n)
    helper.scatter_(1, n.abs().argmin(1, keepdim=True), 1.0)
    t1 = F.normalize(torch.linalg.cross(helper, n, dim=-1), dim=-1)
    t2 = torch.linalg.cross(n, t1, dim=-1)
    return torch.stack([t1, t2, n], dim=-1)


def seed_gaussians(
    depth: Tensor, normal: Tensor, image: Tensor, K: Tensor, world_to_camera: Tensor, mask: Tensor,
    *, stride: int = 2, max_new: int = 5000, initial_opacity: float = 0.5, thin_ratio: float = 0.1,
    generator: torch.Generator | None = None,
) -> NewGaussians:
    """New Gaussians at the masked pixels of one view (on a ``stride`` grid, at most ``max_new``).

    Args:
        depth: (1, H, W) camera-z depth; normal: (3, H, W) camera-frame normal.
        image: (C, H, W) colour in [0, 1] (C = 1 is repeated to RGB).
        K: (3, 3); world_to_camera: (4, 4).
        mask: (1, H, W) bool pixels to seed (e.g. :func:`seed_mask`).
        stride: pixel spacing of the seeds; max_new: cap (random subset beyond it).
        initial_opacity: opacity in (0, 1); thin_ratio: normal scale / tangent scale.
        generator: for the random subset.

    Returns:
        NewGaussians in world coordinates (possibly empty), on ``depth``'s device.
    """
    if not 0.0 < initial_opacity < 1.0:
        raise ValueError(f"initial_opacity must lie in (0, 1), got {initial_opacity}")
    dev = depth.device
    sub = torch.zeros_like(mask)
    sub[:, ::stride, ::stride] = True
    idx = (mask & sub & (depth > 0))[0].reshape(-1).nonzero().squeeze(-1)
    if idx.numel() > max_new:
        pick = torch.randperm(idx.numel(), generator=generator, device="cpu")[:max_new]
        idx = idx[pick.to(dev)]
    h, w = depth.shape[-2:]
    K32 = K.to(dev, torch.float32)
    R = world_to_camera[:3, :3].to(dev, torch.float32)
    t = world_to_camera[:3, 3].to(dev, torch.float32)
    d = depth.reshape(-1)[idx]
    rays = pixel_rays(K32, h, w).reshape(3, -1)[:, idx]
    means = ((d * rays).T - t) @ R  # R^T (X_cam - t), row-wise
    n_world = normal.reshape(3, -1)[:, idx].T.float() @ R
    quats = rotation_matrix_to_quaternion(frames_from_normals(n_world).contiguous())
    footprint = d * stride / (0.5 * (K32[0, 0] + K32[1, 1]))
    scales = torch.stack([footprint, footprint, thin_ratio * footprint], -1)
    colours = image.reshape(image.shape[0], -1)[:, idx].T.float()
    if colours.shape[1] == 1:
        colours = colours.expand(-1, 3)
    opacities = torch.full_like(d, initial_opacity)
    return NewGaussians(means, quats, scales, colours.clamp(0, 1).contiguous(), opacities)
