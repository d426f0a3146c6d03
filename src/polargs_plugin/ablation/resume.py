"""Interruption and resumption of a run in progress.

A run checkpoints periodically into ``<out>/.partial/<name>/`` (``checkpoint.pt`` + ``state.json``:
the curves so far and the cell's fingerprint). An interrupted attempt (killed, preempted, timed
out, Ctrl-C: :func:`mark_interrupted`) keeps that folder and the next attempt resumes from it
(:func:`resume`); the reference trainer's checkpoints resume bit-exactly, so the run folder is the
same as an uninterrupted run's (timings aside).
"""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path
from typing import Any, Callable

from polargs_plugin.ablation.spec import PARTIAL_DIR, Cell
from polargs_plugin.io import json_safe, write_json
from polargs_plugin.service.runs import CHECKPOINT_NAME

__all__ = ["PARTIAL_DIR", "PARTIAL_STATE", "PARTIAL_LOG", "Progress", "mark_interrupted", "is_interruption",
           "make_trainer", "resume", "final_loss", "plain"]

PARTIAL_STATE = "state.json"
PARTIAL_LOG = "attempts.log"

Progress = Callable[[str, int, int], None]  # (phase, done, total)

_INTERRUPTED = False
_EXIT_CODE: int | None = None  # the status the interrupting handler exits with (None: not known)


def mark_interrupted(interrupted: bool = True, exit_code: int | None = None) -> None:
    """Called by a job's preemption / timeout handler (submitit's ``checkpoint``) before it exits,
    or by a pool worker's signal handler: the ``SystemExit`` that follows, or whatever the
    interruption turns into (an import it breaks fails with ImportError), is an interruption (the
    partial checkpoint is kept and the exception passes through unchanged), not a failure.
    ``exit_code``: the status the handler ends the process with (a requeue's), with which the next
    training step ends the run if the handler's own exit was lost on the way.
    ``interrupted=False`` clears the mark (a pool worker before its next cell)."""
    global _INTERRUPTED, _EXIT_CODE
    _INTERRUPTED = interrupted
    _EXIT_CODE = exit_code if interrupted else None


def is_interruption(err: BaseException) -> bool:
    """Whether ``err`` ends the run as an interruption (Ctrl-C, or anything after :func:`mark_interrupted`)."""
    # after mark_interrupted, whatever ends the run comes from the scheduler's signal: the SystemExit
    # of a requeue, or submitit's UncompletedJobError when the job has timed out too often
    return isinstance(err, KeyboardInterrupt) or _INTERRUPTED


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
            if _INTERRUPTED:
                # the interruption's own exception was swallowed on the way (an `except ImportError`,
                # a finaliser, which drops what it raises): end the run as the handler was ending it,
                # so that a requeue still reads as one
                raise KeyboardInterrupt if _EXIT_CODE is None else SystemExit(_EXIT_CODE)
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


def make_trainer(views, config, polar_cfg, init_points, report: Progress):
    """A recording trainer (see :func:`_recording_trainer_class`) with the hooks of ``polar_cfg``."""
    from polargs_plugin.service.train import build_trainer

    trainer = build_trainer(views, config, polar_cfg, init_points, trainer_class=_recording_trainer_class())
    trainer.curve, trainer.resumes, trainer.report = [], [], report
    return trainer


def plain(data: Any) -> Any:
    """``data`` as it reads back from JSON."""
    return json.loads(json.dumps(json_safe(data)))


def resume(cell: Cell, trainer, partial: Path) -> bool:
    """Load ``partial``'s checkpoint into ``trainer`` when it is this cell's (else remove it and
    return False). Raises when the checkpoint is this cell's but cannot be loaded."""
    checkpoint, state_path = partial / CHECKPOINT_NAME, partial / PARTIAL_STATE
    if not checkpoint.is_file():
        return False
    try:
        state = json.loads(state_path.read_text())
    except (OSError, ValueError):
        state = {}
    if state.get("fingerprint") != plain(cell.fingerprint()):
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


def final_loss(curve: list[dict[str, float]], log_every: int) -> float | None:
    """The trainer's final ``loss`` figure (mean over the iterations since the last multiple of
    ``log_every``), from the curves: identical for a resumed and an uninterrupted run."""
    if not curve:
        return None
    end = int(curve[-1]["iteration"])
    start = ((end - 1) // max(1, log_every)) * max(1, log_every)
    values = [row["loss"] for row in curve if row["iteration"] > start]
    return float(sum(values) / len(values)) if values else None
