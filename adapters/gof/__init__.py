"""PolarGS adapter for autonomousvision/gaussian-opacity-fields (``python adapters/gof/patch.py``)."""

from polargs_adapters.gof.adapter import GofAdapter, attach

__all__ = ["GofAdapter", "attach"]
