"""A stand-in for Gaussian Opacity Fields' (GOF) training objects, written for these tests.

Built on :mod:`standins.inria` (same ``Camera`` and ``Scene``); what GOF adds, with its
attribute names and conventions, rendered with the bundled reference rasterizer:

- ``GaussianModel``: ``filter_3D`` (N, 1), absent until ``compute_3D_filter(cameras)`` first runs;
  ``get_scaling_with_3D_filter`` / ``get_opacity_with_3D_filter``; the absolute-gradient
  statistics ``xyz_gradient_accum_abs`` and ``xyz_gradient_accum_abs_max``; the six-argument
  ``densification_postfix`` that resets every statistic.
- ``render(camera, pc, pipe, bg_color, kernel_size, scaling_modifier=1.0, override_color=None,
  subpixel_offset=None)`` (``kernel_size`` has no default, as in GOF) -> dict with ``render``
  (9, H, W) = RGB with background, alpha-weighted camera-frame normal facing the camera,
  median depth, alpha, distortion (zeros here); ``viewspace_points``; ``visibility_filter``
  (bool (N,)); ``radii``. It renders the 3D-filtered scales and opacities, so a ``filter_3D``
  of the wrong length fails as GOF's render does.

Differences from GOF, none of which the adapter reads: ``kernel_size`` is accepted but the
reference rasterizer's fixed 0.3 px^2 low-pass is used instead; normals are the Gaussians'
shortest axes (GOF's are per-ray normals, the same for flat Gaussians); the median depth is 0 where
transmittance never drops below 0.5; ``viewspace_points`` is the rasterizer's (N, 2) ``means2d``
and the "absolute" statistic is the L1 norm of its gradient (GOF sums per-pixel absolute
gradients in its CUDA backward).
"""

from __future__ import annotations

import math

import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from standins import inria
from standins.inria import Camera, Scene, l1_ssim_loss  # noqa: F401  (re-exported for the tests)

# GOF's compute_3D_filter: points closer than this to a camera do not count for it
FILTER_NEAR = 0.2
# ... and points this far outside the image (fraction of its size) still count
FILTER_MARGIN = 0.15
# filter std = sqrt(this) pixels at the closest distance, in world units
FILTER_VARIANCE_PX = 0.2


class GaussianModel(inria.GaussianModel):
    """GOF-shaped model: 3D filter, absolute-gradient statistics, six-argument postfix."""

    def __init__(self, points: torch.Tensor, colors: torch.Tensor, sh_degree: int = 1):
        super().__init__(points, colors, sh_degree, postfix_arguments=6)
        self.filter_3D_computations = 0

    def reset_statistics(self) -> None:
        super().reset_statistics()
        n = self._xyz.shape[0]
        self.xyz_gradient_accum_abs = torch.zeros(n, 1)
        self.xyz_gradient_accum_abs_max = torch.zeros(n, 1)

    # ------------------------------------------------------------------- 3D filter
    def compute_3D_filter(self, cameras) -> None:
        """Per Gaussian: the smallest camera z over the cameras that see it (in front of
        FILTER_NEAR, inside the image grown by FILTER_MARGIN), divided by the largest focal
        length, times sqrt(FILTER_VARIANCE_PX); Gaussians no camera sees take the largest value."""
        with torch.no_grad():
            xyz = self._xyz.detach()
            nearest = torch.full((xyz.shape[0],), math.inf)
            focal = 0.0
            for camera in cameras:
                w2c = camera.world_view_transform.T
                cam = xyz @ w2c[:3, :3].T + w2c[:3, 3]
                K = camera.intrinsics()
                z = cam[:, 2]
                u = cam[:, 0] / z.clamp_min(1e-3) * K[0, 0] + K[0, 2]
                v = cam[:, 1] / z.clamp_min(1e-3) * K[1, 1] + K[1, 2]
                w, h = camera.image_width, camera.image_height
                sees = (
                    (z > FILTER_NEAR)
                    & (u >= -FILTER_MARGIN * w) & (u <= (1 + FILTER_MARGIN) * w)
                    & (v >= -FILTER_MARGIN * h) & (v <= (1 + FILTER_MARGIN) * h)
                )
                nearest = torch.where(sees, torch.minimum(nearest, z), nearest)
                focal = max(focal, float(K[0, 0]))
            seen = torch.isfinite(nearest)
            if bool(seen.any()):
                nearest[~seen] = nearest[seen].max()
            else:
                nearest[:] = 1.0
            self.filter_3D = (nearest / focal * math.sqrt(FILTER_VARIANCE_PX))[:, None]
            self.filter_3D_computations += 1

    @property
    def get_scaling_with_3D_filter(self):
        return torch.sqrt(self.get_scaling.square() + self.filter_3D.square())

    @property
    def get_opacity_with_3D_filter(self):
        squared = self.get_scaling.square()
        ratio = squared.prod(dim=1) / (squared + self.filter_3D.square()).prod(dim=1)
        return self.get_opacity * torch.sqrt(ratio)[:, None]

    # ---------------------------------------------------------------- densification
    def add_densification_stats(self, viewspace_points, visibility_filter):
        grad = viewspace_points.grad[visibility_filter]
        self.xyz_gradient_accum[visibility_filter] += grad[:, :2].norm(dim=-1, keepdim=True)
        absolute = grad.abs().sum(dim=-1, keepdim=True)
        self.xyz_gradient_accum_abs[visibility_filter] += absolute
        self.xyz_gradient_accum_abs_max[visibility_filter] = torch.maximum(
            self.xyz_gradient_accum_abs_max[visibility_filter], absolute
        )
        self.denom[visibility_filter] += 1

    def densification_postfix(self, new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                              new_rotation):
        super().densification_postfix(new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                                      new_rotation)


def render(viewpoint_camera, pc, pipe, bg_color, kernel_size, scaling_modifier=1.0, override_color=None,
           subpixel_offset=None):
    """GOF's render() on the bundled rasterizer: one (9, H, W) tensor, 3D-filtered Gaussians."""
    if not isinstance(kernel_size, (int, float)):
        raise TypeError(f"kernel_size must be a number, got {type(kernel_size).__name__}")
    camera = viewpoint_camera
    K = camera.intrinsics()
    w2c = camera.world_view_transform.T
    opacity = pc.get_opacity_with_3D_filter[:, 0]
    scales = pc.get_scaling_with_3D_filter * scaling_modifier
    if override_color is not None:
        colors = override_color
    else:
        colors = pc.get_features[:, : (pc.active_sh_degree + 1) ** 2]
    out = rasterize(pc.get_xyz, pc.get_rotation, scales, opacity, colors, K, w2c,
                    camera.image_width, camera.image_height, background=bg_color)
    distortion = torch.zeros_like(out.alpha)
    image = torch.cat([out.color, out.normal, out.median_depth, out.alpha, distortion], dim=0)
    return {
        "render": image,
        "viewspace_points": out.means2d,
        "visibility_filter": out.radii > 0,
        "radii": out.radii,
    }


def make_model(points, colors, sh_degree: int = 1) -> GaussianModel:
    return GaussianModel(points, colors, sh_degree)
