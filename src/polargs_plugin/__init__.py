"""polargs_plugin: PolarGS polarization cues for 3D Gaussian Splatting trainers."""

from typing import TYPE_CHECKING, Any

from polargs_plugin.config import PolarConfig
from polargs_plugin.types import GaussianState, NewGaussians, PolarMaps, RenderOut, View

if TYPE_CHECKING:
    from polargs_plugin.hooks import PolarHooks

__version__ = "0.1.0"

__all__ = ["PolarConfig", "PolarHooks", "View", "PolarMaps", "RenderOut", "GaussianState", "NewGaussians"]


def __getattr__(name: str) -> Any:
    # PolarHooks pulls in the optics and correction modules (numba among them): imported on first
    # use, so `import polargs_plugin` stays light.
    if name == "PolarHooks":
        from polargs_plugin.hooks import PolarHooks

        return PolarHooks
    raise AttributeError(f"module 'polargs_plugin' has no attribute '{name}'")
