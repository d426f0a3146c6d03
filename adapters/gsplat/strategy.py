"""PolarStrategy: a gsplat ``Strategy`` that adds PolarGS densification (module Dense) to an
inner gsplat strategy (``DefaultStrategy`` or ``MCMCStrategy``).

One training step of gsplat's ``simple_trainer.py`` with it (``step`` is gsplat's 0-based step)::

    render_colors, render_alphas, info = rasterization(..., colors=polar_colors(...))
    strategy.step_pre_backward(params, optimizers, state, step, info)       # inner's
    loss = own_loss(render_colors[..., :3])
    extra, logs = polar_loss(hooks, step, view, render_colors, render_alphas, info, params)
    (loss + extra).backward()
    for opt in optimizers.values(): opt.step(); opt.zero_grad(set_to_none=True)
    strategy.step_post_backward(params, optimizers, state, step, info, packed=packed)   # lr=... (MCMC)

``step_post_backward`` first runs the inner strategy's step unchanged (grow / prune / reset,
or MCMC relocate / add / noise), then, under ``no_grad``, calls
``hooks.densify(step + 1, view, render_fn, gaussians, render=render)`` (hook iterations are
1-based; Dense thus fires at gsplat steps ``start - 1, start - 1 + interval, ...``) and
appends what it returns: raw rows (:func:`rows_from_new`), zero Adam moments with the step
counter kept (``polargs_plugin.kit.append_rows``), and zero rows for every per-Gaussian tensor
of the strategy state (``grad2d``, ``count``, ``radii``).

Where the view and the renders come from:

- the trained view and its render: ``info["polar_view"]`` / ``info["polar_render"]``, set by
  :func:`polar_loss` on the same ``info`` dict; or the keyword arguments ``view=``, ``render=``;
- renders of other views (PatchMatch sources): the ``render_fn`` field, typically
  ``make_render_fn(params, rasterization)``; or ``info["polar_render_fn"]`` / ``render_fn=``.

Runtime state is the dict of :meth:`initialize_state`: the inner strategy's own entries (same
keys, so the inner strategy reads and writes them unchanged) plus ``state["polar"]``, a dict of
plain counters (``calls``, ``appended``, ``dropped_cap``, ``last_step``); it holds no tensor, so
gsplat's ops, which index every tensor of the state, leave it alone.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Mapping, MutableMapping, Optional, Union

import torch
from torch import Tensor, nn

try:
    from gsplat.strategy import DefaultStrategy, Strategy
except ImportError as error:  # pragma: no cover - exercised only without gsplat
    raise ImportError(
        "polargs_adapters.gsplat needs gsplat: pip install 'polargs_plugin[gsplat]'"
    ) from error

from polargs_plugin.kit import append_rows, logit, raw_from_new
from polargs_plugin.types import NewGaussians, RenderFn, RenderOut, TrainingHooks, View

from .render import RAW_FROM_GSPLAT, gaussian_state

__all__ = ["PolarStrategy", "rows_from_new", "NOT_PER_GAUSSIAN"]

Params = Union[Dict[str, nn.Parameter], nn.ParameterDict]
RowFn = Callable[[NewGaussians, Tensor], Tensor]

NOT_PER_GAUSSIAN = ("binoms", "scene_scale", "polar")
"""Strategy-state keys that are never padded, whatever their shape (MCMC's (51, 51) ``binoms``
would otherwise look per-Gaussian to a shape test when N == 51)."""


def _simple_trainer_colors(new: NewGaussians, like: Tensor) -> Tensor:
    # simple_trainer.py with appearance optimisation stores colours as logits.
    return logit(new.colors.to(like).clamp(0, 1))


def rows_from_new(
    new: NewGaussians, params: Mapping[str, Tensor], extra_rows: Mapping[str, RowFn] | None = None
) -> dict[str, Tensor]:
    """gsplat raw parameter rows of Gaussians to append.

    Args:
        new: activated Gaussians (``PolarHooks.densify``).
        params: the current parameters (names, trailing shapes, device, dtype).
        extra_rows: ``name -> fn(new, param) -> (M, ...) rows`` for parameters other than the
            six of simple_trainer (and ``colors``, logit RGB, of its appearance mode).

    Returns:
        ``{name: (M, ...) rows}`` for every name of ``params``: log scales, logit opacities,
        unit quaternions, SH DC from the colours, zero higher bands; any other parameter without an
        ``extra_rows`` entry gets zero rows.
    """
    like = params["means"]
    sh_rest = params["shN"].shape[1] if "shN" in params else 0
    raw = raw_from_new(new, sh_rest, like=like)
    rows: dict[str, Tensor] = {}
    m = len(new)
    for name, param in params.items():
        if extra_rows is not None and name in extra_rows:
            value = extra_rows[name](new, param)
        elif name in RAW_FROM_GSPLAT:
            value = raw[RAW_FROM_GSPLAT[name]]
        elif name == "colors":
            value = _simple_trainer_colors(new, param)
        else:
            value = param.new_zeros((m, *param.shape[1:]))
        rows[name] = value.detach().to(param).reshape(m, *param.shape[1:])
    return rows


def _missing_render_fn(view: View) -> RenderOut:
    raise ValueError(
        "PolarStrategy: Dense needs renders of source views; set strategy.render_fn "
        "(e.g. make_render_fn(params, rasterization)) or pass render_fn= / info['polar_render_fn']"
    )


def _index_new(new: NewGaussians, index: Tensor) -> NewGaussians:
    return NewGaussians(
        means=new.means[index], quats=new.quats[index], scales=new.scales[index],
        colors=new.colors[index], opacities=new.opacities[index],
    )


@dataclass
class PolarStrategy(Strategy):
    """A gsplat strategy composing an inner strategy with PolarGS densification (Dense).

    Args:
        hooks (TrainingHooks): the PolarGS hooks (a ``PolarHooks``), already ``preprocess``-ed
            with the training views (their names are how Dense finds a view's maps and sources).
            Required; a dataclass default of None only keeps gsplat's all-keyword style.
        inner (Strategy): the gsplat strategy doing the usual density control:
            ``DefaultStrategy()`` (default) or ``MCMCStrategy(...)``; any strategy with the same
            interface works.
        render_fn (callable): ``render_fn(view) -> RenderOut`` with the current Gaussians, for the
            PatchMatch source views (:func:`make_render_fn`). Default None: taken from
            ``info["polar_render_fn"]`` / the ``render_fn=`` argument of ``step_post_backward``.
        cap_max (int): no Polar append beyond this many Gaussians. Default None: the inner
            strategy's ``cap_max`` when it has one (MCMC), else unlimited. Appended Gaussians count
            against MCMC's ``cap_max``; when the new rows do not fit, an evenly spaced subset of them
            is kept (the densifier emits them in image order, so a prefix would cover only the top
            of the image) and the rest are counted in ``state["polar"]["dropped_cap"]``.
        extra_rows (dict): ``name -> fn(new, param) -> rows`` for extra per-Gaussian parameters
            (see :func:`rows_from_new`).
        verbose (bool): print every append.

    Examples:

        >>> strategy = PolarStrategy(hooks, inner=DefaultStrategy(), render_fn=make_render_fn(params))
        >>> strategy.check_sanity(params, optimizers)
        >>> state = strategy.initialize_state(scene_scale=1.0)
        >>> # per step: see the module docstring
    """

    hooks: Optional[TrainingHooks] = None
    inner: Strategy = field(default_factory=DefaultStrategy)
    render_fn: Optional[RenderFn] = None
    cap_max: Optional[int] = None
    extra_rows: Dict[str, RowFn] = field(default_factory=dict)
    verbose: bool = False

    # ---------------------------------------------------------------------------- interface
    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        """The inner strategy's state (``scene_scale`` passed on when it takes one) plus
        ``state["polar"]``: counters ``calls`` (densify calls that returned Gaussians),
        ``appended``, ``dropped_cap`` and ``last_step`` (gsplat step of the last append, -1)."""
        init = self.inner.initialize_state
        if "scene_scale" in inspect.signature(init).parameters:
            state = init(scene_scale=scene_scale)
        else:
            state = init()
        if "polar" in state:
            raise ValueError("the inner strategy's state already has a 'polar' entry")
        state["polar"] = {"calls": 0, "appended": 0, "dropped_cap": 0, "last_step": -1}
        return state

    def check_sanity(self, params: Params, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """The inner strategy's checks, plus: ``hooks`` set, a colour parameter (``sh0`` or
        ``colors``), and, with Dense on, preprocessed hooks.

        Raises:
            AssertionError: as gsplat's own ``check_sanity``.
        """
        self.inner.check_sanity(params, optimizers)
        assert self.hooks is not None, "PolarStrategy.hooks is required (a PolarHooks)"
        assert "sh0" in params or "colors" in params or "sh0" in self.extra_rows, (
            "PolarStrategy appends colours as sh0 (or simple_trainer's logit 'colors'); neither is in params"
        )
        config = getattr(self.hooks, "config", None)
        if config is not None and config.densify.enabled:
            assert getattr(self.hooks, "maps", None), "call hooks.preprocess(views) before training"

    def step_pre_backward(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
    ) -> None:
        """The inner strategy's ``step_pre_backward`` (retains ``info["means2d"]``'s grad)."""
        self.inner.step_pre_backward(params, optimizers, state, step, info)

    def step_post_backward(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
        packed: bool = False,
        lr: Optional[float] = None,
        *,
        view: Optional[View] = None,
        render: Optional[RenderOut] = None,
        render_fn: Optional[Callable[[View], RenderOut]] = None,
    ) -> Optional[NewGaussians]:
        """The inner strategy's step, then Dense (call it after the optimizer steps).

        Args:
            params: the gsplat parameters, as for gsplat's strategies.
            optimizers: their optimizers, as for gsplat's strategies.
            state: this strategy's state (:meth:`initialize_state`).
            step: gsplat's 0-based step.
            info: gsplat's ``meta`` dict of the step's render.
            packed: passed to an inner strategy that takes it (DefaultStrategy).
            lr: the means' learning rate, passed to an inner strategy that takes it (MCMC,
                required there).
            view: the trained view (default ``info["polar_view"]``); without one, only the inner
                strategy runs.
            render: its render (default ``info["polar_render"]``; else Dense renders it).
            render_fn: renders other views (default ``info["polar_render_fn"]``, then the field).

        Returns:
            The appended Gaussians (after the cap), or None.
        """
        inner_kwargs: Dict[str, Any] = {}
        accepted = inspect.signature(self.inner.step_post_backward).parameters
        if "packed" in accepted:
            inner_kwargs["packed"] = packed
        if "lr" in accepted:
            if lr is None:
                raise ValueError(f"{type(self.inner).__name__}.step_post_backward needs lr (the means' learning rate)")
            inner_kwargs["lr"] = lr
        self.inner.step_post_backward(params, optimizers, state, step, info, **inner_kwargs)

        view = view if view is not None else info.get("polar_view")
        if view is None or self.hooks is None or not self.hooks.densify_due(step + 1):
            return None
        render = render if render is not None else info.get("polar_render")
        render_fn = render_fn or info.get("polar_render_fn") or self.render_fn or _missing_render_fn
        with torch.no_grad():
            new = self.hooks.densify(step + 1, view, render_fn, gaussian_state(params), render=render)
            if new is None or len(new) == 0:
                return None
            return self._append(params, optimizers, state, step, new)

    # ------------------------------------------------------------------------------- append
    def _cap(self) -> Optional[int]:
        if self.cap_max is not None:
            return int(self.cap_max)
        cap = getattr(self.inner, "cap_max", None)
        return None if cap is None else int(cap)

    @torch.no_grad()
    def _append(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        new: NewGaussians,
    ) -> Optional[NewGaussians]:
        polar = state.setdefault("polar", {"calls": 0, "appended": 0, "dropped_cap": 0, "last_step": -1})
        polar["calls"] += 1
        n = len(params["means"])
        cap = self._cap()
        if cap is not None:
            room = max(0, cap - n)
            if room < len(new):
                polar["dropped_cap"] += len(new) - room
                if room == 0:
                    return None
                keep = torch.linspace(0, len(new) - 1, room, device=new.means.device).round().long()
                new = _index_new(new, keep)
        rows = rows_from_new(new, params, self.extra_rows)

        # Per-Gaussian statistics of the strategy state, padded by append_rows (never the
        # NOT_PER_GAUSSIAN entries, whatever their shape).
        row_state: MutableMapping[str, Any] = {
            key: value for key, value in state.items()
            if key not in NOT_PER_GAUSSIAN and isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == n
        }
        # gsplat allows frozen parameters without an optimizer: those are concatenated here.
        trainable = {name: p for name, p in params.items() if name in optimizers}
        frozen = [name for name in params.keys() if name not in optimizers]
        append_rows(trainable, optimizers, {name: rows[name] for name in trainable}, state=row_state)
        for name, value in trainable.items():
            params[name] = value
        for name in frozen:
            old = params[name]
            params[name] = nn.Parameter(torch.cat([old.detach(), rows[name]], dim=0), requires_grad=False)
        state.update(row_state)

        polar["appended"] += len(new)
        polar["last_step"] = step
        if self.verbose:
            print(f"Step {step}: PolarGS appended {len(new)} GSs. Now having {len(params['means'])} GSs.")
        return new
