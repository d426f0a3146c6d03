"""The adapter kit: what every adapter between PolarGS and a 3DGS trainer needs, in one place.

- :mod:`.render`: per-Gaussian camera-frame normals and the extra render pass (normal, alpha,
  depth) for rasterizers that composite extra channels; depth conversions into RenderOut's camera z.
- :mod:`.append`: raw <-> activated parameter conversions and appending rows to parameters
  with their Adam state (one optimizer with named groups, or one optimizer per name).
- :mod:`.cameras`: the graphdeco-family camera (FoV, transposed W2C) <-> :class:`View`.
- :mod:`.patching` (imported on its own): the anchor-line engine of the patch scripts.
- from :mod:`polargs_plugin.geometry`, the pieces adapters call most: SH DC conversions
  (:func:`rgb_to_sh`, :func:`sh_to_rgb`), shortest-axis normals and the plane depth.

The reference trainer (``polargs_plugin.backends.reference``) uses this kit itself.
"""

from polargs_plugin.geometry import depth_from_plane, rgb_to_sh, sh_to_rgb, shortest_axis_normals
from polargs_plugin.kit.append import (
    RAW_NAMES,
    append_rows,
    edit_rows,
    logit,
    new_from_raw,
    pad_rows,
    raw_from_new,
    state_from_raw,
)
from polargs_plugin.kit.cameras import GraphdecoCamera, graphdeco_from_view, view_from_graphdeco, world_view_transform
from polargs_plugin.kit.render import (
    AUX_CHANNELS,
    aux_channels,
    clamped_aux_colors,
    depth_from_accumulated,
    depth_from_inverse,
    gaussian_normals,
    render_out_from_aux,
    render_out_from_clamped_aux,
)

__all__ = [
    "RAW_NAMES",
    "append_rows",
    "edit_rows",
    "logit",
    "new_from_raw",
    "pad_rows",
    "raw_from_new",
    "rgb_to_sh",
    "sh_to_rgb",
    "state_from_raw",
    "GraphdecoCamera",
    "graphdeco_from_view",
    "view_from_graphdeco",
    "world_view_transform",
    "AUX_CHANNELS",
    "aux_channels",
    "clamped_aux_colors",
    "render_out_from_clamped_aux",
    "depth_from_accumulated",
    "depth_from_inverse",
    "depth_from_plane",
    "gaussian_normals",
    "render_out_from_aux",
    "shortest_axis_normals",
]
