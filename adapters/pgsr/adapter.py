"""PolarGS for zju3dv/PGSR (de24f1a) (``python adapters/pgsr/patch.py``; docs/adapters/pgsr.md).

What it translates:

- camera: PGSR's camera is the Inria one (``R`` transposed, ``T``, FoVs) plus ``Fx, Fy,
  Cx = W / 2, Cy = H / 2``; the View's K (from the FoVs, centred principal point with +0.5 pixel
  centres) is that same K.
- render package -> RenderOut:

  * colour = what train.py's L1 compares: ``app_image`` (the exposure-compensated image) when the
    package has it and the trainer's SSIM loss 1 - SSIM(render, gt) is below 0.5, else
    ``render``. The gate is re-evaluated here without a host sync (``torch.where``) against the
    camera's preloaded ``original_image`` (the View's image when it has none).
  * geometry: PGSR returns no alpha, and asks for its plane outputs only after iteration 7000,
    while the plug-in needs them earlier (Dense runs in 1k-7k). So when the hooks need
    geometry the adapter makes ONE extra pass through the trainer's own ``render`` with
    ``override_color`` = ones, background 0, ``return_plane=True`` and no ``app_model``: its
    ``render`` image is the alpha (sum w), ``rendered_normal`` is the camera-frame,
    alpha-weighted, camera-facing normal, ``rendered_distance`` the alpha-weighted plane
    distance. The pass makes its own screen-space tensors, so the densification statistics
    that train.py reads from the main pass are untouched by the plug-in's geometry terms.
    ``return_depth_normal`` is off in that pass (the RenderOut has no use for PGSR's
    depth-derived normal).
  * depth: PGSR's ``plane_depth`` is the plane's camera z along rays through INTEGER pixel
    coordinates ((px - W/2) / Fx, ...), i.e. half a pixel up-left of this project's +0.5 pixel
    centres; on a tilted surface that is off by half a pixel's worth of depth slope. The
    adapter recomputes the camera z at the +0.5 centres from the same rendered distance and
    normal (``kit.depth_from_plane(..., pixel_center=0.5)``), which is exact for planar
    Gaussians and costs no pass.
- model -> GaussianState (``get_xyz``, ``get_rotation``, ``get_scaling``, ``get_opacity``).
- NewGaussians -> PGSR's ``densification_postfix(new_xyz, new_knn_f, new_features_dc,
  new_features_rest, new_opacities, new_scaling, new_rotation)`` with ``new_knn_f`` drawn from a
  standard normal, as ``create_from_pcd`` does; appends stop at the model's ``max_all_points``;
  every statistic the postfix resets (plain and absolute gradient accumulators, ``denom``,
  ``denom_abs``, ``max_radii2D``, ``max_weight``) is kept and padded with zeros.

PGSR has its own depth-normal term (from 7000) and flattening term (visible Gaussians, x100), so
the plug-in's ``use_depth_normal`` and ``use_scale`` are off unless ``keep_native_terms``.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

import torch
from torch import Tensor

from polargs_plugin.kit import depth_from_plane
from polargs_plugin.kit.inria import InriaAdapter
from polargs_plugin.service.adapters import adapter_inputs
from polargs_plugin.ssim import ssim_map
from polargs_plugin.types import RenderOut, View

__all__ = ["PgsrAdapter", "attach"]

#: train.py uses ``app_image`` for its L1 only while its SSIM loss is below this.
APP_IMAGE_SSIM_LOSS_BELOW = 0.5


class PgsrAdapter(InriaAdapter):
    """:class:`polargs_plugin.kit.inria.InriaAdapter` for PGSR's ``train.py``.

    Takes the arguments of :class:`InriaAdapter`; ``max_gaussians`` defaults to the model's
    ``max_all_points`` (set by PGSR's ``training_setup``), and ``render_kwargs`` carries PGSR's
    ``app_model``.
    """

    native_terms: ClassVar[dict[str, str]] = {
        "use_depth_normal": "PGSR's single-view loss |depth_normal - rendered_normal| (from iteration 7000)",
        "use_scale": "PGSR's flattening loss: smallest scale of the visible Gaussians, x100",
    }
    statistics: ClassVar[tuple[str, ...]] = (
        "xyz_gradient_accum", "xyz_gradient_accum_abs", "denom", "denom_abs", "max_radii2D", "max_weight",
    )
    model_cap: ClassVar[str | None] = "max_all_points"

    # ------------------------------------------------------------------ translation
    def loss_color(self, camera: Any, render_pkg: Mapping[str, Any]) -> Tensor:
        """The image train.py's L1 compares: ``app_image`` while 1 - SSIM(render, gt) < 0.5."""
        image = render_pkg["render"]
        app_image = render_pkg.get("app_image")
        if app_image is None:
            return image
        target = getattr(camera, "original_image", None)
        if not isinstance(target, Tensor):
            target = self._view(camera).image
        with torch.no_grad():
            ssim_loss = 1.0 - ssim_map(image.detach(), target.to(image).clamp(0, 1)).mean()
        return torch.where(ssim_loss < APP_IMAGE_SSIM_LOSS_BELOW, app_image, image)

    def render_out(self, camera: Any, render_pkg: Mapping[str, Any], geometry: bool = True) -> RenderOut:
        color = self.loss_color(camera, render_pkg)
        if not geometry:
            return self._color_only(color)
        g = self.gaussians
        ones = torch.ones_like(g.get_xyz)
        aux = self.render(
            camera, g, self.pipe, self._background(color), override_color=ones, app_model=None,
            return_plane=True, return_depth_normal=False,
        )
        alpha = aux["render"][:1]
        normal = aux["rendered_normal"]
        K = self._view(camera).K
        depth = depth_from_plane(aux["rendered_distance"], normal, K, pixel_center=0.5)
        return RenderOut(color=color, depth=depth, normal=normal, alpha=alpha, plane_depth=depth)

    def render_view(self, view: View) -> RenderOut:
        """Render a training view for Dense: a colour pass without PGSR's plane outputs, then
        the geometry pass of :meth:`render_out`."""
        camera = self.cameras[view.name]
        kwargs = {**self.render_kwargs, "return_plane": False, "return_depth_normal": False}
        pkg = self.render(camera, self.gaussians, self.pipe, self._background(self.gaussians.get_xyz), **kwargs)
        return self.render_out(camera, pkg, geometry=True)

    # ----------------------------------------------------------------------- append
    def _postfix(self, rows: dict[str, Tensor]) -> None:
        g = self.gaussians
        xyz = rows["new_xyz"]
        knn_f = torch.randn((xyz.shape[0], int(g._knn_f.shape[1])), device=xyz.device, dtype=xyz.dtype)
        g.densification_postfix(
            xyz, knn_f, rows["new_features_dc"], rows["new_features_rest"], rows["new_opacities"],
            rows["new_scaling"], rows["new_rotation"],
        )


def attach(scene: Any, gaussians: Any, pipe: Any, render: Any, **render_kwargs: Any) -> PgsrAdapter:
    """The call the patch script inserts before the training loop, ``app_model=app_model`` in
    ``render_kwargs`` (settings from the environment: ``POLARGS_DATA``, ``POLARGS_PRESET``,
    ``POLARGS_CONFIG``; see ``polargs_plugin.service.adapters``)."""
    inputs = adapter_inputs(tuple(PgsrAdapter.native_terms))
    return PgsrAdapter.from_inputs(inputs, scene, gaussians, pipe, render, **render_kwargs)
