"""The bundled reference backend: a differentiable torch rasterizer (with a compiled CPU kernel),
a minimal vanilla-3DGS Gaussian model with adaptive density control, and its trainer.

Names are imported on first use, so that importing one module of the backend does not pull in
the trainer and its dependencies. The SH colour (``eval_sh``, ``rgb_to_sh``, ``sh_to_rgb``) lives
in :mod:`polargs_plugin.geometry`.
"""

from importlib import import_module
from typing import Any

_EXPORTS = {
    "rasterize": "rasterizer",
    "resolve_backend": "rasterizer",
    "GaussianModel": "model",
    "init_points_from_masks": "model",
    "DensityConfig": "strategy",
    "DensityControl": "strategy",
    "TrainConfig": "trainer",
    "Trainer": "trainer",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module '{__name__}' has no attribute '{name}'")
    return getattr(import_module(f"{__name__}.{_EXPORTS[name]}"), name)
