"""PolarGS adapter for graphdeco-inria/gaussian-splatting (``python adapters/graphdeco/patch.py``)."""

from polargs_adapters.graphdeco.adapter import GraphdecoAdapter, attach

__all__ = ["GraphdecoAdapter", "attach"]
