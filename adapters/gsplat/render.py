"""gsplat renders <-> the hooks' :class:`RenderOut` / :class:`GaussianState`; the PolarGS loss.

gsplat 1.5 renders no normals. PolarGS needs a normal, an alpha and a camera-z depth of the
*same* render whose colour drives the loss, so the trainer appends the six per-Gaussian
channels of :func:`polargs_plugin.kit.aux_channels` (camera-frame normal, 1, camera z, plane
distance) to its colours and renders everything in ONE ``rasterization`` call
(``sh_degree=None``: the SH are evaluated first, :func:`sh_colors`)::

    colors = polar_colors(sh_colors(params, viewmats, sh_degree), params, viewmats)  # [N, 3 + 6]
    render_colors, render_alphas, info = rasterization(
        means, quats, exp(scales), sigmoid(opacities), colors, viewmats, Ks, W, H,
        sh_degree=None, backgrounds=polar_backgrounds(bg))                        # [1, H, W, 9]
    rgb = render_colors[..., :3]

A second call would give the aux channels a ``means2d`` of their own that the strategy does not
track; one call keeps a single ``info["means2d"]`` (gsplat's strategies read ``info["means2d"]`` of that call). A consequence:
gradients of L_n / L_dn reach ``means2d`` and hence DefaultStrategy's ``grad2d`` statistics
(docs/adapters/gsplat.md, "Differences").

Parameter names follow gsplat's ``simple_trainer.py``: ``means`` [N, 3], ``scales`` (log)
[N, 3], ``quats`` (wxyz, unnormalised) [N, 4], ``opacities`` (logit) [N], ``sh0`` [N, 1, 3],
``shN`` [N, K - 1, 3] (or ``colors`` (logit RGB) + ``features`` with appearance optimisation).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any, Callable, Mapping

import torch
from torch import Tensor

from polargs_plugin.geometry import eval_sh
from polargs_plugin.kit import AUX_CHANNELS, aux_channels, render_out_from_aux, state_from_raw
from polargs_plugin.types import GaussianState, RenderOut, TrainingHooks, View

from .cameras import gsplat_cameras

__all__ = [
    "NUM_AUX",
    "RAW_FROM_GSPLAT",
    "gaussian_state",
    "gsplat_sh",
    "sh_colors",
    "polar_colors",
    "polar_backgrounds",
    "render_out_from_gsplat",
    "polar_loss",
    "make_render_fn",
]

NUM_AUX = len(AUX_CHANNELS)
"""Number of extra colour channels PolarGS needs (normal x/y/z, alpha, camera z)."""

RAW_FROM_GSPLAT = {
    "means": "means",
    "scales": "log_scales",
    "quats": "quats",
    "opacities": "opacity_logits",
    "sh0": "sh_dc",
    "shN": "sh_rest",
}
"""gsplat parameter name -> the kit's raw name (:data:`polargs_plugin.kit.RAW_NAMES`)."""


def gaussian_state(params: Mapping[str, Tensor]) -> GaussianState:
    """The hooks' :class:`GaussianState` (activated, autograd-connected) of gsplat parameters."""
    return state_from_raw({raw: params[name] for name, raw in RAW_FROM_GSPLAT.items() if name in params})


def _viewmat(viewmats: Tensor) -> Tensor:
    if viewmats.dim() == 3:
        if viewmats.shape[0] != 1:
            raise ValueError(f"one camera per call: viewmats must be (1, 4, 4), got {tuple(viewmats.shape)}")
        viewmats = viewmats[0]
    if tuple(viewmats.shape) != (4, 4):
        raise ValueError(f"viewmats must be (1, 4, 4) or (4, 4), got {tuple(viewmats.shape)}")
    return viewmats


def gsplat_sh(degree: int, means: Tensor, viewmats: Tensor, coeffs: Tensor, sh_fn: Callable[..., Tensor]) -> Tensor:
    """(N, D) SH values (no offset, no clamp) of one camera through ``gsplat.spherical_harmonics``,
    whichever of its two signatures ``sh_fn`` has (read from the function, not from a version):

    - gsplat 1.5: ``(degrees_to_use, dirs, coeffs, masks=None) -> [N, D]``, dirs = mean - camera centre;
    - gsplat main (1.6): ``(degrees_to_use, means, viewmats, coeffs, ...) -> [C, N, D]``, the
      camera centre taken from each view matrix.

    Raises:
        TypeError: ``sh_fn`` has neither signature (the message shows the one it has).
    """
    parameters = inspect.signature(sh_fn).parameters
    w2c = _viewmat(viewmats).to(means)
    if "viewmats" in parameters and "means" in parameters:
        return sh_fn(degree, means, w2c[None], coeffs)[0]
    if "dirs" in parameters:
        camera_center = -w2c[:3, :3].T @ w2c[:3, 3]
        return sh_fn(degree, means - camera_center, coeffs)
    raise TypeError(
        f"spherical_harmonics{inspect.signature(sh_fn)}: expected gsplat 1.5's (degrees_to_use, dirs, coeffs, ...) "
        "or gsplat 1.6's (degrees_to_use, means, viewmats, coeffs, ...)"
    )


def sh_colors(
    params: Mapping[str, Tensor],
    viewmats: Tensor,
    sh_degree: int | None = None,
    sh_fn: Callable[..., Tensor] | None = None,
) -> Tensor:
    """Per-Gaussian RGB of the SH parameters for one camera, as gsplat's ``rasterization``
    computes them internally (``clamp_min(SH(dir) + 0.5, 0)``, dir = mean - camera centre).

    Needed because the extra PolarGS channels only fit with ``sh_degree=None``.

    Args:
        params: gsplat parameters with ``means``, ``sh0`` and (optionally) ``shN``.
        viewmats: (1, 4, 4) or (4, 4) world-to-camera.
        sh_degree: active SH degree (default: all bands of ``sh0`` + ``shN``).
        sh_fn: a function with the signature of ``gsplat.spherical_harmonics``, either gsplat's
            (:func:`gsplat_sh`). Default: gsplat's own on CUDA; on CPU, where gsplat's is not
            available, :func:`polargs_plugin.geometry.eval_sh` (the same real SH basis).

    Returns:
        (N, 3) colours, differentiable w.r.t. the SH coefficients (and means for degree >= 1).
    """
    coeffs = params["sh0"]
    if "shN" in params and params["shN"].shape[1] > 0:
        coeffs = torch.cat([coeffs, params["shN"]], dim=1)
    full = math.isqrt(coeffs.shape[1]) - 1
    degree = full if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= full:
        raise ValueError(f"sh_degree {degree} outside 0..{full} (K = {coeffs.shape[1]} coefficients)")
    means = params["means"]
    if sh_fn is None and coeffs.is_cuda:
        from gsplat import spherical_harmonics as sh_fn
    if sh_fn is not None:
        return torch.clamp_min(gsplat_sh(degree, means, viewmats, coeffs, sh_fn) + 0.5, 0.0)
    w2c = _viewmat(viewmats).to(means)
    camera_center = -w2c[:3, :3].T @ w2c[:3, 3]
    return eval_sh(coeffs[:, : (degree + 1) ** 2], means - camera_center)


def polar_colors(colors: Tensor, params: Mapping[str, Tensor], viewmats: Tensor) -> Tensor:
    """``colors`` with the :data:`NUM_AUX` PolarGS channels appended, for one ``rasterization`` call.

    Args:
        colors: (N, D) post-activation colours (e.g. :func:`sh_colors`).
        params: gsplat parameters (``means``, ``quats``, log ``scales``).
        viewmats: (1, 4, 4) or (4, 4) world-to-camera of the rendered camera.

    Returns:
        (N, D + 6): ``[colors, normal (3), 1, camera z, plane distance]``
        (:data:`polargs_plugin.kit.AUX_CHANNELS`).
    """
    aux = aux_channels(params["means"], params["quats"], torch.exp(params["scales"]), _viewmat(viewmats))
    return torch.cat([colors, aux.to(colors)], dim=-1)


def polar_backgrounds(backgrounds: Tensor | None) -> Tensor | None:
    """Backgrounds ([..., C, D]) padded with zeros for the aux channels (they need background 0)."""
    if backgrounds is None:
        return None
    return torch.cat([backgrounds, backgrounds.new_zeros((*backgrounds.shape[:-1], NUM_AUX))], dim=-1)


def render_out_from_gsplat(
    render_colors: Tensor,
    render_alphas: Tensor | None = None,
    *,
    rgb_channels: int = 3,
    K: Tensor | None = None,
) -> RenderOut:
    """A :class:`RenderOut` of one gsplat render whose colours carry the aux channels.

    Args:
        render_colors: [1, H, W, X] channel-last output of ``rasterization`` with the colours of
            :func:`polar_colors`: RGB in ``[..., :rgb_channels]``, then the six aux channels
            (anything after them, e.g. the ``RGB+ED`` depth, is ignored).
        render_alphas: [1, H, W, 1] (shape check only: alpha is the aux channel ``1``, equal to
            it when the aux background is 0).
        rgb_channels: number of colour channels before the aux ones (3).
        K: (3, 3) intrinsics of the render (the view's): given, the RenderOut has the unbiased
            plane depth too, which L_dn uses (``polargs_plugin.kit.render_out_from_aux``).

    Returns:
        RenderOut with color (3, H, W) (not clamped), camera-frame normal, alpha, camera-z
        depth Σwz / Σw and with ``K`` plane depth, all channel-first and autograd-connected.
    """
    if render_colors.dim() != 4 or render_colors.shape[0] != 1:
        raise ValueError(f"render_colors must be [1, H, W, X] (one camera), got {tuple(render_colors.shape)}")
    if render_colors.shape[-1] < rgb_channels + NUM_AUX:
        raise ValueError(
            f"render_colors has {render_colors.shape[-1]} channels; PolarGS needs {rgb_channels} colour + "
            f"{NUM_AUX} aux channels: render colors=polar_colors(...) in the same rasterization call"
        )
    if render_alphas is not None and tuple(render_alphas.shape) != (*render_colors.shape[:3], 1):
        raise ValueError(f"render_alphas must be [1, H, W, 1], got {tuple(render_alphas.shape)}")
    image = render_colors[0].permute(2, 0, 1)
    return render_out_from_aux(image[:rgb_channels], image[rgb_channels : rgb_channels + NUM_AUX], K=K)


def polar_loss(
    hooks: TrainingHooks,
    step: int,
    view: View,
    render_colors: Tensor,
    render_alphas: Tensor | None,
    info: dict[str, Any] | None,
    params: Mapping[str, Tensor],
    *,
    rgb_channels: int = 3,
) -> tuple[Tensor, dict[str, Tensor]]:
    """The PolarGS loss to add to a gsplat trainer's loss (after ``step_pre_backward``, before
    ``backward``).

    Args:
        hooks: a preprocessed :class:`polargs_plugin.PolarHooks`.
        step: gsplat's 0-based step; the hooks get ``step + 1`` (their iterations are 1-based).
        view: the trained view (:func:`view_from_gsplat`, same name as at ``hooks.preprocess``).
        render_colors: ``rasterization``'s colour output, the colours from :func:`polar_colors`.
        render_alphas: ``rasterization``'s alpha output.
        info: gsplat's ``meta`` dict of this render, or None. When given, ``info["polar_view"]``
            and ``info["polar_render"]`` (the detached RenderOut) are set so that
            :meth:`PolarStrategy.step_post_backward` densifies from this view and render.
        params: the gsplat parameters (for :class:`GaussianState`: L_scale).
        rgb_channels: colour channels before the aux ones.

    Returns:
        ``(loss, logs)`` as :meth:`PolarHooks.loss`: a scalar to add, detached scalar logs.
    """
    render = render_out_from_gsplat(render_colors, render_alphas, rgb_channels=rgb_channels, K=view.K)
    extra, logs = hooks.loss(step + 1, view, render, gaussian_state(params))
    if info is not None:
        info["polar_view"] = view
        info["polar_render"] = render.detached()
    return extra, logs


ColorsFn = Callable[[Mapping[str, Tensor], Tensor], Tensor]


def make_render_fn(
    params: Mapping[str, Tensor],
    rasterize: Callable[..., tuple[Tensor, Tensor, dict]] | None = None,
    *,
    sh_degree: int | None = None,
    colors_fn: ColorsFn | None = None,
    background: Tensor | None = None,
    **raster_kwargs: Any,
) -> Callable[[View], RenderOut]:
    """A ``render_fn(view) -> RenderOut`` over the live gsplat parameters (for Dense's source views).

    The returned function reads ``params`` at call time, so it stays valid when a strategy
    replaces the parameters (keep passing the same dict / ParameterDict).

    Args:
        params: the gsplat parameters dict.
        rasterize: ``gsplat.rasterization`` (default) or a function with its signature.
        sh_degree: active SH degree for :func:`sh_colors` (default: all bands).
        colors_fn: ``(params, viewmats) -> (N, 3)`` colours, replacing :func:`sh_colors`
            (e.g. appearance-optimised colours).
        background: optional (3,) background colour (as the trainer's).
        **raster_kwargs: passed to ``rasterize`` (``packed``, ``near_plane``, ``rasterize_mode``...).

    Returns:
        The render function; its RenderOut is detached, colour clamped to [0, 1].
    """
    if rasterize is None:
        from gsplat import rasterization as rasterize

    def render_fn(view: View) -> RenderOut:
        with torch.no_grad():
            means = params["means"]
            viewmats, Ks = gsplat_cameras(view, means.device)
            rgb = colors_fn(params, viewmats) if colors_fn is not None else sh_colors(params, viewmats, sh_degree)
            colors = polar_colors(rgb, params, viewmats)
            backgrounds = None if background is None else polar_backgrounds(background.to(means).reshape(1, 3))
            render_colors, render_alphas, _ = rasterize(
                means, params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
                colors, viewmats, Ks, view.width, view.height,
                sh_degree=None, backgrounds=backgrounds, **raster_kwargs,
            )
            render = render_out_from_gsplat(render_colors, render_alphas, rgb_channels=rgb.shape[-1], K=view.K)
            return dataclasses.replace(render.detached(), color=render.color.clamp(0, 1))

    return render_fn
