"""The bundled reference backend: a differentiable torch rasterizer (with a compiled CPU kernel),
a minimal vanilla-3DGS Gaussian model with adaptive density control, and its trainer."""

from polargs_plugin.backends.reference.model import GaussianModel, init_points_from_masks
from polargs_plugin.backends.reference.projection import eval_sh, rgb_to_sh, sh_to_rgb
from polargs_plugin.backends.reference.rasterizer import rasterize, resolve_backend
from polargs_plugin.backends.reference.strategy import DensityConfig, DensityControl
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer

__all__ = [
    "rasterize",
    "resolve_backend",
    "eval_sh",
    "rgb_to_sh",
    "sh_to_rgb",
    "GaussianModel",
    "init_points_from_masks",
    "DensityConfig",
    "DensityControl",
    "TrainConfig",
    "Trainer",
]
