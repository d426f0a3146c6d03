"""Training a run folder with the reference backend, as ``polargs train`` does.

:func:`train_run` owns the run-folder contract (docs/cli.md): it locks the folder, checks that a
``resume`` continues the same data, estimates the peak memory (refusing what is beyond reach) and
the time (:mod:`polargs_plugin.service.estimates`), chooses the maps cache, trains with periodic
checkpoints and writes ``summary.json``. A stop request (Ctrl-C) ends the training after the
current iteration with a final checkpoint (:class:`TrainingInterrupted`); nothing is left of a
run that did not start.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from polargs_plugin.io import FolderLock, PolarInputError, atomic_write, check_writable, remove_stale_temporaries
from polargs_plugin.service.data import Dataset, ReaderOptions, dataset_location, load_dataset
from polargs_plugin.service.estimates import RunEstimate, estimate_memory, estimate_time, peak_memory
from polargs_plugin.service.fingerprints import compare_fingerprints, fingerprint, read_fingerprint
from polargs_plugin.service.maps import MAPS_NAME, prepare_maps_cache, rebuilt_reasons
from polargs_plugin.service.provenance import provenance
from polargs_plugin.service.runs import CHECKPOINT_NAME, FINGERPRINT_NAME, LOCK_NAME, SUMMARY_NAME

if TYPE_CHECKING:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.types import View

__all__ = ["CHECKPOINTS_PER_RUN", "TrainRequest", "TrainResult", "StopRequest", "TrainingInterrupted",
           "RunEstimate", "build_trainer", "checkpoint_interval", "estimate_memory", "estimate_time", "train_run"]

#: Default periodic checkpoints: this many per run (every 10 % of the iterations).
CHECKPOINTS_PER_RUN = 10

Notify = Callable[[str], None]


def _ignore(_: str) -> None:
    pass


@dataclass
class TrainRequest:
    """A training run of ``polargs train``, as plain values.

    Attributes:
        dataset: a dataset folder, or ``synthetic:NAME``.
        out: the run folder.
        train: the trainer's settings (``service.configs.train_config``).
        polar: the PolarGS settings, or None for plain 3DGS (``service.configs.polar_config``).
        reader: the dataset reader's options.
        maps_cache: a maps cache chosen by the user (default: ``out/maps``, seeded from
            ``DATASET/preprocessed/maps``).
        resume: continue ``out/checkpoint.pt`` (on the same data: checked).
        checkpoint_every: iterations between periodic checkpoints; None: every 10 % of the run;
            0: only at the end.
        command: the command line, recorded in the folder's lock and the summary's ``provenance``.
        labels: how the settings were chosen (``schedule``, ``preset``, ``switches``,
            ``config_file``), recorded in ``summary.json``.
        memory_check: refuse to start when the estimated peak memory is beyond reach
            (:mod:`polargs_plugin.service.estimates`; default True).
    """

    dataset: str
    out: Path
    train: "TrainConfig"
    polar: PolarConfig | None = None
    reader: ReaderOptions = field(default_factory=ReaderOptions)
    maps_cache: Path | None = None
    resume: bool = False
    checkpoint_every: int | None = None
    command: str = "polargs train"
    labels: dict[str, Any] = field(default_factory=dict)
    memory_check: bool = True


@dataclass
class TrainResult:
    """A finished training.

    Attributes:
        run_dir: the run folder.
        summary: what ``summary.json`` holds: settings, the final figures (``iterations``,
            ``num_gaussians``, ``psnr``, ``loss``, ``seconds``), the full configs and the
            ``provenance`` (:func:`polargs_plugin.service.provenance.provenance`: library versions,
            commit, command line, machine, threads).
        dataset: the data trained on.
    """

    run_dir: Path
    summary: dict[str, Any]
    dataset: Dataset


class StopRequest:
    """A request to stop training, set from a signal handler.

    The first :meth:`request` during training asks to stop after the current iteration (the
    training then ends with a checkpoint); a second one, or one before training started, stops at
    once by raising ``KeyboardInterrupt`` where the program is.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        self.hard = False
        self.armed = False

    def request(self, signum: int) -> None:
        """Ask to stop (``signum``: the signal that asked); raises KeyboardInterrupt when at once."""
        if self.signal is not None or not self.armed:
            self.signal, self.hard = signum, True
            raise KeyboardInterrupt
        self.signal = signum

    @property
    def exit_status(self) -> int:
        """128 + the signal number (SIGINT when none came: a KeyboardInterrupt of its own)."""
        return 128 + int(self.signal if self.signal is not None else signal.SIGINT)

    def arm(self, trainer: "Trainer") -> None:
        """From now on a first request stops ``trainer`` after its current step."""
        step = trainer.step

        def step_then_check():
            logs = step()
            if self.signal is not None:
                raise KeyboardInterrupt
            return logs

        trainer.step = step_then_check
        self.armed = True


class TrainingInterrupted(Exception):
    """Training was stopped by a :class:`StopRequest`.

    Attributes:
        status: the exit status of a program stopped this way (128 + signal).
        situation: what was kept, in one line.
        resumable: whether ``resume`` continues from a checkpoint.
    """

    def __init__(self, status: int, situation: str, resumable: bool):
        super().__init__(situation)
        self.status, self.situation, self.resumable = status, situation, resumable

    def message(self, resume_command: str) -> str:
        """The line to show, naming the command that resumes when there is one."""
        return self.situation + (f"; resume with: {resume_command}" if self.resumable else "")


def checkpoint_interval(every: int | None, iterations: int) -> int:
    """Iterations between periodic checkpoints: ``every``, or 10 per run when None."""
    return max(1, math.ceil(iterations / CHECKPOINTS_PER_RUN)) if every is None else every


def build_trainer(views: Sequence[View], config: "TrainConfig", polar: PolarConfig | None,
                  init_points: Any = None, trainer_class: type | None = None) -> "Trainer":
    """The reference trainer (or ``trainer_class``, a subclass) with the PolarGS hooks of ``polar``
    (None: plain 3DGS). Settings the hooks or the trainer refuse raise PolarInputError."""
    from polargs_plugin.backends.reference.trainer import Trainer
    from polargs_plugin.hooks import PolarHooks

    try:
        hooks = None if polar is None else PolarHooks(polar)
    except (TypeError, ValueError) as err:
        raise PolarInputError("settings", f"invalid PolarGS settings ({err})") from None
    try:
        return (trainer_class or Trainer)(list(views), config, hooks=hooks, init_points=init_points)
    except ValueError as err:
        raise PolarInputError("settings", str(err)) from None


def _remove_if_empty(out: Path) -> None:
    with contextlib.suppress(OSError):
        out.rmdir()  # only succeeds when empty: a folder this run created and left unused


def _check_resume_state(request: TrainRequest, checkpoint: Path) -> None:
    if checkpoint.exists() and not request.resume:
        raise PolarInputError(checkpoint, "exists; pass --resume to continue it or choose another --out")
    if request.resume and not checkpoint.exists():
        raise PolarInputError(checkpoint, "--resume given but the file does not exist")


def _check_same_data(request: TrainRequest, prints: dict[str, Any], notify: Notify) -> None:
    """On ``resume``: refuse data other than the run's (its fingerprint.json)."""
    path = request.out / FINGERPRINT_NAME
    stored = read_fingerprint(path)
    if stored is None:
        notify(f"note: {path}: missing (an older run); only the view names are checked")
        return
    problem = compare_fingerprints(stored, prints)
    if problem is not None:
        raise PolarInputError(path, f"--resume on other data than {request.dataset} was: {problem}; "
                              "resume with the original data or choose another --out")


@dataclass
class _Progress:
    """Where a run is, for the cleanup of an error or an interruption.

    Attributes:
        stage: before, during or after training.
        trainer: the trainer once built.
        wrote_fingerprint: this run wrote fingerprint.json.
        discarded: an error left nothing to resume, and what this run wrote was removed.
        estimate: the memory and time estimate printed before training.
    """

    stage: str = "before training started"
    trainer: Any = None
    wrote_fingerprint: bool = False
    discarded: bool = False
    estimate: RunEstimate | None = None


def _discard_untrained(out: Path, checkpoint: Path, maps_existed: bool, progress: _Progress) -> bool:
    """After an error: when there is no checkpoint to resume, remove what this run wrote (its
    fingerprint.json, the maps/ cache it created) and return True; else keep everything."""
    if checkpoint.is_file():
        return False
    if progress.wrote_fingerprint:
        with contextlib.suppress(OSError):
            (out / FINGERPRINT_NAME).unlink()
    if not maps_existed:
        shutil.rmtree(out / MAPS_NAME, ignore_errors=True)
    progress.discarded = True
    return True


def _write_failed(err: OSError, out: Path, checkpoint: Path, discarded: bool) -> PolarInputError:
    """A failed write or read (a full disk: :func:`~polargs_plugin.io.atomic_torch_save` reports
    torch's too as OSError) as one line that says what is kept."""
    problem = err.strerror or str(err)
    if discarded:
        problem += "; nothing of this run is kept"
    elif checkpoint.is_file():
        problem += f"; {checkpoint} keeps the last checkpoint (resume with --resume once there is room)"
    return PolarInputError(err.filename or out, problem)


def train_run(request: TrainRequest, notify: Notify = _ignore, stop: StopRequest | None = None) -> TrainResult:
    """Train ``request.dataset`` into the run folder ``request.out``.

    Args:
        request: what to train and where.
        notify: receives one-line notes for the user (the data read, the maps reused, a stale
            lock taken over); nothing is printed here.
        stop: the stop request a signal handler sets (see :class:`StopRequest`).

    Raises:
        PolarInputError: bad input, naming the file or setting, or a failed write (a full disk),
            naming the file and saying what is kept. When no checkpoint is left to resume,
            what the run wrote (fingerprint.json, the maps/ it created, a folder it created) is
            removed; an existing checkpoint is never touched.
        TrainingDiverged: a non-finite loss or parameter (the last periodic checkpoint stays).
        TrainingInterrupted: a stop request; the checkpoint to resume from is written when possible.
    """
    out = Path(request.out)
    checkpoint = out / CHECKPOINT_NAME
    created = not out.exists()
    maps_existed = (out / MAPS_NAME).exists()
    stop = stop or StopRequest()
    progress = _Progress()
    lock = None
    try:
        check_writable(out)
        lock = FolderLock(out / LOCK_NAME, command=request.command)
        lock.acquire()
        if lock.note:
            notify(f"note: {lock.note}")
        for name in (CHECKPOINT_NAME, FINGERPRINT_NAME, SUMMARY_NAME):  # left by a writer killed mid-write
            remove_stale_temporaries(out / name)
        _check_resume_state(request, checkpoint)
        dataset = load_dataset(request.dataset, request.reader)
        figures, every, start = _train(request, dataset, checkpoint, stop, progress, notify)
    except KeyboardInterrupt:
        raise _interrupted(request, stop, progress, checkpoint, created) from None
    except (PolarInputError, OSError) as err:
        # what this run wrote, never what the run of another process (holding the lock) did
        discarded = lock is not None and lock.held and _discard_untrained(out, checkpoint, maps_existed, progress)
        if isinstance(err, PolarInputError):
            raise
        raise _write_failed(err, out, checkpoint, discarded) from None
    finally:
        if lock is not None:
            lock.release()
            if created and (progress.stage == "before training started" or progress.discarded):
                _remove_if_empty(out)
    summary = _summary(request, dataset, figures, every, time.perf_counter() - start, progress.estimate)
    try:
        with atomic_write(out / SUMMARY_NAME) as handle:
            json.dump(summary, handle, indent=2)
    except OSError as err:
        raise PolarInputError(out / SUMMARY_NAME, f"cannot write ({err.strerror or err}); the checkpoint is saved") from None
    return TrainResult(out, summary, dataset)


def _train(request: TrainRequest, dataset: Dataset, checkpoint: Path, stop: StopRequest, progress: _Progress,
           notify: Notify) -> tuple[dict[str, Any], int, float]:
    """Check the data, build the trainer, resume, train: (figures, checkpoint interval, start time)."""
    if dataset.pattern:
        evidence = ", ".join(f"{100 * v:.0f} %" for v in list(dataset.colour_evidence.values())[:4] if v is not None)
        how = "given" if request.reader.pattern not in (None, "auto") else "told from the frames"
        notify(f"raw mosaics: {dataset.pattern} ({how}; Bayer colour structure in {evidence or '-'} of bright blocks)")
    if dataset.sfm_model:
        took = "" if dataset.sfm_seconds is None else f" in {dataset.sfm_seconds:.0f} s"
        notify(f"SfM: model written to {dataset.sfm_model}{took}")
    # the maps get a cache folder below (prepare_maps_cache), which hosts Dense's per-view state
    estimate = progress.estimate = estimate_memory(dataset.views, request.train, request.polar, maps_folder=True)
    notify(estimate.memory_line())
    if request.memory_check and not estimate.fits:
        raise PolarInputError(request.dataset, estimate.refusal())
    prints = fingerprint(dataset.views)
    if request.resume:
        _check_same_data(request, prints, notify)
    polar = request.polar
    if polar is not None:
        cache = prepare_maps_cache(dataset.views, polar, request.out, request.maps_cache, request.dataset)
        polar.cache_dir = os.path.abspath(cache.folder)  # recorded in summary.json: valid from any folder
    trainer = progress.trainer = build_trainer(dataset.views, request.train, polar)
    if polar is not None:
        notify(cache.describe())
    if request.resume:
        trainer.load_checkpoint(checkpoint)
    if trainer.iteration >= request.train.iterations:
        raise PolarInputError(checkpoint, f"already at iteration {trainer.iteration}; give a larger --iters to continue")
    estimate = progress.estimate = estimate_time(estimate, trainer, request.train.iterations)
    notify(estimate.time_line(request.train.iterations))
    every = checkpoint_interval(request.checkpoint_every, request.train.iterations)
    fingerprint_path = request.out / FINGERPRINT_NAME
    if not request.resume or not fingerprint_path.is_file():
        with atomic_write(fingerprint_path) as handle:
            json.dump({**prints, "dataset": dataset_location(request.dataset)}, handle)
        progress.wrote_fingerprint = True
    stop.arm(trainer)
    progress.stage = "during training"
    start = time.perf_counter()
    figures = trainer.train(checkpoint=checkpoint, checkpoint_every=every)
    progress.stage = "after training"
    rebuilt = trainer.hooks.maps.rebuilt if trainer.hooks is not None else {}
    if rebuilt:  # the maps line above counted the cache's files before they were read
        notify(f"maps: rebuilt {len(rebuilt)} of the cached views, their entries could not be used "
               f"({rebuilt_reasons(rebuilt)})")
    return figures, every, start


def _summary(request: TrainRequest, dataset: Dataset, figures: dict[str, Any], every: int,
             wall_seconds: float, estimate: RunEstimate | None) -> dict[str, Any]:
    polar = request.polar
    labels = dict(request.labels)
    config_file = labels.get("config_file")
    return {
        "dataset": dataset_location(request.dataset),
        "dataset_format": dataset.format,
        "reader": dataset.record(),
        "num_views": len(dataset.views),
        "image_size": dataset.image_size,
        "sfm_seconds": dataset.sfm_seconds,
        "polar": polar is not None,
        "schedule": labels.get("schedule"),
        "preset": labels.get("preset") if polar is not None else None,
        "switches": list(labels.get("switches", [])),
        "config_file": None if config_file is None else os.path.abspath(config_file),
        "resumed": bool(request.resume),
        "checkpoint": os.path.abspath(request.out / CHECKPOINT_NAME),
        "checkpoint_every": every,
        "maps_cache": None if polar is None else polar.cache_dir,
        "wall_seconds": wall_seconds,
        "peak_memory_bytes": peak_memory(),
        "estimate": None if estimate is None else {"peak_memory_bytes": estimate.peak_bytes, "seconds": estimate.seconds},
        **figures,
        "config": request.train.to_dict(),
        "polar_config": None if polar is None else polar.to_dict(),
        "provenance": provenance(request.command),
    }


def _interrupted(request: TrainRequest, stop: StopRequest, progress: _Progress, checkpoint: Path,
                 created: bool) -> TrainingInterrupted:
    """What a stop request leaves behind, as the exception to raise."""
    status, fresh, trainer = stop.exit_status, not request.resume, progress.trainer
    out = request.out
    if trainer is None or progress.stage != "during training" or (trainer.iteration == 0 and fresh):
        where = progress.stage if progress.stage != "during training" else "before the first iteration"
        if fresh:
            with contextlib.suppress(OSError):
                (out / FINGERPRINT_NAME).unlink()
            if created:
                _remove_if_empty(out)
        return TrainingInterrupted(status, f"interrupted {where}; nothing trained, no checkpoint written", False)
    if stop.hard:
        # stopped inside an iteration: its state may be half-updated, so it is not saved
        if checkpoint.is_file():
            return TrainingInterrupted(status, f"interrupted during iteration {trainer.iteration + 1}; {checkpoint} keeps "
                                       "the last periodic checkpoint", True)
        with contextlib.suppress(OSError):
            (out / FINGERPRINT_NAME).unlink()
        return TrainingInterrupted(status, f"interrupted during iteration {trainer.iteration + 1}, before the first "
                                   "periodic checkpoint; nothing to resume", False)
    try:
        trainer.save_checkpoint(checkpoint)
    except OSError as err:
        return TrainingInterrupted(status, f"error: {checkpoint}: interrupted at iteration {trainer.iteration} but the "
                                   f"checkpoint could not be written ({err.strerror or err})", False)
    return TrainingInterrupted(status, f"interrupted at iteration {trainer.iteration}", True)
