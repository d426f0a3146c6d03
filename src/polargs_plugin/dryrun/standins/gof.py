"""Stand-in for GOF's ``diff_gaussian_rasterization`` fork (autonomousvision/gaussian-opacity-fields
5245b20): the setting adds ``kernel_size`` and ``subpixel_offset``; ``forward`` also takes
``view2gaussian_precomp`` and returns ``(render (9, H, W), radii (N,) int32)`` with GOF's channels

====  ===========================================================================
0-2   RGB, background included
3-5   sum of w * unit normal, camera frame, facing the camera (not renormalised)
6     camera z on the pixel's ray of the last Gaussian blended while T > 0.5
7     accumulated alpha
8     depth distortion over NDC-mapped depths, divided by alpha^2 + 1e-7
====  ===========================================================================

``means2D.grad[:, :2]`` is dL/d(projected mean) in NDC units and ``means2D.grad[:, 2]`` the
absolute gradient of GOF's densification: the sum over pixels of |dL/dx| + |dL/dy|, each in NDC
units. ``kernel_size`` dilates the screen covariance and scales each opacity by
sqrt(det(cov2D) / det(cov2D + kernel_size I)), as GOF's preprocessing does.

Approximations (the rest is exact to the reference rasterizer): GOF evaluates each Gaussian's
alpha, depth and normal at the maximum of the 3D Gaussian along the pixel's ray (ray-Gaussian
intersection through ``view2gaussian``); the stand-in uses the EWA screen-space alpha, the same
ray maximum for the depth, and the Gaussian's shortest axis for the normal. ``view2gaussian_precomp``
is accepted and not read; a non-zero ``subpixel_offset`` is refused (GOF's training passes zeros).
``integrate`` (mesh extraction) is not provided.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from polargs_plugin.dryrun.standins.common import SettingsRasterizer, check_inputs, render_setting, view_colors, with_background

__all__ = ["GaussianRasterizationSettings", "GaussianRasterizer", "CHANNELS"]

CHANNELS = ("r", "g", "b", "normal_x", "normal_y", "normal_z", "median_depth", "alpha", "distortion")
"""The channels of the returned render, in GOF's order (``OUTPUT_CHANNELS`` 9)."""


class GaussianRasterizationSettings(NamedTuple):
    """GOF's raster setting (same fields, same order)."""

    image_height: int
    image_width: int
    tanfovx: float
    tanfovy: float
    kernel_size: float
    subpixel_offset: Tensor
    bg: Tensor
    scale_modifier: float
    viewmatrix: Tensor
    projmatrix: Tensor
    sh_degree: int
    campos: Tensor
    prefiltered: bool
    debug: bool


class GaussianRasterizer(SettingsRasterizer):
    """``forward`` returns (render (9, H, W), radii) like GOF's CUDA rasterizer."""

    def forward(self, means3D: Tensor, means2D: Tensor, opacities: Tensor, shs: Tensor | None = None,
                colors_precomp: Tensor | None = None, scales: Tensor | None = None, rotations: Tensor | None = None,
                cov3D_precomp: Tensor | None = None, view2gaussian_precomp: Tensor | None = None) -> tuple[Tensor, Tensor]:
        s = self.raster_settings
        check_inputs(shs, colors_precomp, scales, rotations, cov3D_precomp)
        offset = s.subpixel_offset
        if offset is not None and offset.numel() > 0 and bool(offset.detach().abs().max() > 0):
            raise NotImplementedError("the CPU stand-in renders at pixel centres only (subpixel_offset must be zeros)")
        colors = view_colors(means3D, shs, colors_precomp, s.sh_degree, s.campos)
        out = render_setting(s, means3D, means2D, opacities, colors, scales, rotations, screen_abs=means2D[:, 2:3],
                             eps2d=float(s.kernel_size), compensate=True, normalize_distortion=True)
        render = torch.cat([
            with_background(out.features, out.alpha, s.bg), out.normal, out.median_depth, out.alpha, out.distortion,
        ])
        return render, out.radii
