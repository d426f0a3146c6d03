"""What a dry run watches inside a graphdeco-family trainer (graphdeco, GOF, PGSR, 2DGS).

:class:`RunProbe` is what every probe records and reports (gsplat's is
:class:`polargs_plugin.dryrun.probe_gsplat.GsplatProbe`); :class:`Probe` wraps, in the trainer's process only, a few methods at class level:

- ``Tensor.backward``: one call per training iteration; it counts iterations, records the loss
  value and the time between iterations, and checks the model's per-Gaussian state first (so the
  state is checked after every densification and optimizer step of the previous iteration);
- the checkout's ``GaussianModel``: ``__init__`` and ``training_setup`` (the model and its
  arguments, for the reload check), ``densification_postfix`` and ``prune_points`` (which rows
  came from Dense, through every clone, split and prune), ``densify_and_prune`` (when the trainer's
  own densification ran);
- ``InriaAdapter.append`` (``polargs_plugin.kit.inria``, every Inria-family adapter): which
  ``densification_postfix`` calls append Dense's rows.

Per-Gaussian state: every attribute of :data:`PER_GAUSSIAN` (and each adapter's ``statistics``)
the model holds must have one row per Gaussian, every optimizer group of :data:`GAUSSIAN_GROUPS`
one row per Gaussian with Adam moments of its shape, and no optimizer state may be left over
from a replaced parameter.
"""

from __future__ import annotations

import functools
import importlib
import math
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

__all__ = ["PER_GAUSSIAN", "GAUSSIAN_GROUPS", "RunProbe", "Probe", "state_problems", "load_checkpoint", "import_model_class", "describe_error"]

PER_GAUSSIAN = (
    "_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity", "_knn_f",
    "xyz_gradient_accum", "xyz_gradient_accum_abs", "xyz_gradient_accum_abs_max", "denom", "denom_abs",
    "max_radii2D", "max_weight", "filter_3D", "tmp_radii",
)
"""Model attributes of the graphdeco family that hold one row per Gaussian when present."""

GAUSSIAN_GROUPS = ("xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation", "knn_f")
"""Names of the optimizer groups that hold per-Gaussian parameters."""

MAX_PROBLEMS = 20


def state_problems(model: Any, names: tuple[str, ...] = PER_GAUSSIAN, optimizer_state: bool = True) -> list[str]:
    """Why the model's per-Gaussian state is out of step (empty when it is not)."""
    n = int(model._xyz.shape[0])
    problems = []
    for name in names:
        value = getattr(model, name, None)
        if isinstance(value, Tensor) and value.dim() >= 1 and value.numel() > 0 and value.shape[0] != n:
            problems.append(f"{name} has {value.shape[0]} rows for {n} Gaussians")
    optimizer = getattr(model, "optimizer", None)
    if optimizer is None or not optimizer_state:
        return problems
    params = set()
    for group in optimizer.param_groups:
        params.update(id(p) for p in group["params"])
        if group.get("name") not in GAUSSIAN_GROUPS:
            continue
        for p in group["params"]:
            if p.shape[0] != n:
                problems.append(f"optimizer group {group['name']} has {p.shape[0]} rows for {n} Gaussians")
            for key in ("exp_avg", "exp_avg_sq"):
                moment = optimizer.state.get(p, {}).get(key)
                if moment is not None and moment.shape != p.shape:
                    problems.append(f"optimizer {key} of {group['name']} is {tuple(moment.shape)}, "
                                    f"the parameter {tuple(p.shape)}")
    stale = [key for key in optimizer.state if id(key) not in params]
    if stale:
        problems.append(f"{len(stale)} optimizer state(s) belong to parameters no longer in the optimizer")
    return problems


def load_checkpoint(path: Path) -> Any:
    """An upstream checkpoint ``(model_args, iteration)``, without unpickling code: tensors,
    containers, numbers and the numpy scalars ``capture()`` may hold (the scene radius)."""
    import numpy as np

    allowed = [np.dtype, type(np.dtype("float64")), type(np.dtype("float32"))]
    scalar = getattr(getattr(np, "_core", np.core).multiarray, "scalar", None)
    if scalar is not None:
        allowed.append(scalar)
    with torch.serialization.safe_globals(allowed):
        return torch.load(path, weights_only=True, map_location="cpu")


class RunProbe:
    """What every dry-run probe records inside the trainer's process (losses, step times,
    per-Gaussian state problems, native densification, Dense's rows); :meth:`report` is the JSON.

    A subclass knows its trainer family: :meth:`install` wraps what it watches, :meth:`_started`
    says whether training has begun, :meth:`_num_gaussians` and :meth:`_state_problems` read its
    model, :meth:`_patched` whether the PolarGS adapter was attached.
    """

    def __init__(self, model_path: Path | None) -> None:
        self.model_path = model_path
        self.iteration = 0
        self.losses: list[float] = []
        self.times: list[float] = []
        self.problems: list[str] = []
        self.native_densify: list[int] = []
        self.dense_rounds: list[tuple[int, int]] = []
        self.dense_rows: Tensor | None = None
        self.rows_lost: str | None = None
        self.initial_gaussians: int | None = None
        self.error: str | None = None
        self._restores: list[tuple[Any, str, Any]] = []

    # ------------------------------------------------------------------ installing
    def _wrap(self, owner: Any, name: str, make: Callable[[Callable[..., Any]], Callable[..., Any]]) -> None:
        original = getattr(owner, name)
        self._restores.append((owner, name, original))
        # wraps: the wrapper keeps the original's name and signature (adapters inspect it, e.g.
        # whether densification_postfix takes graphdeco 2024's new_tmp_radii)
        setattr(owner, name, functools.wraps(original)(make(original)))

    def install(self) -> None:
        """Wrap what the probe watches (``Tensor.backward`` here; subclasses add their trainer's)."""
        self._wrap(torch.Tensor, "backward", self._backward)

    def uninstall(self) -> None:
        """Undo :meth:`install`."""
        while self._restores:
            owner, name, original = self._restores.pop()
            setattr(owner, name, original)

    # ------------------------------------------------------------------ per family
    def _started(self) -> bool:
        raise NotImplementedError

    def _num_gaussians(self) -> int | None:
        raise NotImplementedError

    def _state_problems(self) -> list[str]:
        raise NotImplementedError

    def _patched(self) -> bool:
        raise NotImplementedError

    def checkpoint(self) -> dict:
        """``{"ok": bool, "detail": str}`` of the trainer's newest checkpoint, reloaded."""
        raise NotImplementedError

    # ------------------------------------------------------------------- wrappers
    def _backward(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def backward(tensor: Tensor, *args: Any, **kwargs: Any) -> Any:
            if tensor.dim() == 0 and probe._started():
                probe._iteration_starts(float(tensor.detach()))
            return original(tensor, *args, **kwargs)

        return backward

    def _iteration_starts(self, loss: float) -> None:
        self.iteration += 1
        self.losses.append(loss)
        self.times.append(time.perf_counter())
        self._check(f"iteration {self.iteration}")

    def _start_rows(self, count: int) -> None:
        """Training starts with ``count`` Gaussians, none of them Dense's."""
        self.initial_gaussians = count
        self.dense_rows = torch.zeros(count, dtype=torch.bool)

    def _rows_changed(self, rows: Tensor, what: str) -> None:
        """Dense's rows after an operation on the Gaussians: ``rows`` (one flag per Gaussian), or
        lost track when their number differs from the model's."""
        if self.dense_rows is None:
            return
        if rows.shape[0] == self._num_gaussians():
            self.dense_rows = rows
        else:
            self._lose_rows(f"{what} at iteration {self.iteration}: {rows.shape[0]} rows for {self._num_gaussians()} Gaussians")

    def _lose_rows(self, why: str) -> None:
        self.rows_lost = why
        self.dense_rows = None

    # ------------------------------------------------------------------- checking
    def _check(self, when: str) -> None:
        if len(self.problems) >= MAX_PROBLEMS or not self._started():
            return
        self.problems.extend(f"{when}: {p}" for p in self._state_problems())

    def finish(self) -> None:
        """The checks after the run: the state once more."""
        self._check("at the end")

    def report(self) -> dict:
        """The JSON report of the run."""
        steps = [b - a for a, b in zip(self.times, self.times[1:])]
        return {
            "iterations": self.iteration,
            "error": self.error,
            "losses_finite": all(math.isfinite(x) for x in self.losses),
            "first_nonfinite": next((i + 1 for i, x in enumerate(self.losses) if not math.isfinite(x)), None),
            "loss_first": self.losses[0] if self.losses else None,
            "loss_last": self.losses[-1] if self.losses else None,
            "step_seconds": steps,
            "gaussians_initial": self.initial_gaussians,
            "gaussians_final": self._num_gaussians(),
            "native_densify": self.native_densify,
            "dense_rounds": self.dense_rounds,
            "dense_rows_final": None if self.dense_rows is None else int(self.dense_rows.sum()),
            "rows_lost": self.rows_lost,
            "problems": self.problems,
            "patched": self._patched(),
        }


class Probe(RunProbe):
    """The probe of the graphdeco family (module docstring)."""

    def __init__(self, model_path: Path | None) -> None:
        super().__init__(model_path)
        self.model: Any = None
        self.model_args: tuple[tuple, dict] = ((), {})
        self.training_args: Any = None
        self.adapters: list[Any] = []
        self.statistics: tuple[str, ...] = PER_GAUSSIAN
        self._in_dense = False

    def install(self, model_class: Any = None) -> None:
        """Wrap ``Tensor.backward``, the checkout's ``GaussianModel`` (``model_class``, default
        :func:`import_model_class`) and ``InriaAdapter``."""
        from polargs_plugin.kit.inria import InriaAdapter

        model_class = model_class or import_model_class()
        super().install()
        self._wrap(model_class, "__init__", self._model_init)
        self._wrap(model_class, "training_setup", self._training_setup)
        self._wrap(model_class, "densification_postfix", self._postfix)
        self._wrap(model_class, "prune_points", self._prune)
        self._wrap(model_class, "densify_and_prune", self._densify_and_prune)
        self._wrap(InriaAdapter, "__init__", self._adapter_init)
        self._wrap(InriaAdapter, "append", self._append)

    def _started(self) -> bool:
        return self.model is not None and getattr(self.model, "optimizer", None) is not None

    def _num_gaussians(self) -> int | None:
        return None if self.model is None else int(self.model._xyz.shape[0])

    def _state_problems(self) -> list[str]:
        return state_problems(self.model, self.statistics)

    def _patched(self) -> bool:
        return bool(self.adapters)

    # ------------------------------------------------------------------- wrappers
    def _model_init(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def __init__(model: Any, *args: Any, **kwargs: Any) -> None:
            original(model, *args, **kwargs)
            if probe.model is None:
                probe.model, probe.model_args = model, (args, kwargs)

        return __init__

    def _training_setup(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def training_setup(model: Any, training_args: Any, *args: Any, **kwargs: Any) -> Any:
            result = original(model, training_args, *args, **kwargs)
            if model is probe.model and probe.training_args is None:
                probe.training_args = training_args
                probe._start_rows(int(model._xyz.shape[0]))
            return result

        return training_setup

    def _postfix(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def densification_postfix(model: Any, *args: Any, **kwargs: Any) -> Any:
            before = int(model._xyz.shape[0])
            result = original(model, *args, **kwargs)
            if model is probe.model and probe.dense_rows is not None:
                added = int(model._xyz.shape[0]) - before
                probe.dense_rows = torch.cat([probe.dense_rows, torch.full((added,), probe._in_dense)])
            return result

        return densification_postfix

    def _prune(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def prune_points(model: Any, mask: Tensor, *args: Any, **kwargs: Any) -> Any:
            result = original(model, mask, *args, **kwargs)
            if model is probe.model and probe.dense_rows is not None:
                keep = ~mask.detach().cpu().bool().reshape(-1)
                if keep.shape[0] == probe.dense_rows.shape[0]:
                    probe._rows_changed(probe.dense_rows[keep], "prune_points")
                else:
                    probe._lose_rows(f"prune_points at iteration {probe.iteration}: mask of {keep.shape[0]} rows")
            return result

        return prune_points

    def _densify_and_prune(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def densify_and_prune(model: Any, *args: Any, **kwargs: Any) -> Any:
            result = original(model, *args, **kwargs)
            if model is probe.model:
                probe.native_densify.append(probe.iteration)
            return result

        return densify_and_prune

    def _adapter_init(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def __init__(adapter: Any, *args: Any, **kwargs: Any) -> None:
            original(adapter, *args, **kwargs)
            probe.adapters.append(adapter)
            probe.statistics = tuple(dict.fromkeys(PER_GAUSSIAN + tuple(adapter.statistics)))

        return __init__

    def _append(self, original: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def append(adapter: Any, new: Any) -> int:
            probe._in_dense = True
            try:
                appended = original(adapter, new)
            finally:
                probe._in_dense = False
            probe.dense_rounds.append((probe.iteration, int(appended)))
            probe._check(f"after Dense at iteration {probe.iteration}")
            return appended

        return append

    def checkpoint(self) -> dict:
        """The newest ``chkpnt*.pth`` of the model folder, loaded and restored into a new model."""
        if self.model_path is None or self.model is None:
            return {"ok": False, "detail": "no model folder or no model"}
        found = sorted(self.model_path.glob("chkpnt*.pth"), key=lambda p: p.stat().st_mtime)
        if not found:
            return {"ok": False, "detail": f"no chkpnt*.pth in {self.model_path}"}
        path = found[-1]
        try:
            model_args, iteration = load_checkpoint(path)
            fresh = type(self.model)(*self.model_args[0], **self.model_args[1])
            fresh.restore(model_args, self.training_args)
            problems = state_problems(fresh, ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity"))
        except Exception as err:  # the report says what failed; the run itself is over
            return {"ok": False, "detail": f"{path.name}: {type(err).__name__}: {err}"}
        n = int(fresh._xyz.shape[0])
        detail = f"{path.name} (iteration {iteration}) restored into a new model: {n} Gaussians"
        return {"ok": not problems, "detail": detail + ("; " + "; ".join(problems) if problems else "")}


def import_model_class(module: str = "scene.gaussian_model", name: str = "GaussianModel") -> Any:
    """The checkout's ``GaussianModel`` (its folder must be first on ``sys.path``)."""
    return getattr(importlib.import_module(module), name)


def describe_error(err: BaseException) -> str:
    """The last lines of a traceback: where the trainer failed and why."""
    lines = traceback.format_exception(type(err), err, err.__traceback__)
    return "".join(lines[-6:]).strip()
