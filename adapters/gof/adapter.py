"""PolarGS for autonomousvision/gaussian-opacity-fields (GOF), verified against 5245b20.

What it translates (docs/adapters/gof.md):

- camera: graphdeco-family ``R`` (stored transposed), ``T``, FoVs -> View (the kit's
  ``view_from_graphdeco``), like every Inria-family adapter;
- render package -> RenderOut, no extra pass (``geometry_in_render``): GOF's ``render`` is a
  (9, H, W) tensor whose channels are read as they are:

  ====  ======================================================================  ==============
  ch.   GOF                                                                     RenderOut
  ====  ======================================================================  ==============
  0-2   RGB, background included                                                ``color``
  3-5   sum of alpha * T * n (n: the unit ray-Gaussian normal, camera frame,   ``normal``
        facing the camera), composited with the colour weights
  6     median depth: camera z of the max-response point of the Gaussian at     ``depth`` and
        which T crosses 0.5 (the last one blended where it never does)          ``median_depth``
  7     accumulated alpha                                                       ``alpha``
  8     distortion                                                              (not used)
  ====  ======================================================================  ==============

  The normal is already the contract's alpha-weighted camera-frame normal (not renormalised),
  so it is passed through. The depth is GOF's median depth, not the contract's alpha-normalised
  expected depth: it is the camera z of one surface and is meaningful only where alpha > 0.5
  (elsewhere it is the depth of whatever Gaussian was blended last, 0 where none was); the
  plug-in reads depth only where alpha > 0.5 (Dense) or weighted by alpha (L_dn). Gradients of
  the plug-in's geometric terms go through this main render, as GOF's own do;
- model -> GaussianState: the RAW scales and opacities (``get_scaling``, ``get_opacity``), not
  GOF's 3D-filtered ones. GOF's 3D filter (``filter_3D``) is a per-Gaussian low-pass floor
  added at render time (scale sqrt(s^2 + f^2), opacity scaled by the volume ratio); L_scale
  flattens the Gaussian itself: on filtered scales its gradient s / sqrt(s^2 + f^2) would vanish
  and its value could not go below f. The appended rows are raw values too (as GOF's own
  ``create_from_pcd``, clone and split write them), so their rendered opacity is the seed's
  opacity times GOF's filter coefficient;
- NewGaussians -> GOF's six-argument ``densification_postfix``; the statistics it resets, the
  absolute-gradient accumulators included, are kept (padded with zeros); then
  ``compute_3D_filter(cameras=scene.getTrainCameras())`` re-sizes ``filter_3D`` to the new
  count (GOF's next render fails on mismatched shapes otherwise);
- every render the adapter makes (Dense's source views) passes ``kernel_size``.

Terms GOF computes itself (:attr:`GofAdapter.native_terms`): the depth-normal consistency
(PolarGS's L_dn; GOF's from iteration 15 000, weight 0.05), so ``use_depth_normal`` is switched
off unless ``keep_native_terms=True``. The reflective-aware colour loss (``use_ref``), the
PatchMatch normal loss (``use_normal``), flattening (``use_scale``; GOF has none) and Dense stay on.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from torch import Tensor

from polargs_plugin.kit.inria import InriaAdapter
from polargs_plugin.service.adapters import adapter_inputs
from polargs_plugin.types import RenderOut

__all__ = ["GofAdapter", "attach", "GOF_CHANNELS"]

GOF_CHANNELS = ("r", "g", "b", "normal_x", "normal_y", "normal_z", "median_depth", "alpha", "distortion")
"""The channels of GOF's ``render_pkg["render"]`` (``OUTPUT_CHANNELS`` 9 of its rasterizer)."""


class GofAdapter(InriaAdapter):
    """:class:`polargs_plugin.kit.inria.InriaAdapter` for GOF's ``train.py``.

    Pass ``render_kwargs={"kernel_size": dataset.kernel_size}`` (:func:`attach` does): GOF's
    ``render`` has no default for it.
    """

    native_terms: ClassVar[dict[str, str]] = {
        "use_depth_normal": "GOF's train.py has a depth-normal consistency loss (median depth vs "
        "rendered normal, world frame, lambda_depth_normal 0.05 from depth_normal_from_iter 15000)",
    }
    statistics: ClassVar[tuple[str, ...]] = (
        "xyz_gradient_accum",
        "xyz_gradient_accum_abs",
        "xyz_gradient_accum_abs_max",
        "denom",
        "max_radii2D",
    )
    geometry_in_render: ClassVar[bool] = True

    def render_out(self, camera: Any, render_pkg: Mapping[str, Any], geometry: bool = True) -> RenderOut:
        """The RenderOut of GOF's (9, H, W) ``render`` (channels :data:`GOF_CHANNELS`); slicing
        costs nothing, so the geometry is returned whatever ``geometry`` says."""
        rendering: Tensor = render_pkg["render"]
        if rendering.dim() != 3 or rendering.shape[0] != len(GOF_CHANNELS):
            raise ValueError(
                f"GOF's render_pkg['render'] should be ({len(GOF_CHANNELS)}, H, W) "
                f"({', '.join(GOF_CHANNELS)}), got {tuple(rendering.shape)}"
            )
        median_depth = rendering[6:7]
        return RenderOut(
            color=rendering[0:3],
            depth=median_depth,
            normal=rendering[3:6],
            alpha=rendering[7:8],
            median_depth=median_depth,
        )

    def _after_append(self) -> None:
        self.gaussians.compute_3D_filter(cameras=self.scene.getTrainCameras())


def attach(scene: Any, gaussians: Any, pipe: Any, render: Any, **render_kwargs: Any) -> GofAdapter:
    """The call the patch script inserts before GOF's training loop,
    ``polargs_gof.attach(scene, gaussians, pipe, render, kernel_size=dataset.kernel_size)``.

    Settings come from the environment: ``POLARGS_DATA`` (required), ``POLARGS_PRESET``,
    ``POLARGS_CONFIG`` (see ``polargs_plugin.service.adapters``). ``render_kwargs`` are passed to every
    render the adapter makes; GOF needs ``kernel_size``.
    """
    if "kernel_size" not in render_kwargs:
        raise TypeError("attach() needs kernel_size=dataset.kernel_size: GOF's render() has no default for it")
    inputs = adapter_inputs(tuple(GofAdapter.native_terms))
    return GofAdapter.from_inputs(inputs, scene, gaussians, pipe, render, **render_kwargs)
