"""Expand scenes x variants x seeds (x inits) into cells and run them on a local process pool
(one run per GPU on a multi-GPU machine: each worker sees one GPU through CUDA_VISIBLE_DEVICES).
A cluster runs the same cells through :mod:`polargs_plugin.ablation.executors`.

Resumable: a cell whose run folder exists is skipped (run folders are complete or absent).
The grid goes on after a failed cell; :class:`GridResult` lists the failures with their logs.
``<out>/grid.json`` records the cells as plain data (what a cluster executor would submit).

This module imports nothing heavy at import time: pool workers (``spawn``) import it first and
set their thread counts before torch / numba load.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import multiprocessing
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

from polargs_plugin.ablation.cell import Cell, CellFailed, is_done, mark_interrupted, run_cell
from polargs_plugin.ablation.scenes import SceneSpec, ensure_scene, parse_scene
from polargs_plugin.ablation.spec import INITS
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.data import ReaderOptions
from polargs_plugin.service.mesh import MeshSettings

__all__ = ["GridOptions", "build_cells", "expand", "run_grid", "GridResult", "default_jobs", "write_grid_file", "GRID_FILE"]

GRID_FILE = "grid.json"


def expand(scenes: Sequence[SceneSpec], variants: Sequence[str], seeds: Sequence[int], out: str | os.PathLike,
           inits: Sequence[str] = ("hull",), **common: Any) -> list[Cell]:
    """Every (scene, seed, init, variant) combination as a :class:`Cell` (``common``: the other
    Cell fields, e.g. ``preset``, ``factor``, ``train_overrides``). Order: scene, seed, init, variant."""
    out = str(Path(out).resolve())
    return [Cell(scene=scene, variant=variant, seed=int(seed), out=out, init=init, **common)
            for scene in scenes for seed in seeds for init in inits for variant in variants]


@dataclass(frozen=True)
class GridOptions:
    """What every cell of a grid shares, as ``polargs ablate`` takes it (docs/ablation.md).

    Attributes:
        out: the grid folder.
        scene_cache: where bundled scenes are generated (None: ``out/scenes``).
        views: views of a generated scene (None: its own, 24 for a bundled scene, the seed's for a
            family scene).
        size: (width, height) of a generated scene (None: its own, 128x128 for a bundled scene,
            the seed's for a family scene).
        inits: initial points, each a separate cell: ``hull``, ``sfm``, ``random``.
        preset: ``cpu`` (the vanilla schedule x ``factor``) or ``paper``.
        factor: the cpu preset's schedule factor (None: 1/6, 5000 iterations).
        iters: training iterations (None: the preset's).
        train_overrides / polar_overrides: nested partial dicts of TrainConfig / PolarConfig fields.
        mesh_preset: TSDF settings (``synthetic`` or ``paper``).
        voxel: TSDF voxel (None: the preset's; bundled scenes scale it to 1 / min(W, H)).
        incidence_trunc: cap of the TSDF truncation's 1/cos widening (``polargs mesh --incidence-trunc``;
            1 gives every pixel the preset's truncation).
        partial_alpha: lowest opacity of the partly transparent pixels fused inside the masks
            (``polargs mesh --partial-alpha``; 0.5 turns it off).
        spare_pieces_in_masks: small TSDF pieces inside every view's mask stay (``polargs mesh
            --spare-pieces-in-masks``; off by default).
        eval_samples: points sampled per mesh for Chamfer.
        cull: cull predicted points to the object region before Chamfer.
        threads: torch threads of each run.
        device: torch device (None: cuda if available, else cpu).
        checkpoint_every: iterations between the periodic checkpoints a run resumes from (None: 10 per run).
        reader: reader options of dataset-folder scenes (an error with bundled scenes).
        command: the command line, recorded in each run's provenance (None: the running process's).
    """

    out: Path
    scene_cache: Path | None = None
    views: int | None = None
    size: tuple[int, int] | None = None
    inits: tuple[str, ...] = ("hull",)
    preset: str = "cpu"
    factor: float | None = None
    iters: int | None = None
    train_overrides: dict[str, Any] = field(default_factory=dict)
    polar_overrides: dict[str, Any] = field(default_factory=dict)
    mesh_preset: str = "synthetic"
    voxel: float | None = None
    incidence_trunc: float = MeshSettings.incidence_trunc
    partial_alpha: float = MeshSettings.partial_alpha
    spare_pieces_in_masks: bool = MeshSettings.spare_pieces_in_masks
    eval_samples: int = 1_000_000
    cull: bool = True
    threads: int = 1
    device: str | None = None
    checkpoint_every: int | None = None
    reader: ReaderOptions = field(default_factory=ReaderOptions)
    command: str | None = None


# How the command line spells each reader option, for the refusal with bundled scenes.
_READER_FLAGS = {"pattern": "--pattern", "bit_depth": "--bit-depth", "sfm": "--sfm", "check_pattern": "--no-pattern-check"}


def _scenes(options: GridOptions, scene_texts: Sequence[str], warn: Callable[[str], None]) -> list[SceneSpec]:
    cache = options.scene_cache or Path(options.out) / "scenes"
    width, height = options.size or (None, None)
    scenes = []
    for text in scene_texts:
        try:
            scenes.append(parse_scene(text, cache, options.views, width, height))
        except ValueError as err:
            raise PolarInputError("--scenes", str(err)) from None
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise PolarInputError("--scenes", f"the same scene name twice ({', '.join(names)})")
    for scene in scenes:
        if scene.bundled is None and not Path(scene.path).exists():
            warn(f"{scene.path}: dataset not found; the runs of scene '{scene.name}' will fail")
    return scenes


def _mesh_settings(options: GridOptions, scene: SceneSpec) -> dict[str, Any]:
    from polargs_plugin.data.resolution import target_size

    mesh: dict[str, Any] = {"preset": options.mesh_preset}
    try:
        width, height = target_size(scene.width, scene.height, options.reader.resolution) if scene.bundled else (0, 0)
    except ValueError as err:
        raise PolarInputError(f"--resolution {options.reader.resolution}", f"scene '{scene.name}': {err}") from None
    if options.voxel is not None:
        mesh["voxel"] = options.voxel
    elif scene.bundled is not None and options.mesh_preset == "synthetic" and min(width, height) != 128:
        mesh["voxel"] = 1.0 / min(width, height)  # the preset's voxel (1/128 at 128 px) per pixel size (trained)
    if options.incidence_trunc != MeshSettings.incidence_trunc:
        # only when set: the cells of grids from before the option keep their fingerprints (and resume)
        mesh["incidence_trunc"] = options.incidence_trunc
    if options.partial_alpha != MeshSettings.partial_alpha:
        mesh["partial_alpha"] = options.partial_alpha
    if options.spare_pieces_in_masks != MeshSettings.spare_pieces_in_masks:
        mesh["spare_pieces_in_masks"] = options.spare_pieces_in_masks
    return mesh


def _bundled_reader(reader: dict[str, Any]) -> dict[str, Any]:
    """The reader options that apply to a bundled scene: only the resolution."""
    return {"resolution": reader["resolution"]} if "resolution" in reader else {}


def build_cells(options: GridOptions, scene_texts: Sequence[str], variants: Sequence[str], seeds: Sequence[int],
                warn: Callable[[str], None] = lambda line: None) -> list[Cell]:
    """The cells of a grid (order: scene, seed, init, variant), every setting checked first.

    Raises:
        PolarInputError: naming the option (``--scenes``, ``--init``, ``--train-set``, ...).
    """
    scenes = _scenes(options, scene_texts, warn)
    reader = options.reader.to_dict()
    flags = [_READER_FLAGS[k] for k in reader if k in _READER_FLAGS]
    bundled = [s.name for s in scenes if s.bundled is not None]
    if flags and bundled:  # as `polargs train` does for synthetic:NAME (--format is ignored there, as in train)
        raise PolarInputError(", ".join(flags), f"only for dataset folders, not for a bundled scene ({', '.join(bundled)}); "
                              "run bundled scenes and dataset folders as separate commands (the same --out is fine)")
    bad = [i for i in options.inits if i not in INITS]
    if bad:
        raise PolarInputError("--init", f"unknown {', '.join(bad)} (known: {', '.join(INITS)})")
    train_overrides = dict(options.train_overrides)
    if options.iters is not None:
        train_overrides["iterations"] = options.iters
    cells = []
    for scene in scenes:
        cells += expand([scene], variants, seeds, options.out, options.inits, preset=options.preset,
                        factor=options.factor, train_overrides=train_overrides,
                        polar_overrides=dict(options.polar_overrides), mesh=_mesh_settings(options, scene),
                        eval={"num_samples": options.eval_samples, "cull": options.cull},
                        threads=options.threads, device=options.device, checkpoint_every=options.checkpoint_every, command=options.command,
                        reader=_bundled_reader(reader) if scene.bundled is not None else dict(reader))
    hooked = [variant for variant in dict.fromkeys(variants)  # overrides are checked before anything runs
              if next(c for c in cells if c.variant == variant).configs()[1] is not None]
    if options.polar_overrides and not hooked:
        raise PolarInputError("--polar-set", f"sets PolarGS values, but no variant of this grid uses the PolarGS hooks "
                              f"({', '.join(dict.fromkeys(variants))})")
    return cells


def default_jobs(threads_per_run: int = 1, gpus: Sequence[str] = ()) -> int:
    """One run per GPU when ``gpus`` are given, else cores available to this process // threads
    per run (at least 1)."""
    if gpus:
        return len(gpus)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, cores // max(1, threads_per_run))


def write_grid_file(cells: Sequence[Cell], out: str | os.PathLike) -> Path:
    """``<out>/grid.json``: the cells of the latest invocation, as plain data."""
    from polargs_plugin.io import atomic_write

    path = Path(out) / GRID_FILE
    with atomic_write(path) as handle:
        json.dump({"format": "polargs-ablation-grid-v1", "cells": [c.to_dict() for c in cells]}, handle, indent=2)
    return path


@dataclass
class GridResult:
    """What :func:`run_grid` did: cells skipped (already done), finished now, and failed."""

    skipped: list[Cell] = field(default_factory=list)
    finished: list[tuple[Cell, dict]] = field(default_factory=list)
    failed: list[tuple[Cell, str, str]] = field(default_factory=list)  # (cell, log path, message)

    @property
    def ok(self) -> bool:
        return not self.failed


# ------------------------------------------------------------------------------------ progress
class _Progress:
    """One bar for the whole grid, in work units: a cell's iterations, plus a tenth of them each
    for meshing and for evaluation (with the report pictures).

    The remaining time is the average rate since the first training step applied to the work
    left, shown once a cell has ended or a tenth of the work is done. tqdm's own estimate counted
    scene generation and SfM (a minute or more before any step) and came out hours off; the
    set-up of later cells still enters the average, as it should. The rate counts only work done
    in this grid (``worked``): a run resumed from its checkpoint jumps the bar to its iteration at
    its first step, and a failed run's unfinished work leaves the bar, but neither took time here."""

    #: share of the work after which the remaining time is shown even if no cell has ended yet
    ETA_AFTER = 0.1

    def __init__(self, cells: Sequence[Cell], enabled: bool, stream: TextIO):
        self.lock = threading.Lock()
        self.stream = stream
        self.weights: dict[str, tuple[int, int]] = {}
        for cell in cells:
            iterations = max(1, int(cell.configs()[0].iterations))
            self.weights[cell.name] = (iterations, max(1, iterations // 10))
        self.done: dict[str, int] = dict.fromkeys(self.weights, 0)
        self.counts = {"done": 0, "failed": 0, "running": 0}
        self.started: set[str] = set()
        self.clock: Callable[[], float] = time.monotonic
        self.worked = 0  # units done by this grid (no resumed part, no failed run's remainder)
        self.training: set[str] = set()  # cells that have reported a training step
        self.first_work: tuple[float, int] | None = None  # (clock, units worked) at the first training step
        total = sum(i + 2 * e for i, e in self.weights.values())
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="ablate", unit="step", file=stream, dynamic_ncols=True,
                            mininterval=0.5, bar_format="{l_bar}{bar}| {percentage:3.0f}% [{elapsed}]{postfix}")
            self._postfix()

    def _postfix(self) -> None:
        if self.bar is not None:
            c = self.counts
            self.bar.set_postfix_str(f"{self._remaining()}, {c['done']}/{len(self.weights)} cells done, "
                                     f"{c['running']} running, {c['failed']} failed", refresh=False)

    def _remaining(self) -> str:
        done, total = self.bar.n, self.bar.total
        ended = self.counts["done"] + self.counts["failed"]
        if self.first_work is None or (ended == 0 and done < self.ETA_AFTER * total):
            return "time left: after the first cell"
        since, units = self.first_work
        rate = max(self.worked - units, 1) / max(self.clock() - since, 1e-9)
        return f"~{self.bar.format_interval((total - done) / rate)} left"

    def update(self, name: str, phase: str, done: int, total: int) -> None:
        iterations, extra = self.weights[name]
        units = {"scene": 0, "train": round(iterations * done / max(1, total)), "mesh": iterations,
                 "eval": iterations + extra, "pictures": iterations + 2 * extra, "done": iterations + 2 * extra}.get(phase)
        if units is None:
            return
        with self.lock:
            if name not in self.started:
                self.started.add(name)
                self.counts["running"] += 1
                self._postfix()
            delta = units - self.done[name]
            if delta > 0:
                self.done[name] = units
                self.worked += delta
                if phase == "train" and name not in self.training:
                    self.training.add(name)
                    # the first report comes after one step; a resumed run's checkpoint holds the rest
                    self.worked -= round(iterations * (done - 1) / max(1, total))
                if self.first_work is None:
                    self.first_work = (self.clock(), self.worked)
                if self.bar is not None:
                    self.bar.update(delta)
                    self._postfix()

    def finish(self, name: str, ok: bool, line: str) -> None:
        iterations, extra = self.weights[name]
        with self.lock:
            if name in self.started:
                self.counts["running"] -= 1
            self.counts["done" if ok else "failed"] += 1
            delta = iterations + 2 * extra - self.done[name]
            self.done[name] += delta
            if ok:
                self.worked += delta
            if self.bar is not None:
                self.bar.update(delta)
                self._postfix()
                self.bar.refresh()
                self.bar.write(line, file=self.stream)
            else:
                print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _finished_line(cell: Cell, summary: dict) -> str:
    f = summary.get("figures", {})

    def num(key: str, fmt: str) -> str:
        return "n/a" if f.get(key) is None else format(f[key], fmt)

    seconds = summary.get("timings", {}).get("total", 0.0)
    return (f"done    {cell.name}: Chamfer {num('chamfer', '.4g')}, normal MAE {num('normal_mae_deg', '.2f')} deg, "
            f"PSNR {num('psnr', '.2f')} dB, {f.get('num_gaussians', '?')} Gaussians, {seconds:.0f} s")


# ------------------------------------------------------------------------------------- workers
_QUEUE: Any = None


_ORPHANED = threading.Event()
_STOP: Any = None  # the grid's stop event (a multiprocessing Event), set when the grid is interrupted
_IN_CELL = threading.Event()  # this worker runs a cell
_INTERRUPTED = threading.Event()  # ... and has been asked to stop it


def _interrupt_cell(signum: int, frame: Any) -> None:
    """A worker's SIGINT / SIGTERM handler: stop the running cell once, as Ctrl-C does (its
    partial checkpoint is kept). A signal between cells, or a repeated one, is ignored: it would
    otherwise break the pool's loop, or the cell's own clean-up of the interruption."""
    if _IN_CELL.is_set() and not _INTERRUPTED.is_set():
        _INTERRUPTED.set()
        mark_interrupted()  # what the KeyboardInterrupt may turn into still ends the cell as interrupted
        raise KeyboardInterrupt


def _watch(parent: int, interval: float = 1.0, grace: float = 10.0) -> None:
    """Stop this worker's cell when the grid asks (its stop event), and end this worker once its
    parent, the grid, is gone: a grid killed by SIGKILL cannot stop its workers itself, and they
    would otherwise train their cells to the end unseen. SIGINT stops the running cell and
    :func:`_worker` then exits; a worker that was idle, or that blocks on the pool's pipes (nobody
    reads them any more), exits after ``grace`` seconds."""
    stopped = False
    while os.getppid() == parent:
        if _STOP is None or stopped:
            time.sleep(interval)
        elif _STOP.wait(interval):
            stopped = True
            os.kill(os.getpid(), signal.SIGINT)
    _ORPHANED.set()
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(grace)
    os._exit(1)


def _init_worker(queue: Any, threads: int, gpu_queue: Any = None, parent: int | None = None, stop: Any = None) -> None:
    """Pool initializer: thread counts before torch / numba are imported, the progress queue,
    this worker's GPU (``CUDA_VISIBLE_DEVICES``, read by CUDA at its first use in the worker) and
    a watch (:func:`_watch`) on ``stop``, the grid's stop event, and on ``parent``, the grid's
    process id (passed, not read here: the grid may be gone before a spawned worker gets this far)."""
    global _QUEUE, _STOP
    _QUEUE, _STOP = queue, stop
    # A grid started in the background (`cmd &` in a script, nohup) inherits SIGINT ignored; the
    # workers take their own handler so that an interruption reaches the cell. SIGTERM (a
    # scheduler's, sent to every process of a job) stops the cell the same way.
    signal.signal(signal.SIGINT, _interrupt_cell)
    signal.signal(signal.SIGTERM, _interrupt_cell)
    if parent is not None:
        threading.Thread(target=_watch, args=(parent,), daemon=True).start()
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[key] = str(max(1, threads))
    if gpu_queue is not None:
        with contextlib.suppress(Exception):
            os.environ["CUDA_VISIBLE_DEVICES"] = str(gpu_queue.get(timeout=30))


def _worker(cell_data: dict) -> dict:
    cell = Cell.from_dict(cell_data)
    step = max(1, int(cell.configs()[0].iterations) // 100)

    def report(phase: str, done: int, total: int) -> None:
        if phase != "train" or done % step == 0 or done == total:
            _QUEUE.put((cell.name, phase, done, total))

    _INTERRUPTED.clear()
    mark_interrupted(False)
    _IN_CELL.set()  # before the check: a stop signalled from here on interrupts the cell
    try:
        if _STOP is not None and _STOP.is_set():
            raise KeyboardInterrupt  # the grid was interrupted: a cell queued meanwhile does not start
        return run_cell(cell, progress=report)
    except BaseException:
        if _ORPHANED.is_set():  # the grid is gone: nobody to report to, and exiting normally would
            os._exit(130)  # wait for the pool's feeder threads on pipes nobody reads
        raise
    finally:
        _IN_CELL.clear()


def _write_crash_log(cell: Cell, message: str) -> str:
    cell.log_path.parent.mkdir(parents=True, exist_ok=True)
    if not cell.log_path.exists():
        cell.log_path.write_text(f"cell {cell.name}\n{json.dumps(cell.to_dict(), indent=2)}\n\nFAILED: {message}\n")
    return str(cell.log_path)


# ---------------------------------------------------------------------------------------- grid
def run_grid(cells: Sequence[Cell], jobs: int = 1, progress: bool = True, stream: TextIO | None = None,
             prepare_scenes: bool = True, gpus: Sequence[str] = ()) -> GridResult:
    """Run the cells not yet done, ``jobs`` at a time; never stops at a failure.

    Args:
        cells: the grid (see :func:`expand`); their ``out`` folders are created.
        jobs: parallel runs. 1 runs in this process; more use a ``spawn`` process pool whose
            workers use ``cell.threads`` threads each.
        progress: one progress bar for the whole grid on ``stream`` (and one line per cell).
        stream: where progress goes (default: stderr).
        prepare_scenes: generate the bundled scenes first (once each; a failure here is left to
            the cells, which then fail with a log).
        gpus: GPU ids (as in ``CUDA_VISIBLE_DEVICES``) handed to the pool's workers in turn, one
            each (``jobs`` > ``len(gpus)`` puts several runs on a GPU); with ``jobs`` 1 the run
            uses this process's devices.
    """
    stream = stream or sys.stderr
    result = GridResult()
    names = [c.name for c in cells]
    if len(set(names)) != len(names):
        raise ValueError("the grid holds the same cell twice")
    for out in {c.out for c in cells}:
        Path(out).mkdir(parents=True, exist_ok=True)
    pending = []
    for cell in cells:
        (result.skipped if is_done(cell) else pending).append(cell)
    if not pending:
        return result
    if prepare_scenes:
        generate_scenes(pending, stream, progress)
    bar = _Progress(pending, progress, stream)
    try:
        if jobs <= 1:
            for cell in pending:
                try:
                    summary = run_cell(cell, progress=lambda phase, done, total, n=cell.name: bar.update(n, phase, done, total))
                except CellFailed as failure:
                    result.failed.append((cell, failure.log, failure.message))
                    bar.finish(cell.name, False, f"FAILED  {failure}")
                else:
                    result.finished.append((cell, summary))
                    bar.finish(cell.name, True, _finished_line(cell, summary))
        else:
            _run_pool(pending, jobs, bar, result, gpus)
    finally:
        bar.close()
    return result


def generate_scenes(cells: Sequence[Cell], stream: TextIO | None = None, progress: bool = False) -> None:
    """Generate the cells' bundled scenes that are not there yet, and run SfM once for the dataset
    folders read with ``sfm`` (reader option ``--sfm``) that have no COLMAP model yet, so parallel
    cells do not each run it (once each; a failure is left to the cells, which then fail with a log)."""
    stream = stream or sys.stderr
    for scene in {c.scene for c in cells if c.scene.bundled}:
        if not Path(scene.path).is_dir():
            print(f"generating {scene.bundled} ({scene.views} views, {scene.width}x{scene.height}) -> {scene.path}",
                  file=stream, flush=True)
            with contextlib.suppress(Exception):
                ensure_scene(scene, progress=progress)
    sfm = {c.scene.path: c.reader for c in cells if c.scene.bundled is None and c.reader.get("sfm")}
    for path, reader in sfm.items():
        if Path(path).is_dir() and not (Path(path) / "sparse" / "0").is_dir():
            from polargs_plugin.service.data import ReaderOptions, load_dataset

            print(f"SfM: {path} has no COLMAP model; running SfM once for its cells", file=stream, flush=True)
            with contextlib.suppress(Exception):
                load_dataset(path, ReaderOptions(**reader))


def _run_pool(pending: Sequence[Cell], jobs: int, bar: _Progress, result: GridResult, gpus: Sequence[str] = ()) -> None:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    threads = max(c.threads for c in pending)
    workers = min(jobs, len(pending))
    gpu_queue = None
    if gpus:
        gpu_queue = context.Queue()
        for i in range(workers):
            gpu_queue.put(str(gpus[i % len(gpus)]))

    def pump() -> None:
        while True:
            item = queue.get()
            if item is None:
                return
            with contextlib.suppress(KeyError):
                bar.update(*item)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    stop = context.Event()
    try:
        futures: dict = {}
        with cf.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_init_worker,
                                    initargs=(queue, threads, gpu_queue, os.getpid(), stop)) as pool, \
                _stopping_on_interrupt(stop, futures):
            futures.update({pool.submit(_worker, cell.to_dict()): cell for cell in pending})
            _collect(futures, bar, result)
    finally:
        queue.put(None)
        reader.join(timeout=5)


@contextlib.contextmanager
def _stopping_on_interrupt(stop: Any, futures: dict) -> Any:
    """On KeyboardInterrupt (Ctrl-C, or SIGTERM turned into it): cancel the cells not started, ask
    the workers to stop their running cells (each keeps its partial checkpoint) and wait until they
    have, so the pool ends cleanly (no process or semaphore left behind); then re-raise."""
    try:
        yield
    except KeyboardInterrupt:
        for future in futures:
            future.cancel()
        stop.set()
        cf.wait(futures)
        raise


def _collect(futures: dict, bar: _Progress, result: GridResult) -> None:
    """Each cell's outcome into ``result`` as its future completes."""
    for future in cf.as_completed(futures):
        cell = futures[future]
        try:
            summary = future.result()
        except CellFailed as failure:
            result.failed.append((cell, failure.log, failure.message))
            bar.finish(cell.name, False, f"FAILED  {failure}")
        except Exception as err:  # the worker process died (BrokenProcessPool) or could not start
            message = f"worker process failed: {type(err).__name__}: {err}"
            log = _write_crash_log(cell, message)
            result.failed.append((cell, log, message))
            bar.finish(cell.name, False, f"FAILED  {cell.name}: {message} (log: {log})")
        else:
            result.finished.append((cell, summary))
            bar.finish(cell.name, True, _finished_line(cell, summary))
