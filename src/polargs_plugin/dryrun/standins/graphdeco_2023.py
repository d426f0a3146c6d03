"""Stand-in for graphdeco-inria's ``diff_gaussian_rasterization`` as the 2023 trainers use it
(graphdeco 472689c and the forks built on it): ``GaussianRasterizer(...)(means3D, means2D,
opacities, shs | colors_precomp, scales, rotations)`` returns ``(color (3, H, W) with the
background, radii (N,) int32)``; ``means2D.grad[:, :2]`` is dL/d(projected mean) in NDC units.

Approximation: none beyond the reference rasterizer's (float64 transmittance, exact per-pixel
alpha); the projection matrix is not read (the frustum comes from the FoVs, as upstream builds it).
"""

from __future__ import annotations

from torch import Tensor

from polargs_plugin.dryrun.standins.common import RasterSettings, SettingsRasterizer, check_inputs, render_setting, view_colors, with_background

__all__ = ["GaussianRasterizationSettings", "GaussianRasterizer"]


#: The upstream raster setting (same fields, same order).
GaussianRasterizationSettings = RasterSettings


class GaussianRasterizer(SettingsRasterizer):
    """``forward`` returns (color, radii) like the 2023 CUDA rasterizer."""

    def forward(self, means3D: Tensor, means2D: Tensor, opacities: Tensor, shs: Tensor | None = None,
                colors_precomp: Tensor | None = None, scales: Tensor | None = None, rotations: Tensor | None = None,
                cov3D_precomp: Tensor | None = None) -> tuple[Tensor, Tensor]:
        s = self.raster_settings
        check_inputs(shs, colors_precomp, scales, rotations, cov3D_precomp)
        colors = view_colors(means3D, shs, colors_precomp, s.sh_degree, s.campos)
        out = render_setting(s, means3D, means2D, opacities, colors, scales, rotations)
        return with_background(out.features, out.alpha, s.bg), out.radii
