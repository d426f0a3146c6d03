"""Stand-in for 2DGS's ``diff_surfel_rasterization`` (hbb1/diff-surfel-rasterization, as
hbb1/2d-gaussian-splatting 1920a23 uses it): ``forward(means3D, means2D, opacities, shs |
colors_precomp, scales (N, 2), rotations)`` returns ``(color (3, H, W) with the background,
radii (N,) int32, allmap (7, H, W))`` with 2DGS's rows

====  =========================================================================
0     sum of w * depth (camera z on the pixel's ray; divide by alpha for the mean)
1     alpha
2-4   sum of w * surfel normal, camera frame, facing the camera
5     depth of the last surfel blended while T > 0.5
6     depth distortion over NDC-mapped depths (not normalised)
====  =========================================================================

``means2D.grad[:, :2]`` is dL/d(projected mean) in NDC units, the quantity 2DGS's densification
reads. Approximation: 2DGS intersects each pixel's ray with the surfel's plane and low-passes
with a 2D screen-space Gaussian; the stand-in renders each surfel as a 3D Gaussian whose third
axis is 1e-7 (EWA splatting of a flat Gaussian with the usual 0.3 px^2 dilation), whose per-pixel
depth is that same ray-plane intersection.
"""

from __future__ import annotations

import torch
from torch import Tensor

from polargs_plugin.dryrun.standins.common import RasterSettings, SettingsRasterizer, check_inputs, render_setting, view_colors, with_background

__all__ = ["GaussianRasterizationSettings", "GaussianRasterizer"]


#: The upstream raster setting (same fields, same order).
GaussianRasterizationSettings = RasterSettings


class GaussianRasterizer(SettingsRasterizer):
    """``forward`` returns (color, radii, allmap) like 2DGS's CUDA rasterizer."""

    def forward(self, means3D: Tensor, means2D: Tensor, opacities: Tensor, shs: Tensor | None = None,
                colors_precomp: Tensor | None = None, scales: Tensor | None = None, rotations: Tensor | None = None,
                cov3D_precomp: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        s = self.raster_settings
        check_inputs(shs, colors_precomp, scales, rotations, cov3D_precomp)
        colors = view_colors(means3D, shs, colors_precomp, s.sh_degree, s.campos)
        out = render_setting(s, means3D, means2D, opacities, colors, scales, rotations)
        allmap = torch.cat([out.depth, out.alpha, out.normal, out.median_depth, out.distortion])
        return with_background(out.features, out.alpha, s.bg), out.radii, allmap
