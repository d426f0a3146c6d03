"""A stand-in for 2DGS's (hbb1/2d-gaussian-splatting) training objects, written for these tests.

Built on :mod:`standins.inria` (same ``Camera`` and ``Scene``); what 2DGS changes, with its
attribute names and conventions, rendered with the bundled reference rasterizer:

- ``GaussianModel``: surfels, ``_scaling`` (N, 2) log scales (``get_scaling`` (N, 2)), the
  six-argument ``densification_postfix`` (2DGS forks the 2023 loop).
- ``render(camera, pc, pipe, bg_color, scaling_modifier=1.0, override_color=None)`` -> dict with
  ``render`` (RGB with background), ``viewspace_points``, ``visibility_filter`` (bool (N,)),
  ``radii`` and 2DGS's maps: ``rend_alpha``, ``rend_normal`` (alpha-weighted, facing the camera,
  WORLD frame), ``rend_dist`` (zeros here), ``surf_depth`` (camera z) and ``surf_normal``.

Differences from 2DGS, none of which the adapter reads: surfels are rendered as Gaussians of
thickness :data:`THICKNESS` (the reference rasterizer splats 3D Gaussians, 2DGS intersects rays
with the surfel planes); ``surf_depth`` is the expected depth (2DGS's ``depth_ratio`` 0);
``surf_normal`` is the rendered normal (2DGS derives it from the depth map).
"""

from __future__ import annotations

import torch
from torch import nn

from polargs_plugin.backends.reference.rasterizer import rasterize
from standins import inria
from standins.inria import Camera, Scene, l1_ssim_loss  # noqa: F401  (re-exported for the tests)

THICKNESS = 1e-6
"""Third scale the surfels are rendered with (world units)."""


class GaussianModel(inria.GaussianModel):
    """2DGS-shaped model: two log scales per surfel, six-argument postfix."""

    def __init__(self, points: torch.Tensor, colors: torch.Tensor, sh_degree: int = 1):
        super().__init__(points, colors, sh_degree, postfix_arguments=6)
        surfel = nn.Parameter(self._scaling.detach()[:, :2].clone())
        group = next(g for g in self.optimizer.param_groups if g["name"] == "scaling")
        group["params"][0] = surfel
        self._scaling = surfel

    def add_densification_stats(self, viewspace_points, visibility_filter):
        grad = viewspace_points.grad[visibility_filter]
        self.xyz_gradient_accum[visibility_filter] += grad[:, :2].norm(dim=-1, keepdim=True)
        self.denom[visibility_filter] += 1


def render(viewpoint_camera, pc, pipe, bg_color, scaling_modifier=1.0, override_color=None):
    """2DGS's render() on the bundled rasterizer: colour plus the surfel maps, normals in world."""
    camera = viewpoint_camera
    K = camera.intrinsics()
    w2c = camera.world_view_transform.T
    surfel = pc.get_scaling * scaling_modifier
    if surfel.shape[1] != 2:
        raise RuntimeError(f"2DGS surfels have 2 scales, got {surfel.shape[1]}")
    scales = torch.cat([surfel, torch.full_like(surfel[:, :1], THICKNESS)], dim=1)
    colors = override_color if override_color is not None else pc.get_features[:, : (pc.active_sh_degree + 1) ** 2]
    out = rasterize(pc.get_xyz, pc.get_rotation, scales, pc.get_opacity[:, 0], colors, K, w2c,
                    camera.image_width, camera.image_height, background=bg_color)
    normal_world = torch.einsum("ji,jhw->ihw", w2c[:3, :3], out.normal)  # R^T n: camera -> world
    return {
        "render": out.color,
        "viewspace_points": out.means2d,
        "visibility_filter": out.radii > 0,
        "radii": out.radii,
        "rend_alpha": out.alpha,
        "rend_normal": normal_world,
        "rend_dist": torch.zeros_like(out.alpha),
        "surf_depth": out.depth,
        "surf_normal": normal_world,
    }


def make_model(points, colors, sh_degree: int = 1) -> GaussianModel:
    return GaussianModel(points, colors, sh_degree)
