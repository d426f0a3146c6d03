"""PolarGS in gsplat's ``examples/simple_trainer.py`` (1.5.3 and main): what the patched lines call.

``python adapters/gsplat/patch.py CHECKOUT`` inserts three lines (docs/adapters/gsplat.md)::

    import polargs_adapters.gsplat as polargs_gsplat                     # after gsplat's strategy import
    self.polar = polargs_gsplat.attach(self)                           # Runner.__init__, before check_sanity
    loss = loss + self.polar.loss(step, image_ids, camtoworlds, Ks, renders, alphas, info)   # before backward

``attach`` turns the configured ``DefaultStrategy`` / ``MCMCStrategy`` into its PolarGS subclass
(same settings), so the trainer's ``isinstance`` dispatch, ``step_pre_backward`` and
``step_post_backward`` (with ``scene=`` on main) run unchanged and Dense runs at the end of
``step_post_backward``. The loss hook renders the trained view's geometry (normal, alpha, depth)
in a second ``rasterization`` call with the same camera; its screen-space means are its own, so
the gradients of the geometric terms do not enter DefaultStrategy's ``grad2d`` statistics (the
colour terms act on the trainer's own render, as its photometric loss does).
"""

from __future__ import annotations

from typing import Any, Callable, Dict, List, Sequence

import torch
from torch import Tensor

from polargs_plugin.config import PolarConfig
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.io import PolarInputError
from polargs_plugin.kit import aux_channels, render_out_from_aux
from polargs_plugin.kit.inria import polar_data_by_name
from polargs_plugin.service.adapters import adapter_inputs
from polargs_plugin.types import RenderOut, View

from .cameras import view_from_gsplat
from .render import gaussian_state, make_render_fn, sh_colors
from .strategy import polar_strategy

__all__ = ["SimpleTrainerPolar", "attach", "trainer_views"]


def trainer_views(parser: Any, trainset: Any, polar_views: Sequence[View], source: str = "") -> List[View]:
    """One :class:`View` per item of simple_trainer's training set (``data["image_id"]`` indexes it).

    The camera is the parser's (``camtoworlds``, ``Ks_dict`` and ``imsize_dict`` of the image's
    camera, after its downscaling and undistortion); the Stokes and mask come from the
    polarimetric view of the image's name, at that size.
    """
    images = []
    for item in range(len(trainset)):
        index = int(trainset.indices[item])
        width, height = parser.imsize_dict[parser.camera_ids[index]]
        images.append((parser.image_names[index], int(height), int(width)))
    data = polar_data_by_name(images, polar_views, source)
    views = []
    for item, (name, _, _) in enumerate(images):
        index = int(trainset.indices[item])
        c2w = torch.as_tensor(parser.camtoworlds[index], dtype=torch.float64)
        K = torch.as_tensor(parser.Ks_dict[parser.camera_ids[index]], dtype=torch.float64)
        polar = data[name]
        views.append(view_from_gsplat(torch.linalg.inv(c2w), K, polar.stokes, name=name, mask=polar.mask,
                                      source=polar.source))
    return views


class SimpleTrainerPolar:
    """PolarGS attached to a simple_trainer.py ``Runner``.

    Args:
        runner: the trainer's ``Runner`` (``cfg``, ``parser``, ``trainset``, ``splats``,
            ``optimizers``, ``world_size``).
        polar_views: the polarimetric views of the scene (matched to the images by name).
        config: PolarGS settings.
        source: the dataset folder, for messages.
        rasterize: ``gsplat.rasterization`` (default) or a function with its signature.

    Attributes:
        hooks: the :class:`PolarHooks`; views: one View per training-set item; logs: the last
            loss logs (detached tensors).
    """

    def __init__(
        self,
        runner: Any,
        polar_views: Sequence[View],
        config: PolarConfig,
        source: str = "",
        rasterize: Callable[..., Any] | None = None,
    ) -> None:
        cfg = runner.cfg
        if getattr(cfg, "batch_size", 1) != 1 or getattr(runner, "world_size", 1) != 1:
            raise PolarInputError("simple_trainer.py", "PolarGS trains one image per step on one GPU: use --batch_size 1")
        if getattr(cfg, "patch_size", None):
            raise PolarInputError("simple_trainer.py", "PolarGS needs whole images: leave --patch_size unset")
        if rasterize is None:
            from gsplat import rasterization as rasterize
        self.runner = runner
        self.rasterize = rasterize
        self.raster_kwargs: Dict[str, Any] = {
            "packed": bool(getattr(cfg, "packed", False)),
            "near_plane": float(getattr(cfg, "near_plane", 0.01)),
            "far_plane": float(getattr(cfg, "far_plane", 1e10)),
            "rasterize_mode": "antialiased" if getattr(cfg, "antialiased", False) else "classic",
        }
        self.views = trainer_views(runner.parser, runner.trainset, polar_views, source)
        self.hooks = PolarHooks(config)
        self.hooks.preprocess(self.views)
        self.logs: Dict[str, Tensor] = {}
        render_fn = make_render_fn(runner.splats, rasterize, colors_fn=self._colors, **self.raster_kwargs)
        runner.cfg.strategy = polar_strategy(cfg.strategy, hooks=self.hooks, render_fn=render_fn)

    def _colors(self, params: Any, viewmats: Tensor) -> Tensor:
        """The Gaussians' RGB for Dense's source renders: the SH colour, or with appearance
        optimisation the base colour (``sigmoid(colors)``, no per-image embedding)."""
        if "sh0" in params:
            return sh_colors(params, viewmats)
        return torch.sigmoid(params["colors"])

    def loss(
        self,
        step: int,
        image_ids: Tensor,
        camtoworlds: Tensor,
        Ks: Tensor,
        renders: Tensor,
        alphas: Tensor,
        info: Dict[str, Any],
    ) -> Tensor:
        """The PolarGS loss to add before ``loss.backward()`` (``step`` is gsplat's 0-based step).

        The colour is the trainer's render (``renders[..., :3]``); the geometry, when the hooks
        need it at this step, comes from a second render of the same camera. Sets
        ``info["polar_view"]`` / ``info["polar_render"]`` for the strategy's Dense step."""
        view = self.views[int(image_ids.reshape(-1)[0])]
        color = renders[0, ..., :3].permute(2, 0, 1)
        if self.hooks.geometry_needed(step + 1, view.name):
            render = self._geometry(camtoworlds, Ks, color, view)
        else:
            zero = color.new_zeros((1, *color.shape[-2:]))
            render = RenderOut(color=color, depth=zero, normal=color.new_zeros(color.shape), alpha=zero)
        params = self.runner.splats
        extra, self.logs = self.hooks.loss(step + 1, view, render, gaussian_state(params))
        info["polar_view"] = view
        info["polar_render"] = render.detached()
        return extra

    def _geometry(self, camtoworlds: Tensor, Ks: Tensor, color: Tensor, view: View) -> RenderOut:
        params = self.runner.splats
        viewmats = torch.linalg.inv(camtoworlds)
        scales = torch.exp(params["scales"])
        aux = aux_channels(params["means"], params["quats"], scales, viewmats[0])
        aux_image, _, _ = self.rasterize(
            params["means"], params["quats"], scales, torch.sigmoid(params["opacities"]), aux, viewmats, Ks,
            view.width, view.height, sh_degree=None, **self.raster_kwargs,
        )
        return render_out_from_aux(color, aux_image[0].permute(2, 0, 1), K=view.K.to(color))


def attach(runner: Any, rasterize: Callable[..., Any] | None = None) -> SimpleTrainerPolar:
    """The call the patch script inserts into simple_trainer.py's ``Runner.__init__``.

    Settings come from the environment: ``POLARGS_DATA`` (required), ``POLARGS_PRESET``,
    ``POLARGS_CONFIG`` (see ``polargs_plugin.service.adapters``).
    """
    inputs = adapter_inputs()
    return SimpleTrainerPolar(runner, inputs.views, inputs.config, inputs.source, rasterize)
