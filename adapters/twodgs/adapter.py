"""PolarGS for hbb1/2d-gaussian-splatting (2DGS), verified against 1920a23.

What it translates (docs/adapters/twodgs.md):

- camera: graphdeco-family ``R`` (stored transposed), ``T``, FoVs -> View (the kit's
  ``view_from_graphdeco``), like every Inria-family adapter;
- render package -> RenderOut, no extra pass (``geometry_in_render``): 2DGS renders its surfels'
  geometry itself:

  ===============  =====================================================  ===================
  2DGS key         what it is                                             RenderOut
  ===============  =====================================================  ===================
  ``render``       RGB, background included                               ``color``
  ``rend_normal``  alpha-weighted surfel normal, facing the camera,       ``normal``, rotated
                   rotated to the WORLD frame                             back to the camera
  ``surf_depth``   camera z: (1 - depth_ratio) expected + depth_ratio     ``depth``
                   median depth
  ``rend_alpha``   accumulated alpha                                      ``alpha``
  ``rend_dist``    depth distortion                                       (not used)
  ===============  =====================================================  ===================

  Gradients of the plug-in's geometric terms go through this main render, as 2DGS's own
  normal-consistency term's do;
- model -> GaussianState: surfels have two scales (``get_scaling`` is (N, 2)); the hooks get
  them with a third, zero scale along the surfel normal (the rotation's third axis);
- NewGaussians -> 2DGS's six-argument ``densification_postfix`` as surfels: Dense seeds flat
  Gaussians whose shortest (third) axis is the PatchMatch normal, so a seed's rotation is kept
  and its two tangent scales become the surfel's; the statistics the postfix resets are kept
  (padded with zeros).

Terms 2DGS computes itself (:attr:`TwoDGSAdapter.native_terms`): its normal consistency between
the rendered normal and the normal of the rendered depth stands in for PolarGS's depth-normal
term L_dn (``use_depth_normal``), and surfels are flat by construction, so flattening
(``use_scale``) has nothing to do; both are switched off unless ``keep_native_terms=True``.
The reflective-aware colour loss (``use_ref``), the PatchMatch normal loss (``use_normal``) and
Dense stay on. 2DGS's depth distortion has no PolarGS counterpart and is left as it is.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

import torch
from torch import Tensor

from polargs_plugin.kit.inria import InriaAdapter
from polargs_plugin.service.adapters import adapter_inputs
from polargs_plugin.types import GaussianState, RenderOut

__all__ = ["TwoDGSAdapter", "attach", "TWODGS_KEYS"]

TWODGS_KEYS = ("render", "rend_normal", "surf_depth", "rend_alpha")
"""The keys of 2DGS's render package the adapter reads."""


class TwoDGSAdapter(InriaAdapter):
    """:class:`polargs_plugin.kit.inria.InriaAdapter` for 2DGS's ``train.py`` (surfels)."""

    native_terms: ClassVar[dict[str, str]] = {
        "use_depth_normal": "2DGS's train.py has a normal-consistency loss between the rendered normal and the "
        "normal of the rendered depth (lambda_normal 0.05 from iteration 7000)",
        "use_scale": "2DGS's surfels have two scales: they are flat by construction",
    }
    geometry_in_render: ClassVar[bool] = True

    def render_out(self, camera: Any, render_pkg: Mapping[str, Any], geometry: bool = True) -> RenderOut:
        """The RenderOut of 2DGS's render package (keys :data:`TWODGS_KEYS`); its maps are
        already rendered, so the geometry is returned whatever ``geometry`` says."""
        missing = [key for key in TWODGS_KEYS if key not in render_pkg]
        if missing:
            raise KeyError(f"2DGS's render package has no {', '.join(missing)} (keys: {', '.join(render_pkg)})")
        rotation = self.world_to_camera(camera)[:3, :3].to(render_pkg["rend_normal"])
        normal = torch.einsum("ij,jhw->ihw", rotation, render_pkg["rend_normal"])  # world -> camera
        return RenderOut(
            color=render_pkg["render"],
            depth=render_pkg["surf_depth"],
            normal=normal,
            alpha=render_pkg["rend_alpha"],
        )

    def gaussian_state(self) -> GaussianState:
        """The surfels with a third, zero scale (along their normal)."""
        state = super().gaussian_state()
        surfel = state.scales
        return GaussianState(
            means=state.means,
            quats=state.quats,
            scales=torch.cat([surfel, surfel.new_zeros((surfel.shape[0], 1))], dim=1),
            opacities=state.opacities,
        )

    def _postfix(self, rows: dict[str, Tensor]) -> None:
        """Seeds as surfels: the two tangent log-scales (the third axis is the seed's normal)."""
        self.gaussians.densification_postfix(**dict(rows, new_scaling=rows["new_scaling"][:, :2]))


def attach(scene: Any, gaussians: Any, pipe: Any, render: Any, **render_kwargs: Any) -> TwoDGSAdapter:
    """The call the patch script inserts before 2DGS's training loop,
    ``polargs_twodgs.attach(scene, gaussians, pipe, render)``.

    Settings come from the environment: ``POLARGS_DATA`` (required), ``POLARGS_PRESET``,
    ``POLARGS_CONFIG`` (see ``polargs_plugin.service.adapters``). ``render_kwargs`` are passed to
    every render the adapter makes.
    """
    inputs = adapter_inputs(tuple(TwoDGSAdapter.native_terms))
    return TwoDGSAdapter.from_inputs(inputs, scene, gaussians, pipe, render, **render_kwargs)
