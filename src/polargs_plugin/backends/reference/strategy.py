"""Vanilla 3DGS adaptive density control as a strategy object with an explicit state (gsplat style).

Per iteration, after ``backward()``, :meth:`DensityControl.update` accumulates the screen-space
positional gradient norm of every visible Gaussian (in NDC units, as vanilla 3DGS: pixel
gradients times ``(W / 2, H / 2)``). After the optimizer step, :meth:`DensityControl.step`
refines on the schedule:

- clone Gaussians whose mean gradient exceeds ``grow_grad2d`` and whose largest scale is at most
  ``grow_scale3d * extent``; split (2 samples, scales / 1.6) the larger ones;
- prune opacity below ``prune_opa`` and, after the first opacity reset, Gaussians larger than
  ``prune_scale3d * extent`` in the world or ``prune_screen_px`` on screen;
- every ``reset_every`` iterations clamp opacities to ``2 * prune_opa`` (unless
  ``opacity_reset`` is off: at vanilla learning rates opacities need a few hundred iterations
  to recover from a reset whatever the schedule factor, so very short runs skip it).

Iterations are 1-based as in vanilla 3DGS. Every schedule number is multiplied by one factor
(:meth:`DensityConfig.scaled`) so that CPU runs can be short.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from polargs_plugin.backends.reference.model import PARAM_NAMES, GaussianModel
from polargs_plugin.config import CheckedConfig, above, at_least, within
from polargs_plugin.types import RenderOut

__all__ = ["DensityConfig", "DensityControl"]


@dataclass
class DensityConfig(CheckedConfig):
    """Vanilla 3DGS densification settings (graphdeco 3DGS's ``arguments/__init__.py`` and
    ``densify_and_prune``); every default is vanilla's except ``max_gaussians``.

    Iterations are 1-based; the schedule counts are multiplied by ``TrainConfig.schedule_scale``
    (:meth:`scaled`). World sizes are fractions of the scene extent.

    Attributes:
        grow_grad2d: mean screen-space positional gradient norm (NDC units) above which a
            Gaussian is cloned or split; >= 0. Default and vanilla 0.0002.
        grow_scale3d: Gaussians whose largest scale is at most this fraction of the extent are
            cloned, larger ones split (vanilla's ``percent_dense``); >= 0. Default 0.01.
        split_samples: Gaussians a split Gaussian becomes; >= 1. Default and vanilla 2.
        split_scale_divisor: the split Gaussians' scales are the parent's divided by this
            (vanilla: 0.8 times ``split_samples``); > 0. Default 1.6.
        prune_opa: Gaussians with a lower opacity are pruned; an opacity reset sets opacities to
            twice it; in [0, 1). Default and vanilla 0.005.
        prune_scale3d: after the first opacity reset, Gaussians larger than this fraction of the
            extent are pruned; > 0. Default and vanilla 0.1.
        prune_screen_px: after the first opacity reset, Gaussians whose screen radius exceeded
            this many pixels since the last refinement are pruned; > 0. Default and vanilla 20.
        prune_screen_fraction: when set, the screen limit is this fraction of the widest view's
            width instead of ``prune_screen_px``: a model capped at a few thousand Gaussians
            (``max_gaussians``) covers a larger image with larger splats, and an absolute limit
            tuned at one size prunes the whole model at a larger one (``TrainConfig.cpu`` sets
            20 / 128, vanilla's 20 px at the bundled scenes' 128 px); in (0, 1], or None
            (default): ``prune_screen_px``.
        refine_start: refinement runs at iterations after this one; >= 0. Default and vanilla 500.
        refine_stop: no refinement, and no statistics, from this iteration on; >= 0 (at most
            ``refine_start``: vanilla density control off). Default and vanilla 15000.
        refine_every: iterations between refinements; >= 1. Default and vanilla 100.
        reset_every: iterations between opacity resets; >= 1. Default and vanilla 3000.
        opacity_reset: reset opacities at all (``TrainConfig.cpu`` turns it off: at vanilla
            learning rates opacities need a few hundred iterations to recover). Default True.
        max_gaussians: no clone / split beyond this count; >= 0, or None: unlimited (default, as
            vanilla). It bounds vanilla density control only: Gaussians appended by the PolarGS
            densify hook are not capped (capping them at a full model would switch Dense off),
            so a Full run can exceed it by Dense's appends. They count towards N all the same:
            once they take N past the cap, clone and split stop until pruning brings N back below
            it (the CPU preset reaches its 6000 by iteration ~250).
    """

    grow_grad2d: float = field(default=2e-4, metadata=at_least(0))
    grow_scale3d: float = field(default=0.01, metadata=at_least(0))
    split_samples: int = field(default=2, metadata=at_least(1))
    split_scale_divisor: float = field(default=1.6, metadata=above(0))
    prune_opa: float = field(default=0.005, metadata=within(0, 1, high_open=True))
    prune_scale3d: float = field(default=0.1, metadata=above(0))
    prune_screen_px: float = field(default=20.0, metadata=above(0))
    prune_screen_fraction: float | None = field(default=None, metadata=within(0, 1, low_open=True))
    refine_start: int = field(default=500, metadata=at_least(0))
    refine_stop: int = field(default=15_000, metadata=at_least(0))
    refine_every: int = field(default=100, metadata=at_least(1))
    reset_every: int = field(default=3000, metadata=at_least(1))
    opacity_reset: bool = True
    max_gaussians: int | None = field(default=None, metadata=at_least(0))

    def scaled(self, factor: float) -> "DensityConfig":
        """A copy with start, stop, interval and reset interval multiplied by ``factor``."""
        if factor <= 0:
            raise ValueError(f"DensityConfig.scaled: factor must be positive, got {factor}")
        return replace(
            self,
            refine_start=round(self.refine_start * factor),
            refine_stop=round(self.refine_stop * factor),
            refine_every=max(1, round(self.refine_every * factor)),
            reset_every=max(1, round(self.reset_every * factor)),
        )


class DensityControl:
    """Vanilla clone / split / prune / opacity reset with an explicit, checkpointable state.

    Args:
        config: thresholds and (already scaled) schedule.
        extent: scene extent (world-size thresholds are relative to it).
        image_width: the widest training view's width in pixels, for
            ``config.prune_screen_fraction``.

    State (``state_dict()``): ``grad2d`` (N,) summed NDC gradient norms, ``count`` (N,) number of
    accumulations, ``max_radii`` (N,) largest screen radius in pixels since the last refinement.
    """

    def __init__(self, config: DensityConfig, extent: float, image_width: int | None = None):
        if config.prune_screen_fraction is not None and image_width is None:
            raise ValueError("DensityControl: prune_screen_fraction needs the image width")
        self.config = config
        self.extent = float(extent)
        #: the screen radius in pixels above which a Gaussian is pruned (after the first reset)
        self.screen_limit_px = (config.prune_screen_px if config.prune_screen_fraction is None
                                else config.prune_screen_fraction * image_width)
        self.state: dict[str, Tensor | None] = {"grad2d": None, "count": None, "max_radii": None}

    # -------------------------------------------------------------------- statistics
    def _ensure(self, n: int, device: torch.device) -> None:
        if self.state["grad2d"] is None or self.state["grad2d"].shape[0] != n:
            if self.state["grad2d"] is not None:
                raise RuntimeError(
                    f"DensityControl: statistics track {self.state['grad2d'].shape[0]} Gaussians but the model "
                    f"has {n}; call pad() after appending"
                )
            self.state = {k: torch.zeros(n, device=device) for k in ("grad2d", "count", "max_radii")}

    def update(self, render: RenderOut, width: int, height: int, iteration: int) -> None:
        """Accumulate statistics from a render whose ``means2d.grad`` is populated (after backward).

        Does nothing outside ``iteration < refine_stop`` (vanilla).
        """
        if iteration >= self.config.refine_stop:
            return
        if render.means2d is None or render.means2d.grad is None or render.radii is None:
            raise RuntimeError("DensityControl.update: the render has no means2d gradient or radii")
        grad = render.means2d.grad.detach()
        self._ensure(grad.shape[0], grad.device)
        # Dense masked updates instead of boolean indexing: no nonzero() (a host sync on CUDA), no
        # gathers; the same values bit for bit (invisible rows add exactly 0; radii are 0 there
        # and max_radii >= 0).
        visible = render.radii > 0
        norms = (grad * self._ndc_scale(width, height, grad)).norm(dim=-1)
        self.state["grad2d"].add_(torch.where(visible, norms, torch.zeros_like(norms)))
        self.state["count"].add_(visible.to(self.state["count"].dtype))
        torch.maximum(self.state["max_radii"], render.radii.to(self.state["max_radii"]), out=self.state["max_radii"])

    def _ndc_scale(self, width: int, height: int, like: Tensor) -> Tensor:
        """(2,) pixel-to-NDC gradient factors ``(W / 2, H / 2)``, built once per image size."""
        key = (width, height, like.device, like.dtype)
        if getattr(self, "_scale_key", None) != key:
            self._scale_key = key
            self._scale = like.new_tensor([width / 2.0, height / 2.0])
        return self._scale

    def pad(self, m: int) -> None:
        """Extend the statistics with ``m`` zero rows (after ``GaussianModel.append``)."""
        if self.state["grad2d"] is None:
            return
        self.state = {k: torch.cat([v, v.new_zeros(m)]) for k, v in self.state.items()}

    # -------------------------------------------------------------------- refinement
    def step(self, model: GaussianModel, iteration: int) -> dict[str, int]:
        """Refine ``model`` if the schedule says so (call after the optimizer step).

        Returns:
            ``{"refined", "cloned", "split", "pruned", "reset"}``: flags and counts (zeros when
            nothing ran).
        """
        c = self.config
        out = {"refined": 0, "cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if iteration >= c.refine_stop:
            return out
        if iteration > c.refine_start and iteration % c.refine_every == 0 and self.state["grad2d"] is not None:
            out.update(self.refine(model, prune_large=iteration > c.reset_every), refined=1)
        if c.opacity_reset and iteration % c.reset_every == 0:
            model.reset_opacity(2 * c.prune_opa)
            out["reset"] = 1
        return out

    @torch.no_grad()
    def refine(self, model: GaussianModel, prune_large: bool) -> dict[str, int]:
        """One clone + split + prune pass from the accumulated statistics; statistics reset to zero."""
        c = self.config
        self._ensure(model.num, model.means.device)
        grads = self.state["grad2d"] / self.state["count"].clamp_min(1)
        high = grads >= c.grow_grad2d
        small = model.scales.max(dim=1).values <= c.grow_scale3d * self.extent
        clone, split = high & small, high & ~small
        if c.max_gaussians is not None:
            clone, split = self._limit_growth(clone, split, model.num, grads)
        n_clone, n_split = int(clone.sum()), int(split.sum())
        self._clone(model, clone)
        self._split(model, torch.cat([split, split.new_zeros(n_clone)]))

        prune = model.opacities < c.prune_opa
        if prune_large:
            prune |= model.scales.max(dim=1).values > c.prune_scale3d * self.extent
            prune |= self.state["max_radii"] > self.screen_limit_px
        n_prune = int(prune.sum())
        if n_prune:
            self._keep(model, ~prune)
        self.state = {k: torch.zeros_like(v) for k, v in self.state.items()}
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _limit_growth(self, clone: Tensor, split: Tensor, n: int, grads: Tensor) -> tuple[Tensor, Tensor]:
        """Keep only the highest-gradient candidates so that N does not exceed ``max_gaussians``."""
        budget = max(int(self.config.max_gaussians) - n, 0)  # a split adds one, a clone adds one
        grow = clone | split
        if int(grow.sum()) <= budget:
            return clone, split
        order = torch.argsort(torch.where(grow, grads, grads.new_full((), -1.0)), descending=True)
        chosen = torch.zeros_like(grow)
        chosen[order[:budget]] = True
        return clone & chosen, split & chosen

    def _clone(self, model: GaussianModel, sel: Tensor) -> None:
        m = int(sel.sum())
        if m == 0:
            return
        model.extend({name: getattr(model, name).detach()[sel] for name in PARAM_NAMES})
        self.state = {k: torch.cat([v, v[sel]]) for k, v in self.state.items()}

    def _split(self, model: GaussianModel, sel: Tensor) -> None:
        m = int(sel.sum())
        if m == 0:
            return
        k = self.config.split_samples
        scales = model.scales.detach()[sel].repeat(k, 1)
        rot = model.rotation_matrices()[sel].repeat(k, 1, 1)
        offsets = torch.bmm(rot, (torch.randn_like(scales) * scales).unsqueeze(-1)).squeeze(-1)
        rows = {name: _repeat_rows(getattr(model, name).detach()[sel], k) for name in PARAM_NAMES}
        rows["means"] = rows["means"] + offsets
        rows["log_scales"] = torch.log(scales / self.config.split_scale_divisor)
        model.extend(rows)
        self.state = {key: torch.cat([v, _repeat_rows(v[sel], k)]) for key, v in self.state.items()}
        self._keep(model, torch.cat([~sel, sel.new_ones(m * k)]))

    def _keep(self, model: GaussianModel, mask: Tensor) -> None:
        model.keep(mask)
        self.state = {k: v[mask] for k, v in self.state.items()}

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict:
        return {k: (None if v is None else v.detach().clone()) for k, v in self.state.items()}

    def load_state_dict(self, state: dict) -> None:
        unknown = set(state) - set(self.state)
        if unknown:
            raise KeyError(f"DensityControl.load_state_dict: unknown keys {sorted(unknown)}")
        self.state = {k: (None if state.get(k) is None else state[k].clone()) for k in self.state}


def _repeat_rows(t: Tensor, k: int) -> Tensor:
    """Stack ``k`` copies of ``t`` along dim 0 (copy j of row i at j * len(t) + i)."""
    return t.repeat(k, *([1] * (t.ndim - 1)))
