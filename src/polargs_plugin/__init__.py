"""polargs_plugin: PolarGS polarization cues for 3D Gaussian Splatting trainers."""

from importlib import import_module
from typing import TYPE_CHECKING, Any

from polargs_plugin.config import PolarConfig

if TYPE_CHECKING:
    from polargs_plugin.hooks import PolarHooks
    from polargs_plugin.kit import append_rows, raw_from_new, state_from_raw
    from polargs_plugin.types import GaussianState, NewGaussians, PolarMaps, RenderOut, TrainingHooks, View

__version__ = "0.1.0"

# Imported on first use: the contracts pull in torch and PolarHooks the optics and correction
# modules (numba among them), so `import polargs_plugin` (and `polargs --help`) stays light.
# Everything a training loop of one's own touches is here: the hooks, the contracts, and the
# three kit functions that turn a trainer's raw parameters into the hooks' GaussianState and
# append Dense's Gaussians with their Adam state.
_LAZY = {
    "PolarHooks": "polargs_plugin.hooks",
    "View": "polargs_plugin.types",
    "PolarMaps": "polargs_plugin.types",
    "RenderOut": "polargs_plugin.types",
    "GaussianState": "polargs_plugin.types",
    "NewGaussians": "polargs_plugin.types",
    "TrainingHooks": "polargs_plugin.types",
    "state_from_raw": "polargs_plugin.kit",
    "raw_from_new": "polargs_plugin.kit",
    "append_rows": "polargs_plugin.kit",
}

__all__ = ["PolarConfig", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'polargs_plugin' has no attribute '{name}'")
