"""gsplat strategies with PolarGS densification (module Dense).

- :class:`PolarDefaultStrategy` and :class:`PolarMCMCStrategy`: subclasses of gsplat's
  ``DefaultStrategy`` and ``MCMCStrategy`` (same fields, plus ``hooks``, ``render_fn``,
  ``extra_rows``; ``cap_max`` for both). They pass gsplat's ``isinstance`` dispatch, so they drop
  into ``examples/simple_trainer.py`` (:func:`polar_strategy` converts its configured strategy;
  ``adapters/gsplat/patch.py`` does that for a checkout).
- :class:`PolarStrategy`: the same Dense step composed around any inner strategy.

All three run on gsplat 1.5.x and on gsplat main (1.6): ``step_post_backward`` takes ``scene=``,
passes it to the gsplat step when that step takes it (main), and keeps the scene's per-Gaussian
state in step with Dense's appends: gsplat's scenes have no append hook, so each appended row is
announced as a duplicate of its nearest existing Gaussian (``scene.on_duplicate(parents)``, the
hook gsplat's own ``duplicate`` calls), which gives it that Gaussian's component and side data.

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

import dataclasses
import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Mapping, MutableMapping, Optional, Union

import torch
from torch import Tensor, nn

try:
    from gsplat.strategy import DefaultStrategy, MCMCStrategy, Strategy
except ImportError as error:  # pragma: no cover - exercised only without gsplat
    raise ImportError(
        "polargs_adapters.gsplat needs gsplat: pip install 'polargs_plugin[gsplat]'"
    ) from error

from polargs_plugin.kit import append_rows, logit, raw_from_new
from polargs_plugin.types import NewGaussians, RenderFn, RenderOut, TrainingHooks, View

from .render import RAW_FROM_GSPLAT, gaussian_state

__all__ = [
    "PolarStrategy",
    "PolarDefaultStrategy",
    "PolarMCMCStrategy",
    "polar_strategy",
    "rows_from_new",
    "nearest_rows",
    "NOT_PER_GAUSSIAN",
]

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


def nearest_rows(points: Tensor, queries: Tensor, max_pairs: int = 1 << 24) -> Tensor:
    """Index of the nearest row of ``points`` (N, 3) for each row of ``queries`` (M, 3).

    Distances are computed in chunks of at most ``max_pairs`` query-point pairs (64 MiB of
    float32), so a million Gaussians do not need an M x N matrix."""
    if len(points) == 0:
        raise ValueError("nearest_rows: no points to choose from")
    rows = max(1, max_pairs // len(points))
    return torch.cat(
        [torch.cdist(queries[i : i + rows], points).argmin(dim=1) for i in range(0, len(queries), rows)]
    )


def _missing_render_fn(view: View) -> RenderOut:
    raise ValueError(
        "Dense needs renders of source views; set the strategy's render_fn "
        "(e.g. make_render_fn(params, rasterization)) or pass render_fn= / info['polar_render_fn']"
    )


def _index_new(new: NewGaussians, index: Tensor) -> NewGaussians:
    return NewGaussians(
        means=new.means[index], quats=new.quats[index], scales=new.scales[index],
        colors=new.colors[index], opacities=new.opacities[index],
    )


def _step_kwargs(step_fn: Callable[..., Any], **candidates: Any) -> Dict[str, Any]:
    """The keyword arguments of ``candidates`` that a gsplat ``step_post_backward`` takes.

    ``packed`` (DefaultStrategy), ``lr`` (MCMCStrategy, required there) and ``scene`` (gsplat
    main) are passed when the function names them. A ``scene`` given to a gsplat without scenes
    (1.5.x), or a missing ``lr``, is an error rather than dropped silently.
    """
    accepted = inspect.signature(step_fn).parameters
    owner = getattr(step_fn, "__qualname__", "step_post_backward")
    if "lr" in accepted and candidates.get("lr") is None:
        raise ValueError(f"{owner} needs lr (the means' learning rate)")
    if candidates.get("scene") is not None and "scene" not in accepted:
        raise TypeError(f"{owner} takes no scene= (a gsplat before 1.6): the scene cannot be kept in step")
    return {key: value for key, value in candidates.items() if key in accepted and value is not None}


class PolarDense:
    """What the PolarGS strategies share: Dense after gsplat's step, and the append.

    The dataclasses using it declare ``hooks``, ``render_fn``, ``extra_rows`` and ``verbose``;
    the cap is :meth:`_polar_cap`. Pickling (and ``yaml.dump`` of a trainer's config, as
    simple_trainer.py does) leaves out ``hooks`` and ``render_fn``: they are the run's data and
    live objects, not settings; a loaded strategy gets them again from ``attach``.
    """

    hooks: Optional[TrainingHooks]
    render_fn: Optional[RenderFn]
    extra_rows: Dict[str, RowFn]
    verbose: bool

    def __getstate__(self) -> Dict[str, Any]:
        state = dict(self.__dict__)
        state["hooks"] = None
        state["render_fn"] = None
        return state

    def _polar_cap(self) -> Optional[int]:
        cap = getattr(self, "cap_max", None)
        return None if cap is None else int(cap)

    @staticmethod
    def _with_polar_state(state: Dict[str, Any]) -> Dict[str, Any]:
        if "polar" in state:
            raise ValueError("the gsplat strategy's state already has a 'polar' entry")
        state["polar"] = {"calls": 0, "appended": 0, "dropped_cap": 0, "last_step": -1}
        return state

    def check_sanity(self, params: Params, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """gsplat's checks of the strategy this is mixed into, plus the PolarGS ones: ``hooks``
        set, a colour parameter (``sh0`` or ``colors``), and, with Dense on, preprocessed hooks.

        Raises:
            AssertionError: as gsplat's own ``check_sanity``.
        """
        super().check_sanity(params, optimizers)  # type: ignore[misc]
        self._check_polar(params)

    def _check_polar(self, params: Params) -> None:
        assert self.hooks is not None, f"{type(self).__name__}.hooks is required (a PolarHooks)"
        assert "sh0" in params or "colors" in params or "sh0" in self.extra_rows, (
            "PolarGS appends colours as sh0 (or simple_trainer's logit 'colors'); neither is in params"
        )
        config = getattr(self.hooks, "config", None)
        if config is not None and config.densify.enabled:
            assert getattr(self.hooks, "maps", None), "call hooks.preprocess(views) before training"

    def _dense(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
        scene: Any = None,
        view: Optional[View] = None,
        render: Optional[RenderOut] = None,
        render_fn: Optional[Callable[[View], RenderOut]] = None,
    ) -> Optional[NewGaussians]:
        """Dense for gsplat step ``step`` (hook iteration ``step + 1``), after gsplat's own step."""
        view = view if view is not None else info.get("polar_view")
        if view is None or self.hooks is None or not self.hooks.densify_due(step + 1):
            return None
        render = render if render is not None else info.get("polar_render")
        render_fn = render_fn or info.get("polar_render_fn") or self.render_fn or _missing_render_fn
        with torch.no_grad():
            new = self.hooks.densify(step + 1, view, render_fn, gaussian_state(params), render=render)
            if new is None or len(new) == 0:
                return None
            return self._append(params, optimizers, state, step, new, scene)

    @torch.no_grad()
    def _append(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        new: NewGaussians,
        scene: Any = None,
    ) -> Optional[NewGaussians]:
        polar = state.setdefault("polar", {"calls": 0, "appended": 0, "dropped_cap": 0, "last_step": -1})
        polar["calls"] += 1
        n = len(params["means"])
        cap = self._polar_cap()
        if cap is not None:
            room = max(0, cap - n)
            if room < len(new):
                polar["dropped_cap"] += len(new) - room
                if room == 0:
                    return None
                keep = torch.linspace(0, len(new) - 1, room, device=new.means.device).round().long()
                new = _index_new(new, keep)
        rows = rows_from_new(new, params, self.extra_rows)
        parents = nearest_rows(params["means"].detach(), rows["means"]) if scene is not None else None

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
        if parents is not None:
            scene.on_duplicate(parents)

        polar["appended"] += len(new)
        polar["last_step"] = step
        if self.verbose:
            print(f"Step {step}: PolarGS appended {len(new)} GSs. Now having {len(params['means'])} GSs.")
        return new


@dataclass
class PolarStrategy(PolarDense, Strategy):
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

    ``simple_trainer.py`` accepts only subclasses of ``DefaultStrategy`` / ``MCMCStrategy``: use
    :class:`PolarDefaultStrategy` / :class:`PolarMCMCStrategy` there.

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
        return self._with_polar_state(state)

    def check_sanity(self, params: Params, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """The inner strategy's checks, plus: ``hooks`` set, a colour parameter (``sh0`` or
        ``colors``), and, with Dense on, preprocessed hooks.

        Raises:
            AssertionError: as gsplat's own ``check_sanity``.
        """
        self.inner.check_sanity(params, optimizers)
        self._check_polar(params)

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
        scene: Any = None,
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
            scene: gsplat main's ``Scene``: passed to the inner step, and told about the
                appended rows (``on_duplicate`` of each row's nearest existing Gaussian).
            view: the trained view (default ``info["polar_view"]``); without one, only the inner
                strategy runs.
            render: its render (default ``info["polar_render"]``; else Dense renders it).
            render_fn: renders other views (default ``info["polar_render_fn"]``, then the field).

        Returns:
            The appended Gaussians (after the cap), or None.
        """
        step_fn = self.inner.step_post_backward
        kwargs = _step_kwargs(step_fn, packed=packed, lr=lr, scene=scene)
        step_fn(params, optimizers, state, step, info, **kwargs)
        return self._dense(params, optimizers, state, step, info, scene, view, render, render_fn)

    def _polar_cap(self) -> Optional[int]:
        cap = self.cap_max if self.cap_max is not None else getattr(self.inner, "cap_max", None)
        return None if cap is None else int(cap)


@dataclass
class PolarDefaultStrategy(PolarDense, DefaultStrategy):
    """gsplat's ``DefaultStrategy`` (every field and step unchanged) followed by PolarGS's Dense.

    A subclass, so ``simple_trainer.py``'s ``isinstance(strategy, DefaultStrategy)`` dispatch
    takes it. Its fields are DefaultStrategy's and these:

    Args:
        hooks (TrainingHooks): the PolarGS hooks (a ``PolarHooks``), already ``preprocess``-ed
            with the training views. Required; a default of None keeps gsplat's all-keyword style.
        render_fn (callable): ``render_fn(view) -> RenderOut`` with the current Gaussians, for the
            PatchMatch source views (:func:`make_render_fn`); or ``info["polar_render_fn"]`` /
            the ``render_fn=`` argument of ``step_post_backward``.
        extra_rows (dict): ``name -> fn(new, param) -> rows`` for extra per-Gaussian parameters
            (:func:`rows_from_new`).
        cap_max (int): no Polar append beyond this many Gaussians (default None: unlimited;
            an evenly spaced subset of the new rows is kept when they do not fit).
    """

    hooks: Optional[TrainingHooks] = None
    render_fn: Optional[RenderFn] = None
    extra_rows: Dict[str, RowFn] = field(default_factory=dict)
    cap_max: Optional[int] = None

    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        """DefaultStrategy's state plus ``state["polar"]`` (counters, as :class:`PolarStrategy`)."""
        return self._with_polar_state(super().initialize_state(scene_scale=scene_scale))

    def step_post_backward(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
        packed: bool = False,
        scene: Any = None,
        *,
        view: Optional[View] = None,
        render: Optional[RenderOut] = None,
        render_fn: Optional[Callable[[View], RenderOut]] = None,
    ) -> Optional[NewGaussians]:
        """DefaultStrategy's step (``scene`` passed on with gsplat main), then Dense; the
        arguments are :meth:`PolarStrategy.step_post_backward`'s."""
        step_fn = super().step_post_backward
        step_fn(params, optimizers, state, step, info, **_step_kwargs(step_fn, packed=packed, scene=scene))
        return self._dense(params, optimizers, state, step, info, scene, view, render, render_fn)


@dataclass
class PolarMCMCStrategy(PolarDense, MCMCStrategy):
    """gsplat's ``MCMCStrategy`` (every field and step unchanged) followed by PolarGS's Dense.

    A subclass, so ``simple_trainer.py``'s ``isinstance(strategy, MCMCStrategy)`` dispatch takes
    it. Dense's appends count against MCMC's ``cap_max`` (an evenly spaced subset of the new rows
    is kept when they do not fit). Its fields are MCMCStrategy's and these:

    Args:
        hooks (TrainingHooks): the PolarGS hooks (a ``PolarHooks``), already ``preprocess``-ed
            with the training views. Required; a default of None keeps gsplat's all-keyword style.
        render_fn (callable): ``render_fn(view) -> RenderOut`` with the current Gaussians, for the
            PatchMatch source views (:func:`make_render_fn`); or ``info["polar_render_fn"]`` /
            the ``render_fn=`` argument of ``step_post_backward``.
        extra_rows (dict): ``name -> fn(new, param) -> rows`` for extra per-Gaussian parameters
            (:func:`rows_from_new`).
    """

    hooks: Optional[TrainingHooks] = None
    render_fn: Optional[RenderFn] = None
    extra_rows: Dict[str, RowFn] = field(default_factory=dict)

    def initialize_state(self) -> Dict[str, Any]:
        """MCMCStrategy's state plus ``state["polar"]`` (counters, as :class:`PolarStrategy`)."""
        return self._with_polar_state(super().initialize_state())

    def step_post_backward(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
        lr: Optional[float] = None,
        scene: Any = None,
        *,
        view: Optional[View] = None,
        render: Optional[RenderOut] = None,
        render_fn: Optional[Callable[[View], RenderOut]] = None,
    ) -> Optional[NewGaussians]:
        """MCMCStrategy's step (``lr`` required; ``scene`` passed on with gsplat main), then
        Dense; the arguments are :meth:`PolarStrategy.step_post_backward`'s."""
        step_fn = super().step_post_backward
        step_fn(params, optimizers, state, step, info, **_step_kwargs(step_fn, lr=lr, scene=scene))
        return self._dense(params, optimizers, state, step, info, scene, view, render, render_fn)


_POLAR_OF = {DefaultStrategy: PolarDefaultStrategy, MCMCStrategy: PolarMCMCStrategy}


def polar_strategy(strategy: Strategy, **polar_fields: Any) -> Union[PolarDefaultStrategy, PolarMCMCStrategy]:
    """The PolarGS subclass of a gsplat ``DefaultStrategy`` / ``MCMCStrategy``, same settings.

    Args:
        strategy: gsplat's strategy as configured (e.g. ``cfg.strategy`` of simple_trainer.py);
            a PolarGS one is returned as it is (with ``polar_fields`` set).
        **polar_fields: ``hooks``, ``render_fn``, ``extra_rows``, (Default) ``cap_max``.

    Raises:
        TypeError: a strategy of another class (its own subclass of gsplat's included: its
            overrides would be lost).
    """
    if isinstance(strategy, (PolarDefaultStrategy, PolarMCMCStrategy)):
        for name, value in polar_fields.items():
            setattr(strategy, name, value)
        return strategy
    polar_class = _POLAR_OF.get(type(strategy))
    if polar_class is None:
        raise TypeError(
            f"polar_strategy: {type(strategy).__name__} is neither gsplat's DefaultStrategy nor its MCMCStrategy"
        )
    settings = {f.name: getattr(strategy, f.name) for f in dataclasses.fields(strategy) if f.init}
    return polar_class(**settings, **polar_fields)
