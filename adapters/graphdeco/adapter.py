"""PolarGS for graphdeco-inria/gaussian-splatting (vanilla 3DGS), 2023 (472689c) and 2024 (54c035f).

What it translates (docs/adapters/graphdeco.md):

- camera: ``R`` stored transposed, ``T``, FoVs -> View (``polargs_plugin.kit.view_from_graphdeco``);
- render package -> RenderOut: colour = ``render_pkg["render"]`` (exposure-corrected and clamped,
  the image the trainer's L1 sees); graphdeco renders no normal and no alpha, so when the hooks
  need geometry two extra passes of the trainer's own ``render(..., override_color=...)`` with
  background 0 give the alpha-weighted normal, alpha, depth and plane depth (``kit.clamped_aux_colors``). Each
  pass makes its own screen-space tensor, so the densification statistics, which train.py reads
  from the main pass's ``viewspace_points``, are untouched. The depth comes from the extra pass
  too, not from the 2024 main pass's inverse depth: gradients of the depth losses through the
  main pass would reach ``viewspace_points`` and inflate those statistics (for the 2024 inverse
  depth, ``kit.depth_from_inverse`` gives the same camera z on a single surface layer);
- model -> GaussianState (``get_xyz``, ``get_rotation``, ``get_scaling``, ``get_opacity``);
- NewGaussians -> ``densification_postfix``: the 2024 seven-argument form needs ``tmp_radii``
  set, which happens only inside ``densify_and_prune``; it is set to zeros around the call.
  The gradient statistics the postfix resets are kept (padded with zeros).

vanilla 3DGS has no depth-normal or flattening term, so every plug-in loss stays on.
"""

from __future__ import annotations

import inspect
from typing import Any, Mapping

import torch
from torch import Tensor

from polargs_plugin.kit import clamped_aux_colors, render_out_from_clamped_aux
from polargs_plugin.kit.inria import InriaAdapter
from polargs_plugin.service.adapters import adapter_inputs
from polargs_plugin.types import RenderOut

__all__ = ["GraphdecoAdapter", "attach"]


class GraphdecoAdapter(InriaAdapter):
    """:class:`polargs_plugin.kit.inria.InriaAdapter` for graphdeco's ``train.py``."""

    def render_out(self, camera: Any, render_pkg: Mapping[str, Any], geometry: bool = True) -> RenderOut:
        color = render_pkg["render"]
        if not geometry:
            return self._color_only(color)
        g = self.gaussians
        normal_colors, alpha_depth_colors, z_scale = clamped_aux_colors(
            g.get_xyz, g.get_rotation, g.get_scaling, self.world_to_camera(camera)
        )
        background = self._background(color)
        normal_image = self.render(camera, g, self.pipe, background, override_color=normal_colors)["render"]
        alpha_depth_image = self.render(camera, g, self.pipe, background, override_color=alpha_depth_colors)["render"]
        return render_out_from_clamped_aux(color, normal_image, alpha_depth_image, z_scale, K=self._view(camera).K)

    def _postfix(self, rows: dict[str, Tensor]) -> None:
        g = self.gaussians
        if "new_tmp_radii" not in inspect.signature(g.densification_postfix).parameters:
            g.densification_postfix(**rows)  # 2023 form (472689c), six arguments
            return
        n, m = g.get_xyz.shape[0], rows["new_xyz"].shape[0]
        device = rows["new_xyz"].device
        g.tmp_radii = torch.zeros(n, device=device)
        try:
            g.densification_postfix(**rows, new_tmp_radii=torch.zeros(m, device=device))
        finally:
            g.tmp_radii = None


def attach(scene: Any, gaussians: Any, pipe: Any, render: Any, **render_kwargs: Any) -> GraphdecoAdapter:
    """The call the patch script inserts before the training loop (settings from the environment:
    ``POLARGS_DATA``, ``POLARGS_PRESET``, ``POLARGS_CONFIG``; see ``polargs_plugin.service.adapters``)."""
    inputs = adapter_inputs(tuple(GraphdecoAdapter.native_terms))
    return GraphdecoAdapter.from_inputs(inputs, scene, gaussians, pipe, render, **render_kwargs)
