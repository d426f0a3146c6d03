"""One grid cell of an ablation: a plain-data description and the one function that runs it.

:func:`run_cell` is the only thing an executor calls (the local process pool, a submitit / Slurm
job: docs/ablation.md, docs/cluster.md): it trains, meshes, evaluates and writes the run folder
``<out>/<name>/`` atomically (everything goes to ``<out>/.tmp-<name>-<pid>/``, renamed at the end),
so a run folder is complete or absent. A failure leaves no run folder but
``<out>/logs/<name>.log`` (the run's output and the traceback) and raises :class:`CellFailed`.

Resuming: training checkpoints periodically (``Cell.checkpoint_every``) into the stable folder
``<out>/.partial/<name>/`` (``checkpoint.pt`` + ``state.json``: the curves so far, the cell's
fingerprint). A run that is interrupted (killed, preempted, timed out, Ctrl-C) keeps that folder
and the next attempt resumes from it; the reference trainer's checkpoints resume bit-exactly, so
the run folder is the same as an uninterrupted run's (timings aside). A run that *fails* (an
exception) discards it: after a fix the cell starts over; a failed write (OSError: a full disk)
keeps it, as the checkpoint it holds is intact. The folder is removed once the run folder is
published.

Run folder contents::

    summary.json      TrainConfig, PolarConfig, git commit, seed, init, timings, figures
    metrics.json      `polargs eval` output (Chamfer, F-score, normal MAE)
    curves.csv        per iteration: loss, PSNR, Gaussians, Gaussians appended by Dense
    tsdf_mesh.ply     the TSDF mesh (+ tsdf_mesh.json, its settings)
    checkpoint.pt     the trained model (`polargs mesh` / `polargs eval` accept the folder)
    views.npz         two views rendered for the report (colour, normals, depth) with their GT
    mesh_error.npz    predicted mesh vertices and their signed distance to the GT mesh
    pc_maps.npz       the PC inputs of the two views (variants with PC only)
    run.log           everything the run printed
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, TextIO

from polargs_plugin.ablation.artifacts import EVAL_CULL_DILATION, write_curves, write_report_data
from polargs_plugin.ablation.scenes import SceneSpec, ensure_scene, gt_mesh_path
from polargs_plugin.ablation.variants import DEFAULT_FACTOR, VARIANTS, describe, variant_configs
from polargs_plugin.io import PolarInputError, json_safe, write_json
from polargs_plugin.service.runs import CHECKPOINT_NAME, MESH_NAME, METRICS_NAME, SUMMARY_NAME

__all__ = ["Cell", "CellFailed", "run_cell", "chamfer_figures", "VISIBILITY_CLASSES", "INITS", "RUN_FORMAT", "SUMMARY_NAME", "CURVES_NAME", "is_done",
           "partial_dir", "mark_interrupted", "PARTIAL_DIR", "RECORDED_DISTRIBUTIONS", "run_versions"]

RUN_FORMAT = "polargs-ablation-run-v1"
CURVES_NAME = "curves.csv"
INITS: tuple[str, ...] = ("hull", "sfm", "random")
#: SfM initialisation falls back to the visual hull below this many points.
MIN_SFM_POINTS = 100
#: ``<out>/.partial/<name>/``: the periodic training checkpoint of a run in progress.
PARTIAL_DIR = ".partial"
PARTIAL_STATE = "state.json"
PARTIAL_LOG = "attempts.log"

Progress = Callable[[str, int, int], None]  # (phase, done, total)


@dataclass(frozen=True)
class Cell:
    """One training run of a grid, as plain data (JSON round trip: :meth:`to_dict` / :meth:`from_dict`).

    Attributes:
        scene: the scene.
        variant: one of :data:`~polargs_plugin.ablation.variants.VARIANTS`.
        seed: training seed.
        out: the grid folder; the run folder is ``out/name``.
        init: initial points, ``hull`` (visual hull of the masks), ``sfm`` (triangulated SIFT
            matches with the known poses, hull when too few) or ``random`` (uniform in the
            cameras' look-at cube).
        preset: ``cpu`` or ``paper`` (variants.PRESETS).
        factor: vanilla schedule factor of the cpu preset (None: 1/6, 5000 iterations).
        train_overrides / polar_overrides: nested partial dicts applied to the configs last.
        mesh: `polargs mesh` settings (``preset``, ``voxel``, ``sdf_trunc``, ``depth_trunc``).
        eval: `polargs eval` settings (``num_samples``, ``cull``).
        threads: torch threads of the run.
        device: torch device (None: cuda if available, else cpu).
        checkpoint_every: iterations between the periodic training checkpoints in
            ``<out>/.partial/<name>/`` that an interrupted run resumes from (None: 10 per run;
            0: none, an interrupted run starts over). Not part of the run's identity.
        reader: options of the dataset reader for a dataset-folder scene, as ``polargs train``
            takes them (``fmt``, ``pattern``, ``bit_depth``, ``sfm``, ``check_pattern``; the
            fields of :class:`polargs_plugin.service.ReaderOptions` that differ from the defaults). Empty for a
            bundled scene. The run's ``summary.json`` records under ``reader`` the options that
            read the same views again (what `polargs mesh` / `polargs eval` use).
    """

    scene: SceneSpec
    variant: str
    seed: int
    out: str
    init: str = "hull"
    preset: str = "cpu"
    factor: float | None = None
    train_overrides: dict = field(default_factory=dict)
    polar_overrides: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)
    eval: dict = field(default_factory=dict)
    threads: int = 1
    device: str | None = None
    checkpoint_every: int | None = None
    reader: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant '{self.variant}' (known: {', '.join(VARIANTS)})")
        if self.init not in INITS:
            raise ValueError(f"unknown init '{self.init}' (known: {', '.join(INITS)})")

    @property
    def name(self) -> str:
        return f"{self.scene.name}__{self.variant}__{self.init}__s{self.seed}"

    @property
    def run_dir(self) -> Path:
        return Path(self.out) / self.name

    @property
    def log_path(self) -> Path:
        return Path(self.out) / "logs" / f"{self.name}.log"

    @property
    def partial_dir(self) -> Path:
        return partial_dir(self)

    def fingerprint(self) -> dict[str, Any]:
        """What makes the run's figures: the description less the grid folder, the thread count and
        the checkpoint cadence (a checkpoint is resumed only by a cell with the same fingerprint)."""
        data = self.to_dict()
        for key in ("out", "threads", "checkpoint_every"):
            data.pop(key, None)
        if not data.get("reader"):
            data.pop("reader", None)  # the fingerprint of cells from before reader options (their checkpoints resume)
        return data

    def configs(self):
        """``(TrainConfig, PolarConfig | None)`` of this cell (device and progress not yet set)."""
        return variant_configs(self.variant, self.preset, self.factor, self.seed, self.train_overrides, self.polar_overrides)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Cell":
        data = dict(data)
        data["scene"] = SceneSpec.from_dict(data["scene"])
        return cls(**data)


class CellFailed(RuntimeError):
    """A cell failed; ``log`` holds its output and traceback."""

    def __init__(self, name: str, log: str, message: str):
        super().__init__(name, log, message)
        self.name, self.log, self.message = name, log, message

    def __str__(self) -> str:
        return f"{self.name}: {self.message} (log: {self.log})"


def is_done(cell: Cell) -> bool:
    """Whether the cell's run folder exists (it is complete by construction)."""
    return (cell.run_dir / SUMMARY_NAME).is_file()


def partial_dir(cell: Cell) -> Path:
    """``<out>/.partial/<name>/``: where a run in progress keeps its periodic checkpoint."""
    return Path(cell.out) / PARTIAL_DIR / cell.name


_INTERRUPTED = False


def mark_interrupted(interrupted: bool = True) -> None:
    """Called by a job's preemption / timeout handler (submitit's ``checkpoint``) before it exits,
    or by a pool worker's signal handler: the ``SystemExit`` that follows, or whatever the
    interruption turns into (an import it breaks fails with ImportError), is an interruption (the
    partial checkpoint is kept and the exception passes through unchanged), not a failure.
    ``interrupted=False`` clears the mark (a pool worker before its next cell)."""
    global _INTERRUPTED
    _INTERRUPTED = interrupted


def _is_interruption(err: BaseException) -> bool:
    # after mark_interrupted, whatever ends the run comes from the scheduler's signal: the SystemExit
    # of a requeue, or submitit's UncompletedJobError when the job has timed out too often
    return isinstance(err, KeyboardInterrupt) or _INTERRUPTED


def read_summary(run_dir: str | os.PathLike) -> dict[str, Any]:
    return json.loads((Path(run_dir) / SUMMARY_NAME).read_text())


def run_cell(cell: Cell, progress: Progress | None = None) -> dict[str, Any]:
    """Run one cell (train, mesh, evaluate, report data) and write its run folder atomically.

    Returns the run's summary (read back when the run folder already exists: nothing is rerun).

    Raises:
        CellFailed: after writing ``<out>/logs/<name>.log``; no run folder is left.
    """
    partial = partial_dir(cell)
    if is_done(cell):
        shutil.rmtree(partial, ignore_errors=True)  # left by a run interrupted right after publishing
        return read_summary(cell.run_dir)
    out = Path(cell.out)
    tmp = out / f".tmp-{cell.name}-{os.getpid()}"
    report = progress or (lambda phase, done, total: None)
    log_file = None
    # Everything from the first write on is inside the try: a stop signalled while the temporary
    # folder is being set up still leaves the attempt's log and no .tmp folder.
    try:
        out.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        log_file = open(tmp / "run.log", "w", buffering=1)
        with contextlib.suppress(OSError):  # what the interrupted attempts printed
            log_file.write((partial / PARTIAL_LOG).read_text())
        with contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):
            print(f"cell {cell.name}\n{json.dumps(cell.to_dict(), indent=2)}", flush=True)
            print(f"started {_now()} on {platform.node()} (pid {os.getpid()}, "
                  f"CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')})", flush=True)
            summary = _run(cell, tmp, report)
        log_file.close()
        try:
            os.rename(tmp, cell.run_dir)
        except OSError:
            if not is_done(cell):  # not another process finishing the same cell first
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return read_summary(cell.run_dir)
        shutil.rmtree(partial, ignore_errors=True)
        with contextlib.suppress(OSError):
            partial.parent.rmdir()  # .partial/ once no run is in progress
        with contextlib.suppress(FileNotFoundError):
            cell.log_path.unlink()  # a failure log from an earlier attempt
        report("done", 1, 1)
        return summary
    except BaseException as err:
        if _is_interruption(err):
            # not a failure: keep the periodic checkpoint (and this attempt's output) for the next attempt
            _save_log(log_file, tmp, partial / PARTIAL_LOG,
                      f"\nINTERRUPTED ({type(err).__name__}) at {_now()}; the next attempt resumes "
                      "from the last periodic checkpoint\n", append=True)
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        message = _one_line(err)
        _save_log(log_file, tmp, cell.log_path, "\n" + traceback.format_exc() + f"\nFAILED: {message}\n",
                  append=False)
        shutil.rmtree(tmp, ignore_errors=True)
        if not isinstance(err, OSError):  # a failed write (a full disk) leaves an intact checkpoint to resume
            shutil.rmtree(partial, ignore_errors=True)  # a failed run starts over (after a fix)
        raise CellFailed(cell.name, str(cell.log_path), message) from None


def _save_log(log_file: TextIO | None, tmp: Path, dest: Path, last_words: str, *, append: bool) -> None:
    """End an attempt's log with ``last_words`` and move it to ``dest``. Without an opened log (the
    attempt stopped while setting up) the words go to ``dest`` directly, after what it holds when
    ``append``; no error from here hides the one being handled."""
    with contextlib.suppress(Exception):
        dest.parent.mkdir(parents=True, exist_ok=True)
        if log_file is None:
            with open(dest, "a" if append else "w") as direct:
                direct.write(last_words)
            return
        with contextlib.suppress(Exception):
            log_file.write(last_words)
        log_file.close()
        os.replace(tmp / "run.log", dest)


def _now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    text = text[0] if text else ""
    if isinstance(err, SystemExit):
        return text or f"exit status {err.code}"
    name = type(err).__name__
    return text if name in ("PolarInputError",) else f"{name}: {text}"


class _Clock:
    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.last = self.start
        self.times: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.times[name] = round(now - self.last, 3)
        self.last = now

    def total(self) -> dict[str, float]:
        return {**self.times, "total": round(time.perf_counter() - self.start, 3)}


def _run(cell: Cell, tmp: Path, report: Progress) -> dict[str, Any]:
    """Train, mesh, evaluate and write the report data of ``cell`` into ``tmp``; its summary."""
    import torch

    from polargs_plugin.service.data import ReaderOptions, load_dataset

    started = _now()
    if cell.threads > 0:
        torch.set_num_threads(cell.threads)
    clock = _Clock()
    report("scene", 0, 1)
    folder = ensure_scene(cell.scene)
    if not folder.exists():
        raise PolarInputError(folder, "dataset not found")
    gt_mesh = gt_mesh_path(cell.scene)
    clock.lap("scene")
    dataset = load_dataset(str(folder), ReaderOptions(**cell.reader))
    if dataset.pattern:
        print(f"raw mosaics: {dataset.pattern}", flush=True)
    if dataset.sfm_model:
        print(f"SfM: model written to {dataset.sfm_model}", flush=True)
    clock.lap("load")
    trainer, train_cfg, polar_cfg, figures, init_info = _train(cell, dataset.views, tmp, report, clock)
    summary = _summary(cell, folder, dataset, gt_mesh, trainer, train_cfg, polar_cfg, init_info)
    report("mesh", 0, 1)
    _mesh(cell, trainer, dataset.views, tmp)
    clock.lap("mesh")
    report("eval", 0, 1)
    # a scene folder is handed over as `polargs eval --gt FOLDER` takes it: with its whole-scene
    # mesh.ply beside gt_mesh.ply as the occluder; a GT given as NAME=PATH:GT_MESH has none
    eval_gt = gt_mesh if cell.scene.gt_mesh else gt_mesh.parent
    metrics, cull = _evaluate(cell, trainer, dataset, summary, tmp, eval_gt)
    clock.lap("eval")
    report("pictures", 0, 1)
    from polargs_plugin.service.evaluation import gt_meshes

    write_report_data(trainer, tmp, *gt_meshes(eval_gt), cull)
    clock.lap("pictures")
    summary.update(
        git=_git(),
        host=platform.node(),
        versions=run_versions(),
        started=started,
        finished=_now(),
        timings=clock.total(),
        figures=_figures(metrics, figures, trainer.curve),
        eval=_eval_record(metrics, cull, int(cell.eval.get("num_samples", 1_000_000))),
        files=sorted(p.name for p in tmp.iterdir() if p.name != SUMMARY_NAME) + [SUMMARY_NAME],
    )
    write_json(tmp / SUMMARY_NAME, summary)
    print(f"finished {cell.name}: {json.dumps(summary['figures'])}", flush=True)
    return summary


def _train(cell: Cell, views: list, tmp: Path, report: Progress, clock: "_Clock"):
    """Build the cell's trainer, resume its partial checkpoint if any, train; copy the final
    checkpoint into ``tmp`` and write the curves. (trainer, TrainConfig, PolarConfig, figures, init record)."""
    from polargs_plugin.service.configs import resolve_device

    train_cfg, polar_cfg = cell.configs()
    device = resolve_device(cell.device)
    train_cfg.device, train_cfg.progress = device, False
    if polar_cfg is not None and polar_cfg.cache_dir is None:
        polar_cfg.cache_dir = str(Path(cell.out) / "cache" / "polar_maps")
    init_points, init_info = _initial_points(cell, views, train_cfg)
    clock.lap("init")
    trainer = _make_trainer(views, train_cfg, polar_cfg, init_points, report)
    partial = partial_dir(cell)
    try:
        resumed = _resume(cell, trainer, partial)
    except Exception as err:  # unreadable or inconsistent: start over with a fresh trainer
        print(f"resume: cannot resume from {partial} ({type(err).__name__}: {err}); starting over", flush=True)
        with contextlib.suppress(FileNotFoundError):
            (partial / CHECKPOINT_NAME).unlink()
        trainer, resumed = _make_trainer(views, train_cfg, polar_cfg, init_points, report), False
    every = cell.checkpoint_every
    if every is None:
        from polargs_plugin.service.train import checkpoint_interval

        every = checkpoint_interval(None, train_cfg.iterations)
    trainer.partial = (partial, _plain(cell.fingerprint()))
    print(f"training {cell.variant} ({describe(cell.variant)}), {train_cfg.iterations} iterations on {device}"
          + (f", resumed at iteration {trainer.iteration}" if resumed else ""), flush=True)
    figures = trainer.train(checkpoint=partial / CHECKPOINT_NAME, checkpoint_every=every)
    shutil.copyfile(partial / CHECKPOINT_NAME, tmp / CHECKPOINT_NAME)
    figures["seconds"] = trainer.train_seconds()
    figures["loss"] = _final_loss(trainer.curve, train_cfg.log_every)  # the same whether resumed or not
    clock.lap("train")
    write_curves(tmp / CURVES_NAME, trainer.curve)
    return trainer, train_cfg, polar_cfg, figures, {**init_info, "device": device}


def _summary(cell: Cell, folder: Path, dataset, gt_mesh: Path, trainer, train_cfg, polar_cfg,
             init_info: dict[str, Any]) -> dict[str, Any]:
    """The run's summary before meshing (the settings; the figures come after the evaluation)."""
    import torch

    device = init_info.pop("device")
    return {
        "format": RUN_FORMAT,
        "name": cell.name,
        "dataset": str(folder),  # what `polargs mesh` / `polargs eval` read
        "dataset_format": dataset.format,
        "reader": dataset.record(),  # ... and how: service.load_dataset(dataset, ReaderOptions(**reader))
        "scene": cell.scene.to_dict(),
        "variant": cell.variant,
        "variant_description": describe(cell.variant),
        "seed": cell.seed,
        "preset": cell.preset,
        "factor": DEFAULT_FACTOR if cell.factor is None and cell.preset == "cpu" else cell.factor,
        "num_views": len(dataset.views),
        **init_info,
        "device": device,
        "device_name": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else platform.processor() or None,
        "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"),
        "job": _job_info(),
        "resumed_from": trainer.resumes,
        "gt_mesh": str(gt_mesh),
        "cell": cell.to_dict(),  # the plain description that reproduces the run (run_cell)
        "train_config": train_cfg.to_dict(),
        "polar_config": None if polar_cfg is None else polar_cfg.to_dict(),
    }


def _trained_model(trainer):
    """The trained Gaussians as a run folder's checkpoint holds them (what `polargs mesh` renders)."""
    from polargs_plugin.backends.reference.model import GaussianModel

    return GaussianModel.from_checkpoint(trainer.model.checkpoint())


def _mesh(cell: Cell, trainer, views: list, tmp: Path) -> None:
    """tsdf_mesh.ply (and its settings) in canonical order, as `polargs mesh` with the cell's settings."""
    from polargs_plugin.mesh import canonical_mesh_order
    from polargs_plugin.service.mesh import MeshSettings, fuse_model, write_mesh_result

    settings = MeshSettings(preset=cell.mesh.get("preset", "synthetic"), voxel=cell.mesh.get("voxel"),
                            sdf_trunc=cell.mesh.get("sdf_trunc"), depth_trunc=cell.mesh.get("depth_trunc"),
                            alpha_threshold=cell.mesh.get("alpha_threshold", 0.5),
                            min_cluster=cell.mesh.get("min_cluster", 0.05))
    result = fuse_model(_trained_model(trainer), views, settings, source=str(_published(tmp, tmp, cell)))
    write_mesh_result(result, tmp / MESH_NAME)
    canonical_mesh_order(tmp / MESH_NAME)


def _evaluate(cell: Cell, trainer, dataset, summary: dict[str, Any], tmp: Path, eval_gt: Path) -> tuple[dict[str, Any], bool]:
    """metrics.json, as `polargs eval --gt` (and ``--normals`` where the views have GT normals); (metrics, culled)."""
    from polargs_plugin.service.evaluation import EvalSettings, evaluate, write_metrics
    from polargs_plugin.service.runs import Run

    cull = bool(cell.eval.get("cull", True))
    settings = EvalSettings(gt=eval_gt, normals=any(v.normal_gt is not None for v in dataset.views),
                            num_samples=int(cell.eval.get("num_samples", 1_000_000)),
                            units=cell.eval.get("units", "scene units"), cull=cull, cull_dilation=EVAL_CULL_DILATION)
    metrics = evaluate(tmp, settings, run=Run(tmp, _trained_model(trainer), dataset, summary))
    metrics = _published(metrics, tmp, cell)
    write_metrics(metrics, tmp / METRICS_NAME)
    return metrics, cull


def _published(value: Any, tmp: Path, cell: Cell) -> Any:
    """``value`` (a path, or JSON data holding paths) with the paths into the temporary folder
    ``tmp`` made to point into the run folder it becomes, as an absolute path."""
    if isinstance(value, dict):
        return {key: _published(item, tmp, cell) for key, item in value.items()}
    if isinstance(value, list):
        return [_published(item, tmp, cell) for item in value]
    if isinstance(value, (str, Path)):
        path, base = os.path.abspath(value), os.path.abspath(tmp)
        if path == base or path.startswith(base + os.sep):
            published = os.path.normpath(os.path.join(os.path.abspath(cell.run_dir), os.path.relpath(path, base)))
            return Path(published) if isinstance(value, Path) else published
    return value


#: The visibility classes whose completeness and share a run's figures carry.
VISIBILITY_CLASSES = ("many", "few", "grazing")


def chamfer_figures(chamfer: dict[str, Any]) -> dict[str, Any]:
    """The visible-surface figures of a metrics.json ``chamfer`` entry, flat: ``chamfer_visible``,
    ``completeness_visible``, ``visible_fraction``, ``completeness_<class>`` and ``share_<class>``
    for the classes many, few, grazing (None where the evaluation had no depth maps)."""
    by_class = chamfer.get("completeness_by_visibility") or {}
    shares = chamfer.get("visibility_shares") or {}
    return {
        "chamfer_visible": chamfer.get("chamfer_visible"),
        "completeness_visible": chamfer.get("completeness_visible"),
        "visible_fraction": chamfer.get("visible_fraction"),
        **{f"completeness_{name}": by_class.get(name) for name in VISIBILITY_CLASSES},
        **{f"share_{name}": shares.get(name) for name in VISIBILITY_CLASSES},
    }


def _figures(metrics: dict[str, Any], figures: dict[str, Any], curve: list[dict[str, float]]) -> dict[str, Any]:
    """The summary's ``figures``: the evaluation's and the training's."""
    chamfer = metrics.get("chamfer") or {}
    return {
        "chamfer": chamfer.get("chamfer"),
        "accuracy": chamfer.get("accuracy"),
        "completeness": chamfer.get("completeness"),
        # the same means without the outlier cap, the fractions the cap dropped and the median
        # signed distance (outside positive): a mesh inside the GT shows there, not in the capped means
        "chamfer_uncapped": chamfer.get("chamfer_uncapped"),
        "accuracy_uncapped": chamfer.get("accuracy_uncapped"),
        "completeness_uncapped": chamfer.get("completeness_uncapped"),
        "accuracy_outliers": chamfer.get("accuracy_outliers"),
        "completeness_outliers": chamfer.get("completeness_outliers"),
        "signed_distance_median": chamfer.get("signed_distance_median"),
        # the uncapped Chamfer over the GT surface some view sees, and the completeness of the GT
        # points seen by many views, by few and only at grazing angles (docs/evaluation.md)
        **chamfer_figures(chamfer),
        "fscore": chamfer.get("fscore"),
        "precision": chamfer.get("precision"),
        "recall": chamfer.get("recall"),
        "normal_mae_deg": metrics.get("normal_mae_deg"),
        "psnr": figures["psnr"],
        "loss": figures["loss"],
        "iterations": figures["iterations"],
        "num_gaussians": figures["num_gaussians"],
        "appended_total": int(sum(row["appended"] for row in curve)),
        "train_seconds": figures["seconds"],
        "units": chamfer.get("units", "scene units"),
    }


def _eval_record(metrics: dict[str, Any], cull: bool, num_samples: int) -> dict[str, Any]:
    chamfer = metrics.get("chamfer") or {}
    return {"culled": cull, "num_samples": num_samples, "max_dist": chamfer.get("max_dist"),
            "fscore_threshold": chamfer.get("fscore_threshold"), "normal_region": metrics.get("normal_region")}


@functools.lru_cache(maxsize=1)
def _recording_trainer_class() -> type:
    """The reference Trainer that records every iteration's logs (the curves) and reports
    progress; defined on first use (the trainer imports torch, which a pool worker must not load
    before it sets its thread counts)."""
    from polargs_plugin.backends.reference.trainer import Trainer

    class RecordingTrainer(Trainer):
        """Records the curves; ``save_checkpoint`` also writes ``state.json`` beside the checkpoint
        (curves, fingerprint, training seconds so far) when ``partial`` is set."""

        curve: list[dict[str, float]]
        partial: tuple[Path, dict] | None = None
        seconds_before: float = 0.0
        resumes: list[int]
        report: Progress
        _started: float | None = None

        def train(self, *args, **kwargs):
            self._started = time.perf_counter()
            return super().train(*args, **kwargs)

        def train_seconds(self) -> float:
            return self.seconds_before + (0.0 if self._started is None else time.perf_counter() - self._started)

        def save_checkpoint(self, path):
            if self.partial is not None:
                folder, fingerprint = self.partial
                # state first: a kill between the two leaves a state one checkpoint ahead, cut back on load
                write_json(folder / PARTIAL_STATE, {"fingerprint": fingerprint, "iteration": self.iteration,
                                                    "curve": self.curve, "train_seconds": self.train_seconds(),
                                                    "resumed_from": self.resumes})
            return super().save_checkpoint(path)

        def step(self) -> dict[str, float]:
            if _INTERRUPTED:  # an interruption that a library swallowed on the way (an `except ImportError`)
                raise KeyboardInterrupt
            logs = super().step()
            self.curve.append({
                "iteration": self.iteration,
                **{k: float(v) for k, v in logs.items() if k not in ("num", "appended")},
                "num_gaussians": int(logs["num"]),
                "appended": int(logs.get("appended", 0)),
            })
            self.report("train", self.iteration, self.config.iterations)
            if self.iteration % 50 == 0 or self.iteration == self.config.iterations:
                print(f"iteration {self.iteration}: loss {logs['loss']:.4f}, PSNR {logs['psnr']:.2f}, "
                      f"{int(logs['num'])} Gaussians", flush=True)
            return logs

    return RecordingTrainer


def _make_trainer(views, config, polar_cfg, init_points, report: Progress):
    """A recording trainer (see :func:`_recording_trainer_class`) with the hooks of ``polar_cfg``."""
    from polargs_plugin.service.train import build_trainer

    trainer = build_trainer(views, config, polar_cfg, init_points, trainer_class=_recording_trainer_class())
    trainer.curve, trainer.resumes, trainer.report = [], [], report
    return trainer


def _plain(data: Any) -> Any:
    """``data`` as it reads back from JSON."""
    return json.loads(json.dumps(json_safe(data)))


def _resume(cell: Cell, trainer, partial: Path) -> bool:
    """Load ``partial``'s checkpoint into ``trainer`` when it is this cell's (else remove it and
    return False). Raises when the checkpoint is this cell's but cannot be loaded."""
    checkpoint, state_path = partial / CHECKPOINT_NAME, partial / PARTIAL_STATE
    if not checkpoint.is_file():
        return False
    try:
        state = json.loads(state_path.read_text())
    except (OSError, ValueError):
        state = {}
    if state.get("fingerprint") != _plain(cell.fingerprint()):
        print(f"resume: {partial} holds no checkpoint of this configuration; starting over", flush=True)
        checkpoint.unlink()
        return False
    trainer.load_checkpoint(checkpoint)
    curve = [row for row in state["curve"] if row["iteration"] <= trainer.iteration]
    if [row["iteration"] for row in curve] != list(range(1, trainer.iteration + 1)):
        raise ValueError(f"curves ({len(curve)} rows) do not match the checkpoint (iteration {trainer.iteration})")
    trainer.curve = curve
    trainer.seconds_before = float(state.get("train_seconds") or 0.0)
    trainer.resumes = [int(i) for i in state.get("resumed_from") or []] + [trainer.iteration]
    print(f"resume: loaded {checkpoint} at iteration {trainer.iteration}", flush=True)
    return True


def _final_loss(curve: list[dict[str, float]], log_every: int) -> float | None:
    """The trainer's final ``loss`` figure (mean over the iterations since the last multiple of
    ``log_every``), from the curves: identical for a resumed and an uninterrupted run."""
    if not curve:
        return None
    end = int(curve[-1]["iteration"])
    start = ((end - 1) // max(1, log_every)) * max(1, log_every)
    values = [row["loss"] for row in curve if row["iteration"] > start]
    return float(sum(values) / len(values)) if values else None


def _job_info() -> dict[str, Any] | None:
    """The cluster job this run ran in (Slurm / submitit), for the summary."""
    env = os.environ
    if "SLURM_JOB_ID" in env:
        job = env.get("SLURM_ARRAY_JOB_ID")
        return {"scheduler": "slurm", "job_id": f"{job}_{env.get('SLURM_ARRAY_TASK_ID')}" if job else env["SLURM_JOB_ID"],
                "node": env.get("SLURMD_NODENAME")}
    for key, name in (("SUBMITIT_LOCAL_JOB_ID", "submitit-local"), ("SUBMITIT_DEBUG_JOB_ID", "submitit-debug")):
        if key in env:
            return {"scheduler": name, "job_id": env[key], "node": platform.node()}
    return None


def _initial_points(cell: Cell, views, config):
    """(init_points for the Trainer or None for its default visual hull, record for the summary)."""
    import torch

    info: dict[str, Any] = {"init": cell.init, "init_used": cell.init, "init_note": None}
    if cell.init == "hull":
        info["init_points"] = config.num_init_points
        return None, info
    if cell.init == "random":
        from polargs_plugin.backends.reference.model import init_points_in_box

        points = init_points_in_box(views, config.num_init_points, torch.Generator().manual_seed(cell.seed))
        info["init_points"] = int(points[0].shape[0])
        return points, info
    from polargs_plugin.ablation.init import sfm_points

    try:
        points, colors = sfm_points(views)
        count = int(points.shape[0])
        if count >= MIN_SFM_POINTS:
            info["init_points"] = count
            return (points, colors), info
        note = f"SfM found {count} points (< {MIN_SFM_POINTS})"
    except NotImplementedError as err:
        note = f"SfM unavailable ({err})"
    print(f"init: {note}; falling back to the visual hull", flush=True)
    info.update(init_used="hull", init_note=note + "; fell back to the visual hull", init_points=config.num_init_points)
    return None, info


#: The distributions whose versions a run records: the package and the libraries its figures
#: come from (training, PatchMatch, meshing, evaluation).
RECORDED_DISTRIBUTIONS: tuple[str, ...] = (
    "polargs_plugin", "torch", "numpy", "scipy", "numba", "kornia", "opencv-python-headless", "open3d",
)


def run_versions() -> dict[str, str | None]:
    """Python's version and the installed version of each of :data:`RECORDED_DISTRIBUTIONS`
    (null for one not installed as a distribution, e.g. the package run from a source tree on
    ``PYTHONPATH``). The same code and seed can train to figures a seed's spread apart on two
    machines whose libraries differ; these say whether they did."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in RECORDED_DISTRIBUTIONS:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _git() -> dict[str, Any]:
    """Commit of the source tree this package runs from (null outside a git checkout)."""
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        if commit.returncode != 0:
            return {"commit": None, "dirty": None}
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                capture_output=True, text=True, timeout=10)
        return {"commit": commit.stdout.strip(), "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


if __name__ == "__main__":  # run one cell from its JSON description: python -m polargs_plugin.ablation.cell CELL.json
    cell = Cell.from_dict(json.loads(Path(sys.argv[1]).read_text()))
    try:
        print(json.dumps(run_cell(cell)["figures"], indent=2))
    except CellFailed as failure:
        print(f"error: {failure}", file=sys.stderr)
        sys.exit(1)
