"""Stand-in for PGSR's ``diff_plane_rasterization`` (zju3dv/PGSR de24f1a): the setting adds
``render_geo``; ``forward(means3D, means2D, means2D_abs, opacities, shs | colors_precomp, scales,
rotations, all_map=None)`` returns ``(color (3, H, W) with the background, radii (N,) int32,
out_observe (N,) int32, all-map (5, H, W), plane depth (1, H, W))``:

- ``out_observe``: pixels where the Gaussian was blended while T > 0.5;
- the all-map: ``all_map`` (N, 5) composited with the colour weights, no background (PGSR
  passes the camera-frame normal, 1 and the plane distance, so the rows are the alpha-weighted
  normal, the alpha and the alpha-weighted distance);
- the plane depth: all-map[4] / -(n . ray + 1e-8) with n = all-map[0:3] and the ray
  ((px - W/2) / fx, (py - H/2) / fy, 1) through INTEGER pixel coordinates, as PGSR computes it.

Without ``render_geo`` the last two are empty tensors. ``means2D.grad[:, :2]`` is dL/d(projected
mean) in NDC units; ``means2D_abs.grad[:, 0]`` and ``[:, 1]`` are the sums over pixels of |dL/dx|
and |dL/dy| in the same units (PGSR's absolute-gradient densification).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from polargs_plugin.dryrun.splat import camera_from_upstream
from polargs_plugin.dryrun.standins.common import SettingsRasterizer, check_inputs, render_setting, view_colors, with_background

__all__ = ["GaussianRasterizationSettings", "GaussianRasterizer", "plane_depth"]


class GaussianRasterizationSettings(NamedTuple):
    """PGSR's raster setting (same fields, same order)."""

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
    render_geo: bool
    debug: bool


def plane_depth(all_map: Tensor, K: Tensor) -> Tensor:
    """(1, H, W) PGSR's unbiased depth from a composited all-map (5, H, W), integer pixel rays."""
    _, height, width = all_map.shape
    v, u = torch.meshgrid(torch.arange(height, dtype=all_map.dtype), torch.arange(width, dtype=all_map.dtype), indexing="ij")
    ray_x = (u - K[0, 2]) / K[0, 0]
    ray_y = (v - K[1, 2]) / K[1, 1]
    cosine = all_map[0] * ray_x + all_map[1] * ray_y + all_map[2] + 1.0e-8
    return (all_map[4] / -cosine)[None]


class GaussianRasterizer(SettingsRasterizer):
    """``forward`` returns (color, radii, out_observe, all-map, plane depth) like PGSR's rasterizer."""

    def forward(self, means3D: Tensor, means2D: Tensor, means2D_abs: Tensor, opacities: Tensor,
                shs: Tensor | None = None, colors_precomp: Tensor | None = None, scales: Tensor | None = None,
                rotations: Tensor | None = None, cov3D_precomp: Tensor | None = None,
                all_map: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        s = self.raster_settings
        check_inputs(shs, colors_precomp, scales, rotations, cov3D_precomp)
        colors = view_colors(means3D, shs, colors_precomp, s.sh_degree, s.campos)
        geometry = bool(s.render_geo) and all_map is not None and all_map.numel() > 0
        features = torch.cat([colors, all_map.to(colors)], dim=1) if geometry else colors
        out = render_setting(s, means3D, means2D, opacities, features, scales, rotations, screen_abs=means2D_abs[:, :2])
        color = with_background(out.features[:3], out.alpha, s.bg)
        if not geometry:
            empty = color.new_zeros(0)
            return color, out.radii, out.observe, empty, empty
        maps = out.features[3:8]
        K, _ = camera_from_upstream(s.viewmatrix, s.tanfovx, s.tanfovy, int(s.image_width), int(s.image_height))
        return color, out.radii, out.observe, maps, plane_depth(maps, K.to(maps))
