"""Stand-in for graphdeco-inria's ``diff_gaussian_rasterization`` as the 2024 trainer uses it
(graphdeco 54c035f): the setting has ``antialiasing``; ``forward`` also takes ``dc`` (the SH
DC band given apart from ``shs``) and returns ``(color (3, H, W) with the background, radii (N,)
int32, inverse depth (1, H, W))``, the inverse depth being sum_i w_i / z_i over the camera z of
the means, not divided by alpha. ``antialiasing`` scales each opacity by
sqrt(det(cov2D) / det(cov2D + 0.3 I)) as upstream does. There is no ``SparseGaussianAdam``: a
trainer that tries to import it falls back to its plain Adam.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from polargs_plugin.dryrun.standins.common import SettingsRasterizer, check_inputs, render_setting, view_colors, with_background

__all__ = ["GaussianRasterizationSettings", "GaussianRasterizer"]


class GaussianRasterizationSettings(NamedTuple):
    """The upstream raster setting (same fields, same order)."""

    image_height: int
    image_width: int
    tanfovx: float
    tanfovy: float
    bg: Tensor
    scale_modifier: float
    viewmatrix: Tensor
    projmatrix: Tensor
    sh_degree: int
    campos: Tensor
    prefiltered: bool
    debug: bool
    antialiasing: bool


class GaussianRasterizer(SettingsRasterizer):
    """``forward`` returns (color, radii, inverse depth) like the 2024 CUDA rasterizer."""

    def forward(self, means3D: Tensor, means2D: Tensor, opacities: Tensor, shs: Tensor | None = None,
                colors_precomp: Tensor | None = None, scales: Tensor | None = None, rotations: Tensor | None = None,
                cov3D_precomp: Tensor | None = None, dc: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        s = self.raster_settings
        if dc is not None and shs is not None:
            shs = torch.cat([dc, shs], dim=1)
        check_inputs(shs, colors_precomp, scales, rotations, cov3D_precomp)
        colors = view_colors(means3D, shs, colors_precomp, s.sh_degree, s.campos)
        out = render_setting(s, means3D, means2D, opacities, colors, scales, rotations, compensate=bool(s.antialiasing))
        return with_background(out.features, out.alpha, s.bg), out.radii, out.inverse_depth
