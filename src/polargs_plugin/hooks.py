"""PolarHooks: the four calls a 3DGS trainer makes to gain PolarGS (docs/conventions.md).

A trainer calls, in this order::

    hooks = PolarHooks(config)
    hooks.preprocess(views)                                   # once, before training
    for it in ...:
        render = render_fn(view)
        loss = own_colour_loss(render.color, view.image)      # + the trainer's other terms
        extra, logs = hooks.loss(it, view, render, gaussians)
        (loss + extra).backward(); optimizer.step()
        new = hooks.densify(it, view, render_fn, gaussians)   # NewGaussians or None
        if new is not None: append(new)

Ablations are config switches: ``correction.enabled`` (PC), ``densify.enabled`` (Dense) and
``losses.use_ref / use_normal / use_depth_normal / use_scale``. With Dense off the densify
package is never imported.

What is given to the hooks is checked at the door (docs/choices.md "Checks at the hooks' door"):
``preprocess`` refuses views with non-finite values or wrong shapes (naming the view), reports
physically impossible Stokes per view (refusing a view above
``correction.max_impossible_fraction``) and warns once per view whose s0 / 2 leaves [0, 1];
``loss`` and ``densify`` check the shapes of the render they read (cheap; no per-step scan of
the render's values), with messages that name the argument, the expected and the actual shape,
and refuse an iteration below 1. The config itself is checked when the hooks are built
(``PolarConfig.validate``: a value out of its field's range is refused, named ``config.<field>``).
A cache entry whose values are not finite or whose shapes do not fit the view is recomputed.
"""

from __future__ import annotations

import numbers
import warnings
from functools import partial
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from polargs_plugin.config import PolarConfig
from polargs_plugin.correction import compute_polar_maps, input_range, physical_stokes
from polargs_plugin.correction.store import (
    MEMORY_BUDGET, BytesLRU, MapsStore, maps_cache_file, maps_cache_key, tensor_bytes,
)
from polargs_plugin.io import PolarInputError
from polargs_plugin.losses import (
    ReflectiveTargets, depth_normal_loss, normal_loss, normals_within, polar_normal_loss, scale_loss,
)
from polargs_plugin.optics.single_view import single_view_normals
from polargs_plugin.types import (
    GaussianState, NewGaussians, PolarMaps, RenderOut, View, describe_view, validate_view,
)

__all__ = ["PolarHooks", "maps_cache_key", "maps_cache_file"]  # the cache's key and file: correction.store


def _check_shape(where: str, argument: str, tensor: Any, expected: tuple[int, ...], view: View) -> None:
    """Raise ValueError naming ``argument`` when ``tensor`` does not have shape ``expected``."""
    if not isinstance(tensor, Tensor):
        raise ValueError(f"{where}: {argument} is {type(tensor).__name__}, expected a tensor of shape "
                         f"{expected} like view '{view.name}'")
    if tuple(tensor.shape) != expected:
        raise ValueError(f"{where}: {argument} has shape {tuple(tensor.shape)}, expected {expected} "
                         f"like view '{view.name}'")


def _check_iteration(where: str, iteration: Any) -> None:
    """Raise ValueError unless ``iteration`` is an integer >= 1 (the first step is iteration 1)."""
    if isinstance(iteration, bool) or not isinstance(iteration, numbers.Integral) or iteration < 1:
        raise ValueError(f"{where}: iteration must be an integer >= 1 (iterations are 1-based), got {iteration!r}")


def _check_placement(where: str, tensors: Sequence[tuple[str, Tensor, torch.dtype | None]], view: View) -> None:
    """Raise ValueError naming the argument when a tensor is on the meta device (no values), on
    another device than the first one, or (where a dtype is given) of another dtype."""
    first: tuple[str, torch.device] | None = None
    for argument, tensor, dtype in tensors:
        if tensor.device.type == "meta":
            raise ValueError(f"{where}: {argument} is on the meta device, which holds no values; expected a "
                             "tensor on the device the trainer renders on")
        if dtype is not None and tensor.dtype != dtype:
            raise ValueError(f"{where}: {argument} has dtype {tensor.dtype}, expected {dtype} like the maps of "
                             f"view '{view.name}'")
        if first is None:
            first = (argument, tensor.device)
        elif tensor.device != first[1]:
            raise ValueError(f"{where}: {argument} is on {tensor.device} but {first[0]} on {first[1]}; give every "
                             "tensor on one device")


def _check_render(where: str, render: RenderOut, view: View, dtype: torch.dtype, argument: str = "render",
                  fields: Sequence[str] = ("depth", "normal", "alpha")) -> None:
    """The ``fields`` of ``render`` (what the hooks read): shapes those of ``view``, dtype
    ``dtype`` (the maps'), all on one real device."""
    height, width = view.height, view.width
    shapes = {"color": (3, height, width), "depth": (1, height, width), "normal": (3, height, width),
              "alpha": (1, height, width), "plane_depth": (1, height, width)}
    for name in fields:
        _check_shape(where, f"{argument}.{name}", getattr(render, name, None), shapes[name], view)
    _check_placement(where, [(f"{argument}.{name}", getattr(render, name), dtype) for name in fields], view)


class PolarHooks:
    """PolarGS as trainer hooks: preprocessing, extra losses, densification, state.

    Args:
        config: all settings (default: :meth:`PolarConfig.synthetic`, the paper's synthetic
            preset). ``config.cache_dir`` set means preprocess caches its maps there, keyed by
            :func:`maps_cache_key`.

    Iterations are 1-based (the first optimisation step is iteration 1), as everywhere in
    :class:`polargs_plugin.types.TrainingHooks`; :meth:`loss` and :meth:`densify` refuse 0 and
    negative ones.

    Raises:
        ValueError: a field of ``config`` out of its range (one line naming it, e.g.
            ``config.densify.interval: must be a positive integer, got 0``).
    """

    def __init__(self, config: PolarConfig | None = None) -> None:
        self.config = config if config is not None else PolarConfig.synthetic()
        self.config.validate("config")  # attributes may have been reassigned since it was built
        self.maps = MapsStore(None)
        self._densifier: Any = None
        self._pending_state: dict[str, Any] | None = None
        # per-view constants of L_ref, built from the maps when first used, kept within a budget
        # when every view's fit (BytesLRU's cycle)
        self._reflective = BytesLRU(MEMORY_BUDGET)
        # per-view inputs of the single-view polarimetric normal (losses.use_polar_normal), alike
        self._polar_inputs = BytesLRU(MEMORY_BUDGET)
        self._warned: set[tuple[str, str, str]] = set()  # (kind, view name, source): warn once
        self._shapes: dict[str, tuple[int, int]] = {}

    # ----------------------------------------------------------------------------- preprocess
    def preprocess(self, views: list[View]) -> Sequence[PolarMaps]:
        """Compute (or load from the cache) every view's :class:`PolarMaps`; build the densifier.

        The maps are kept compact (:class:`~polargs_plugin.correction.store.MapsStore`: in
        ``config.cache_dir`` when set, else in memory) and decoded when a view is used.

        Args:
            views: the training views (unique names).

        Returns:
            One :class:`PolarMaps` per view, in order (a sequence that decodes an entry when it is
            indexed).
        """
        names = [view.name for view in views]
        if len(set(names)) != len(names):
            raise ValueError("view names must be unique: the maps are looked up by name")
        for view in views:
            validate_view(view, "hooks.preprocess")
            self._check_physics(view)
        self._shapes = {view.name: (view.height, view.width) for view in views}
        self._reflective.clear()
        self._reflective.set_cycle(len(views))
        self._polar_inputs.clear()
        self._polar_inputs.set_cycle(len(views))
        self.maps = MapsStore(self.config.cache_dir)
        for view in views:
            self.maps.prepare(view, self.config, partial(self._compute_maps, view))
        self.maps.cycle_through(len(views))
        if self.config.densify.enabled:
            from polargs_plugin.densify.densifier import PolarDensifier

            self._densifier = PolarDensifier(self.config, views, self.maps)
            if self._pending_state is not None:
                self._densifier.load_state_dict(self._pending_state)
                self._pending_state = None
        return self.maps.sequence(names)

    def _check_physics(self, view: View) -> None:
        """Warn once per view whose s0 / 2 leaves [0, 1]; report impossible Stokes (one warning
        per view with the counts) and refuse a view beyond ``max_impossible_fraction``."""
        cfg = self.config.correction
        where = describe_view(view)
        low, high = input_range(view.stokes)
        key = ("range", view.name, view.source)
        if (low < -1e-6 or high > 1 + 1e-6) and key not in self._warned:
            self._warned.add(key)
            warnings.warn(
                f"{where}: intensities s0/2 span [{low:.4g}, {high:.4g}], not the [0, 1] of 8-bit LDR "
                f"images; brightness is measured against correction.white_level = {cfg.white_level:g} "
                "and values above it count as saturated (reflective masks, never I_chro donors), and "
                "trainers clamp the colour target to [0, 1] (docs/choices.md 'HDR inputs')",
                stacklevel=3,
            )
        _, check = physical_stokes(view.stokes, cfg.stokes_tolerance * cfg.white_level, view.mask)
        if check.impossible == 0:
            return
        counts = (f"{check.impossible} of {check.total} pixels ({100 * check.fraction:.2f} %) have physically "
                  f"impossible Stokes beyond the noise allowance {cfg.stokes_tolerance:g} "
                  f"({check.negative} with s0 < 0, {check.over_polarized} with s1^2 + s2^2 > s0^2)")
        if check.fraction > cfg.max_impossible_fraction:
            raise PolarInputError(
                view.source or view.name,
                f"hooks.preprocess: {where}: {counts}, more than correction.max_impossible_fraction = "
                f"{cfg.max_impossible_fraction:g}: the reader's scale or sign convention of s0/s1/s2 is "
                "probably wrong (docs/conventions.md: s0 = (I0 + I45 + I90 + I135) / 2, s1 = I0 - I90)",
            )
        key = ("physics", view.name, view.source)
        if key not in self._warned:
            self._warned.add(key)
            warnings.warn(f"{where}: {counts}; clamped onto s0 >= 0, DoLP <= 1 (docs/choices.md "
                          "'Impossible Stokes')", stacklevel=3)

    def _compute_maps(self, view: View) -> PolarMaps:
        return compute_polar_maps(view.stokes, view.mask, self.config.correction)

    def _reflective_targets(self, view: View, device: torch.device) -> ReflectiveTargets | None:
        """The view's :class:`ReflectiveTargets` on ``device`` (built on first use), or ``None``
        when its maps have no reflective masks."""
        key = (view.name, torch.device(device))
        cached = self._reflective.get(key)
        if cached is not None:
            return cached[0]
        if view.name not in self.maps:
            raise KeyError(f"view '{view.name}' was not preprocessed: call hooks.preprocess(views) first")
        maps = self.maps[view.name]
        targets = None
        if maps.specular_mask is not None:
            # Clamped like the trainers' targets, so the plain part cancels their colour loss.
            targets = ReflectiveTargets(
                maps.intensity.clamp(0, 1).to(device),
                maps.specular_mask.to(device),
                maps.i_diff.to(device),
                (maps.overexposed_mask & maps.extras["i_chro_valid"]).to(device),
                maps.i_chro.to(device),
            )
        self._reflective.put(key, (targets,), tensor_bytes(targets))
        return targets

    # ----------------------------------------------------------------------------------- loss
    def loss(
        self, iteration: int, view: View, render: RenderOut, gaussians: GaussianState
    ) -> tuple[Tensor, dict[str, Tensor]]:
        r"""The loss to ADD to the trainer's own loss, before backward.

        Contract for PC (the reflective-aware colour loss). The trainer's colour loss is assumed
        to be :func:`polargs_plugin.losses.photometric_loss` ``(render.color, view.image)``, i.e.
        :math:`(1-\lambda)` mean L1 + :math:`\lambda` (1 - mean SSIM) over the whole image with
        :math:`\lambda` = ``config.losses.ssim_weight`` (vanilla 3DGS's form). The returned loss
        contains ``lambda_ref * L_ref - L_plain(reflective)``, where ``L_plain(reflective)`` is that
        same colour loss summed over the reflective pixels only (all terms divided by H*W). So
        trainer loss + extra = L_non + lambda_ref * L_ref exactly: the plain colour loss is
        replaced on reflective pixels, untouched elsewhere. A trainer whose colour loss differs
        (another SSIM), or whose target differs from ``view.image`` clamped to [0, 1] (e.g. a
        background composited outside ``view.mask``), gets the replacement up to that difference
        inside the SSIM windows of reflective pixels (the L1 part stays exact).

        Other terms: ``alpha * L_n`` once the densifier holds a PatchMatch normal for this view,
        on all its pixels until ``losses.normal_until_after_dense`` iterations past the Dense
        window, and after that (the targets are no longer refreshed) only where the rendered
        normal lies within ``losses.normal_hold_deg`` of the target; with
        ``losses.use_polar_normal``, alongside it ``alpha_polar_normal * L_pn``, L_n against the
        view's own single-view polarimetric normal on the pixels where N_opt is invalid
        (:func:`polargs_plugin.losses.polar_normal_loss`);
        ``beta * L_dn`` from ``config.losses.depth_normal_from_iter`` on, on ``render.plane_depth``
        (the unbiased plane depth, as PGSR) where the renderer gives it, else on ``render.depth``;
        ``gamma * L_scale``.
        Only the terms switched on at this iteration are computed, from per-view constants built
        when a view is first used (and kept within a memory budget); nothing here waits for the device (the logs stay tensors).

        Args:
            iteration: the trainer's iteration (1-based: the first step is 1).
            view: the rendered view (preprocessed).
            render: the render of ``view``.
            gaussians: the current Gaussians (activated, autograd-connected).

        Returns:
            ``(extra, logs)``: scalar tensor on the render's device and a dict of detached scalar
            tensors (each active term, unweighted; ``float()`` them only when logging).
        """
        cfg = self.config.losses
        _check_iteration("hooks.loss", iteration)
        self._check_loss_inputs(iteration, view, render, gaussians)
        color = render.color
        terms: list[Tensor] = []
        logs: dict[str, Tensor] = {}
        if self.config.correction.enabled and cfg.use_ref:
            targets = self._reflective_targets(view, color.device)
            if targets is not None:
                pc, l_s, l_o, plain = targets(color, cfg.lambda_ref, cfg.ssim_weight)
                terms.append(pc)
                logs.update(l_s=l_s.detach(), l_o=l_o.detach(), l_plain_reflective=plain.detach())
        if cfg.use_normal and self._normal_loss_on(iteration):
            target = self.normal_target(view.name)
            if target is not None:
                normal, confirmed = (t.to(color.device) for t in target)
                valid = confirmed
                if not self._normal_targets_fresh(iteration):
                    valid = valid & normals_within(render.normal.detach(), normal, cfg.normal_hold_deg)
                l_n = normal_loss(render.normal, normal, valid)
                terms.append(cfg.alpha_normal * l_n)
                logs["l_n"] = l_n.detach()
                if cfg.use_polar_normal:
                    l_pn = self._polar_normal_loss(view, render, ~confirmed)
                    terms.append(cfg.alpha_polar_normal * l_pn)
                    logs["l_pn"] = l_pn.detach()
        if cfg.use_depth_normal and iteration >= cfg.depth_normal_from_iter:
            depth = render.plane_depth if render.plane_depth is not None else render.depth
            l_dn = depth_normal_loss(depth, render.normal, render.alpha, view.K)
            terms.append(cfg.beta_depth_normal * l_dn)
            logs["l_dn"] = l_dn.detach()
        if cfg.use_scale:
            l_scale = scale_loss(gaussians.scales)
            terms.append(cfg.gamma_scale * l_scale)
            logs["l_scale"] = l_scale.detach()
        extra = sum(terms[1:], terms[0]) if terms else color.new_zeros(())
        return extra, logs

    def _polar_normal_loss(self, view: View, render: RenderOut, unconfirmed: Tensor) -> Tensor:
        """L_n against the view's single-view polarimetric normal (``losses.use_polar_normal``) on
        the ``unconfirmed`` pixels (N_opt invalid) where the render is opaque
        (``densify.alpha_threshold``) and inside the view's mask."""
        cfg = self.config.losses
        device = render.normal.device
        key = (view.name, torch.device(device))
        cached = self._polar_inputs.get(key)
        if cached is None:
            maps = self.maps[view.name]
            cached = tuple(None if t is None else t.to(device)
                           for t in (maps.aolp, maps.dolp, maps.specular_mask, maps.overexposed_mask, view.mask))
            self._polar_inputs.put(key, cached, tensor_bytes(cached))
        aolp, dolp, specular, overexposed, mask = cached
        target = single_view_normals(
            aolp, dolp, render.normal, view.K, self.config.densify.patchmatch.azimuth_model,
            cfg.polar_normal_refractive_index, min_dolp=cfg.polar_normal_min_dolp,
            zenith_min_dolp=cfg.polar_normal_zenith_min_dolp, specular_mask=specular, overexposed_mask=overexposed,
        )
        where = unconfirmed & (render.alpha.detach() > self.config.densify.alpha_threshold)
        return polar_normal_loss(render.normal, target, where if mask is None else where & mask)

    def _check_view_known(self, where: str, view: View) -> None:
        if not isinstance(getattr(view, "stokes", None), Tensor):
            raise ValueError(f"{where}: view '{getattr(view, 'name', '?')}' has no Stokes (view.stokes is "
                             f"{type(getattr(view, 'stokes', None)).__name__}); expected a (3, C, H, W) tensor")
        shape = self._shapes.get(view.name)
        if shape is None:
            raise KeyError(f"{where}: view '{view.name}' was not preprocessed: call hooks.preprocess(views) first")
        if shape != (view.height, view.width):
            raise ValueError(f"{where}: view.stokes is {view.height}x{view.width}, but view '{view.name}' was "
                             f"preprocessed at {shape[0]}x{shape[1]}")

    def _check_loss_inputs(self, iteration: int, view: View, render: RenderOut, gaussians: GaussianState) -> None:
        """Shapes only (cheap): the argument, the expected and the actual shape in the message."""
        where = "hooks.loss"
        self._check_view_known(where, view)
        cfg = self.config.losses
        fields = ["color"] if self.config.correction.enabled and cfg.use_ref else []
        geometry = cfg.use_depth_normal and iteration >= cfg.depth_normal_from_iter
        if geometry:
            fields += ["plane_depth" if render.plane_depth is not None else "depth", "normal", "alpha"]
        elif cfg.use_normal and self._normal_loss_on(iteration) and self.normal_target(view.name) is not None:
            fields += ["normal", "alpha"] if cfg.use_polar_normal else ["normal"]
        _check_render(where, render, view, self._maps_dtype(view), fields=fields)
        if cfg.use_scale:
            scales = getattr(gaussians, "scales", None)
            if not isinstance(scales, Tensor) or scales.ndim != 2 or scales.shape[1] != 3:
                shape = tuple(scales.shape) if isinstance(scales, Tensor) else type(scales).__name__
                raise ValueError(f"{where}: gaussians.scales has shape {shape}, expected (N, 3)")
            read = [(f"render.{name}", getattr(render, name), None) for name in fields]
            _check_placement(where, read + [("gaussians.scales", scales, None)], view)

    def _maps_dtype(self, view: View) -> torch.dtype:
        """The dtype of a preprocessed view's maps, which a render's tensors must share."""
        return self.maps.dtype(view.name)  # without decoding the maps (the step reads them once, later)

    def geometry_needed(self, iteration: int, view_name: str) -> bool:
        """Whether :meth:`loss` reads the render's depth, normal or alpha at this iteration for
        this view (L_n with a PatchMatch target, or L_dn). An adapter whose trainer renders
        those maps in an extra pass can skip the pass when this is False: :meth:`loss` then reads
        only ``render.color``."""
        cfg = self.config.losses
        if cfg.use_depth_normal and iteration >= cfg.depth_normal_from_iter:
            return True
        return cfg.use_normal and self._normal_loss_on(iteration) and self.normal_target(view_name) is not None

    # -------------------------------------------------------------------------------- densify
    def densify_due(self, iteration: int) -> bool:
        """Whether :meth:`densify` runs Dense at ``iteration`` (Dense on and the iteration on its
        schedule, ``config.densify``); elsewhere it returns None, so a trainer can skip the call
        and the Gaussians' state it would build for it."""
        return self._densifier is not None and self._densifier.should_run(iteration)

    def densify(
        self,
        iteration: int,
        view: View,
        render_fn: Callable[[View], RenderOut],
        gaussians: GaussianState,
        render: RenderOut | None = None,
    ) -> NewGaussians | None:
        """Polar-enhanced densification (module Dense) after the optimizer step, under no_grad.

        Args:
            iteration: the trainer's iteration (1-based).
            view: the current view.
            render_fn: renders any view (the sources, and the reference when ``render`` is None)
                with the current Gaussians.
            gaussians: the current Gaussians.
            render: the caller's render of ``view`` from this iteration (depth, normal, alpha are
                read; detached or not), so the reference is not rendered again. It predates the
                optimizer step by one step, which PatchMatch's initialisation does not notice.

        Returns:
            Gaussians to append, or ``None`` (off schedule, Dense disabled, nothing survived).
        """
        where = "hooks.densify"
        _check_iteration(where, iteration)
        if self._densifier is None:
            return None
        self._check_view_known(where, view)
        if render is not None:
            _check_render(where, render, view, self._maps_dtype(view))

        def checked_render_fn(source: View) -> RenderOut:
            out = render_fn(source)
            _check_render(where, out, source, self._maps_dtype(source), argument=f"render_fn(view '{source.name}')")
            return out

        with torch.no_grad():
            return self._densifier(iteration, view, checked_render_fn, gaussians, render=render)

    def consistency_filter(
        self, depths: Sequence[Tensor], normals: Sequence[Tensor] | None, views: Sequence[View], **kwargs: Any
    ) -> Tensor:
        """:func:`polargs_plugin.densify.filters.consistency_filter` with this config's filter
        settings and, for preprocessed views, their AoLP / DoLP maps as defaults.

        Usable on its own, e.g. to clean another MVS's depth and normal maps.

        Args:
            depths: per view :math:`(1, H, W)` camera-z depth.
            normals: per view :math:`(3, H, W)` camera-frame normals (or ``None``).
            views: the cameras of the same views.
            **kwargs: passed on (``aolps``, ``dolps``, ``config``, ``reference``, ``sources``).

        Returns:
            The consistency mask(s), as the filter returns them.
        """
        from polargs_plugin.densify.filters import consistency_filter

        kwargs.setdefault("config", self.config.densify.filters)
        if all(view.name in self.maps for view in views):
            kwargs.setdefault("aolps", [self.maps[view.name].aolp for view in views])
            kwargs.setdefault("dolps", [self.maps[view.name].dolp for view in views])
        return consistency_filter(depths, normals, views, **kwargs)

    def _normal_targets_fresh(self, iteration: int) -> bool:
        after = self.config.losses.normal_until_after_dense
        return after is None or iteration <= self.config.densify.end_iter + after

    def _normal_loss_on(self, iteration: int) -> bool:
        return self.config.losses.normal_hold_deg is not None or self._normal_targets_fresh(iteration)

    def normal_target(self, view_name: str) -> tuple[Tensor, Tensor] | None:
        """The latest PatchMatch normal of a view, ``(normal (3, H, W), valid (1, H, W) bool)``,
        or ``None`` before PatchMatch has run on it (or with Dense off)."""
        if self._densifier is None:
            return None
        return self._densifier.normal_target(view_name)

    # ---------------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint needs to resume (the densifier's state; maps are recomputed or cached)."""
        if self._densifier is not None:
            return {"densifier": self._densifier.state_dict()}
        return {"densifier": self._pending_state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; before :meth:`preprocess` it is kept and applied there."""
        densifier_state = state.get("densifier")
        if densifier_state is None:
            return
        if self._densifier is not None:
            self._densifier.load_state_dict(densifier_state)
        else:
            self._pending_state = densifier_state
