"""PolarGS adapter for hbb1/2d-gaussian-splatting, 2DGS (``python adapters/twodgs/patch.py``)."""

from polargs_adapters.twodgs.adapter import TWODGS_KEYS, TwoDGSAdapter, attach

__all__ = ["TwoDGSAdapter", "attach", "TWODGS_KEYS"]
