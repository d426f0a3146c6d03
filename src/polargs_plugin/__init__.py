"""polargs_plugin: PolarGS polarization cues for 3D Gaussian Splatting trainers."""

from polargs_plugin.config import PolarConfig
from polargs_plugin.types import GaussianState, NewGaussians, PolarMaps, RenderOut, View

__version__ = "0.1.0"

__all__ = ["PolarConfig", "View", "PolarMaps", "RenderOut", "GaussianState", "NewGaussians"]
