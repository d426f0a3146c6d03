"""What the rasterizer stand-ins of the graphdeco family share: reading an upstream raster
setting and the per-Gaussian inputs of ``GaussianRasterizer.forward`` (SH or precomputed colours,
scale/rotation pairs) the way the CUDA preprocessing does, then calling :func:`..splat.splat`."""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from polargs_plugin.dryrun.splat import NEAR_PLANE, SplatOut, camera_from_upstream, splat
from polargs_plugin.geometry import eval_sh

__all__ = ["RasterSettings", "check_inputs", "view_colors", "render_setting", "with_background", "SettingsRasterizer"]


class RasterSettings(NamedTuple):
    """The raster setting of graphdeco's 2023 rasterizer, which 2DGS's keeps (same fields, same
    order); the 2024 form, GOF's and PGSR's add fields of their own."""

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


def check_inputs(shs: Tensor | None, colors_precomp: Tensor | None, scales: Tensor | None, rotations: Tensor | None,
                 cov3D_precomp: Tensor | None) -> None:
    """The argument checks of the upstream ``GaussianRasterizer.forward``, plus the one thing the
    stand-ins leave out: a precomputed 3D covariance (``--compute_cov3D_python``)."""
    if (shs is None) == (colors_precomp is None):
        raise ValueError("give exactly one of shs or colors_precomp")
    if cov3D_precomp is not None and cov3D_precomp.numel() > 0:
        raise NotImplementedError(
            "the CPU stand-in rasterizer takes scales and rotations, not cov3D_precomp "
            "(leave the trainer's compute_cov3D_python option off for a dry run)"
        )
    if scales is None or rotations is None:
        raise ValueError("give scales and rotations")


def view_colors(means: Tensor, shs: Tensor | None, colors_precomp: Tensor | None, sh_degree: int, campos: Tensor) -> Tensor:
    """(N, 3) colours: ``colors_precomp`` as given, or the first (sh_degree + 1)^2 SH bands of
    ``shs`` (N, K, 3) evaluated from ``campos`` towards each mean, + 0.5, clamped at 0."""
    if colors_precomp is not None:
        return colors_precomp
    assert shs is not None
    bands = (int(sh_degree) + 1) ** 2
    return eval_sh(shs[:, :bands], means - campos.to(means).reshape(1, 3))


def render_setting(settings: Any, means3D: Tensor, means2D: Tensor, opacities: Tensor, features: Tensor, scales: Tensor,
                   rotations: Tensor, *, screen_abs: Tensor | None = None, eps2d: float = 0.3, compensate: bool = False,
                   normalize_distortion: bool = False) -> SplatOut:
    """:func:`~polargs_plugin.dryrun.splat.splat` for an upstream raster ``settings``
    (``image_height``, ``image_width``, ``tanfovx``, ``tanfovy``, ``viewmatrix``, ``scale_modifier``)."""
    width, height = int(settings.image_width), int(settings.image_height)
    K, w2c = camera_from_upstream(settings.viewmatrix, settings.tanfovx, settings.tanfovy, width, height)
    if scales.shape[1] == 2:  # 2DGS surfels: a flat Gaussian with a vanishing third axis
        scales = torch.cat([scales, torch.full_like(scales[:, :1], 1e-7)], dim=1)
    return splat(
        means3D, rotations, scales * float(settings.scale_modifier), opacities.reshape(-1), features, K, w2c,
        width, height, screen=means2D, screen_abs=screen_abs, eps2d=eps2d, compensate=compensate,
        normalize_distortion=normalize_distortion,
    )


def with_background(color: Tensor, alpha: Tensor, bg: Tensor) -> Tensor:
    """Colour + (1 - alpha) * background, as the upstream kernels write ``out_color``."""
    return color + (1.0 - alpha) * bg.to(color).reshape(-1, 1, 1)


class SettingsRasterizer(nn.Module):
    """The upstream ``GaussianRasterizer`` shell: holds ``raster_settings``; ``markVisible``."""

    def __init__(self, raster_settings: Any) -> None:
        super().__init__()
        self.raster_settings = raster_settings

    def markVisible(self, positions: Tensor) -> Tensor:  # noqa: N802 (the upstream name)
        """(N,) bool: the points in front of the near plane (upstream frustum culling)."""
        with torch.no_grad():
            view = self.raster_settings.viewmatrix.to(positions)
            z = positions @ view[:3, 2] + view[3, 2]
            return z > NEAR_PLANE
