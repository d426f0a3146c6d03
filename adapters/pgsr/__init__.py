"""PolarGS adapter for zju3dv/PGSR (``python adapters/pgsr/patch.py``)."""

from polargs_adapters.pgsr.adapter import PgsrAdapter, attach

__all__ = ["PgsrAdapter", "attach"]
