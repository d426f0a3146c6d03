"""What a dry run watches inside gsplat's ``examples/simple_trainer.py`` (1.5.x and main).

:class:`GsplatProbe` wraps, in the trainer's process only:

- ``Tensor.backward`` (:class:`~polargs_plugin.dryrun.probe.RunProbe`): iterations, losses, step
  times, and the per-Gaussian state checked before every backward pass;
- the strategies' ``step_pre_backward`` (gsplat's ``Strategy`` and ``DefaultStrategy``): the
  trainer's parameters, optimizers and strategy state, the first time they are passed;
  ``step_post_backward`` (``DefaultStrategy``, ``MCMCStrategy``): gsplat main's ``scene``;
- the ops the strategies call (``duplicate``, ``split``, ``remove`` of DefaultStrategy,
  ``relocate``, ``sample_add`` of MCMCStrategy, in the strategy modules' namespaces): when the
  trainer's own densification ran, and which rows came from Dense through each of them;
- ``PolarHooks.densify`` (every Dense call) and the PolarGS strategies' ``_append`` (the rows
  Dense appended); ``SimpleTrainerPolar.__init__`` (the adapter was attached).

Per-Gaussian state: every parameter has one row per Gaussian; every optimizer holds its
parameter (the same tensor) with Adam moments of its shape and no state of a replaced parameter;
every tensor of the strategy state but ``binoms`` and ``scene_scale`` has one row per Gaussian;
gsplat main's scene has one ``component_index`` per Gaussian.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
from torch import Tensor

from polargs_plugin.dryrun.probe import RunProbe

__all__ = ["GsplatProbe", "gsplat_state_problems", "named_arguments", "NOT_PER_GAUSSIAN_STATE"]

NOT_PER_GAUSSIAN_STATE = ("binoms", "scene_scale")
"""Strategy-state entries that never hold one row per Gaussian (MCMC's binomial table)."""

_OPS = {
    "gsplat.strategy.default": ("duplicate", "split", "remove"),
    "gsplat.strategy.mcmc": ("relocate", "sample_add"),
}


def named_arguments(signature: inspect.Signature, args: tuple, kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """The arguments of a call by parameter name, those caught by a ``**kwargs`` parameter included
    (gsplat's base ``Strategy.step_pre_backward(*args, **kwargs)``, which MCMCStrategy inherits,
    receives ``params=``, ``optimizers=``, ``state=`` that way)."""
    bound = signature.bind(*args, **kwargs).arguments
    for parameter in signature.parameters.values():
        if parameter.kind is inspect.Parameter.VAR_KEYWORD:
            bound.update(bound.pop(parameter.name, {}))
    return dict(bound)


def gsplat_state_problems(params: Mapping[str, Tensor], optimizers: Mapping[str, Any], state: Mapping[str, Any],
                          scene: Any = None) -> list[str]:
    """Why simple_trainer's per-Gaussian state is out of step (empty when it is not)."""
    n = int(params["means"].shape[0])
    problems = [f"parameter {name} has {p.shape[0]} rows for {n} Gaussians" for name, p in params.items() if p.shape[0] != n]
    for name, optimizer in optimizers.items():
        held = [p for group in optimizer.param_groups for p in group["params"]]
        if name in params and not any(p is params[name] for p in held):
            problems.append(f"optimizer {name} does not hold the parameter {name} the trainer renders")
        for p in held:
            for key in ("exp_avg", "exp_avg_sq"):
                moment = optimizer.state.get(p, {}).get(key)
                if moment is not None and moment.shape != p.shape:
                    problems.append(f"optimizer {key} of {name} is {tuple(moment.shape)}, the parameter {tuple(p.shape)}")
        stale = [key for key in optimizer.state if not any(key is p for p in held)]
        if stale:
            problems.append(f"optimizer {name}: {len(stale)} state(s) of parameters no longer in it")
    for key, value in state.items():
        if key in NOT_PER_GAUSSIAN_STATE or not isinstance(value, Tensor) or value.dim() == 0:
            continue
        if value.shape[0] != n:
            problems.append(f"strategy state {key} has {value.shape[0]} rows for {n} Gaussians")
    index = getattr(scene, "component_index", None)
    if isinstance(index, Tensor) and index.shape[0] != n:
        problems.append(f"scene component_index has {index.shape[0]} rows for {n} Gaussians")
    return problems


class GsplatProbe(RunProbe):
    """The probe of gsplat's simple_trainer.py (module docstring)."""

    def __init__(self, model_path: Path | None) -> None:
        super().__init__(model_path)
        self.params: Any = None
        self.optimizers: Mapping[str, Any] = {}
        self.state: Mapping[str, Any] = {}
        self.scene: Any = None
        self.attached = False

    def install(self) -> None:
        """Wrap ``Tensor.backward``, gsplat's strategies and ops, the PolarGS hooks and adapter."""
        import importlib

        from gsplat.strategy import DefaultStrategy, MCMCStrategy
        from gsplat.strategy.base import Strategy

        from polargs_adapters.gsplat.strategy import PolarDense
        from polargs_adapters.gsplat.trainer import SimpleTrainerPolar
        from polargs_plugin.hooks import PolarHooks

        super().install()
        for owner in (Strategy, DefaultStrategy):
            self._wrap(owner, "step_pre_backward", self._step_pre_backward)
        for owner in (DefaultStrategy, MCMCStrategy):
            self._wrap(owner, "step_post_backward", self._step_post_backward)
        for module_name, names in _OPS.items():
            module = importlib.import_module(module_name)
            for name in names:
                self._wrap(module, name, self._op(name))
        self._wrap(PolarHooks, "densify", self._densify)
        self._wrap(PolarDense, "_append", self._append)
        self._wrap(SimpleTrainerPolar, "__init__", self._attach)

    def _started(self) -> bool:
        return self.params is not None

    def _num_gaussians(self) -> int | None:
        return None if self.params is None else int(self.params["means"].shape[0])

    def _state_problems(self) -> list[str]:
        return gsplat_state_problems(self.params, self.optimizers, self.state, self.scene)

    def _patched(self) -> bool:
        return self.attached

    # ------------------------------------------------------------------- wrappers
    def _step_pre_backward(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self
        signature = inspect.signature(original)

        def step_pre_backward(strategy: Any, *args: Any, **kwargs: Any) -> Any:
            if probe.params is None:
                bound = named_arguments(signature, (strategy, *args), kwargs)
                probe.params, probe.optimizers, probe.state = bound["params"], bound["optimizers"], bound["state"]
                probe._start_rows(int(probe.params["means"].shape[0]))
            return original(strategy, *args, **kwargs)

        return step_pre_backward

    def _step_post_backward(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def step_post_backward(strategy: Any, *args: Any, **kwargs: Any) -> Any:
            if kwargs.get("scene") is not None:
                probe.scene = kwargs["scene"]
            return original(strategy, *args, **kwargs)

        return step_post_backward

    def _op(self, name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        probe = self

        def make(original: Callable[..., Any]) -> Callable[..., Any]:
            signature = inspect.signature(original)

            def op(*args: Any, **kwargs: Any) -> Any:
                bound = named_arguments(signature, args, kwargs)
                rows = probe.dense_rows
                result = original(*args, **kwargs)
                if bound["params"] is probe.params:
                    if not probe.native_densify or probe.native_densify[-1] != probe.iteration:
                        probe.native_densify.append(probe.iteration)
                    if rows is not None:
                        probe._rows_changed(_rows_after(name, rows, bound), name)
                return result

            return op

        return make

    def _densify(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def densify(hooks: Any, *args: Any, **kwargs: Any) -> Any:
            new = original(hooks, *args, **kwargs)
            probe.dense_rounds.append((probe.iteration, 0))
            return new

        return densify

    def _append(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def _append(strategy: Any, params: Any, *args: Any, **kwargs: Any) -> Any:
            before = int(params["means"].shape[0])
            result = original(strategy, params, *args, **kwargs)
            added = int(params["means"].shape[0]) - before
            if params is probe.params:
                if probe.dense_rounds:
                    probe.dense_rounds[-1] = (probe.iteration, added)
                if probe.dense_rows is not None:
                    probe._rows_changed(torch.cat([probe.dense_rows, torch.ones(added, dtype=torch.bool)]), "Dense")
                probe._check(f"after Dense at iteration {probe.iteration}")
            return result

        return _append

    def _attach(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def __init__(adapter: Any, *args: Any, **kwargs: Any) -> None:
            original(adapter, *args, **kwargs)
            probe.attached = True

        return __init__

    # ------------------------------------------------------------------- checkpoint
    def checkpoint(self) -> dict:
        """The newest ``ckpts/ckpt_*.pt`` of the result folder, loaded without unpickling code, its
        splats restored into a new ParameterDict as simple_trainer's ``--ckpt`` does."""
        if self.model_path is None or self.params is None:
            return {"ok": False, "detail": "no result folder or no parameters"}
        found = sorted((self.model_path / "ckpts").glob("ckpt_*.pt"), key=lambda p: p.stat().st_mtime)
        if not found:
            return {"ok": False, "detail": f"no ckpts/ckpt_*.pt in {self.model_path}"}
        path = found[-1]
        try:
            data = torch.load(path, weights_only=True, map_location="cpu")
            splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in data["splats"].items()})
        except Exception as err:  # the report says what failed; the run itself is over
            return {"ok": False, "detail": f"{path.name}: {type(err).__name__}: {err}"}
        problems = []
        if set(splats.keys()) != set(self.params.keys()):
            problems.append(f"parameters {sorted(splats.keys())}, the trainer's {sorted(self.params.keys())}")
        problems += gsplat_state_problems(splats, {}, {})
        problems += [f"{k} is not finite" for k, v in splats.items() if not torch.isfinite(v).all()]
        detail = f"{path.name} (step {data.get('step')}) restored into a new ParameterDict: {len(splats['means'])} Gaussians"
        return {"ok": not problems, "detail": detail + ("; " + "; ".join(problems) if problems else "")}


def _rows_after(name: str, rows: Tensor, bound: Mapping[str, Any]) -> Tensor:
    """Dense's flags after gsplat's op ``name``: duplicates and split halves are appended (not
    Dense's), removed rows dropped, relocated rows replaced (no longer Dense's), sampled rows added."""
    if name == "sample_add":
        return torch.cat([rows, torch.zeros(int(bound["n"]), dtype=torch.bool)])
    mask = bound["mask"].detach().cpu().bool().reshape(-1)
    count = int(mask.sum())
    if name == "duplicate":
        return torch.cat([rows, torch.zeros(count, dtype=torch.bool)])
    if name == "split":
        return torch.cat([rows[~mask], torch.zeros(2 * count, dtype=torch.bool)])
    if name == "remove":
        return rows[~mask]
    relocated = rows.clone()
    relocated[mask] = False
    return relocated
