"""One grid cell of an ablation: its plain-data description and the run folder it publishes.

:func:`run_cell` is the only thing an executor calls (the local process pool, a submitit / Slurm
job: docs/ablation.md, docs/cluster.md): it trains, meshes, evaluates and writes the run folder
``<out>/<name>/`` atomically (everything goes to ``<out>/.tmp-<name>-<pid>/``, renamed at the end),
so a run folder is complete or absent. A failure leaves no run folder but
``<out>/logs/<name>.log`` (the run's output and the traceback) and raises :class:`CellFailed`.

The work inside the temporary folder is :func:`~polargs_plugin.ablation.pipeline.run_pipeline`.
Resuming (:mod:`polargs_plugin.ablation.resume`): training checkpoints periodically
(``Cell.checkpoint_every``) into the stable folder ``<out>/.partial/<name>/``; a run that is
interrupted (killed, preempted, timed out, Ctrl-C) keeps that folder and the next attempt resumes
from it, to the same run folder as an uninterrupted run's (timings aside). A run that *fails* (an
exception) discards it: after a fix the cell starts over; a failed write (OSError: a full disk)
keeps it, as the checkpoint it holds is intact. The folder is removed once the run folder is
published.

Run folder contents::

    summary.json      TrainConfig, PolarConfig, seed, init, timings, figures and the provenance
                      (library versions, commit, command line, machine, threads)
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
import json
import os
import platform
import shutil
import sys
import traceback
from pathlib import Path
from typing import Any, TextIO

from polargs_plugin.ablation.pipeline import now, run_pipeline
from polargs_plugin.ablation.resume import PARTIAL_LOG, Progress, is_interruption, mark_interrupted
from polargs_plugin.ablation.spec import Cell, is_done, partial_dir
from polargs_plugin.service.runs import SUMMARY_NAME

__all__ = ["Cell", "CellFailed", "run_cell", "is_done", "partial_dir", "read_summary", "mark_interrupted"]


class CellFailed(RuntimeError):
    """A cell failed; ``log`` holds its output and traceback."""

    def __init__(self, name: str, log: str, message: str):
        super().__init__(name, log, message)
        self.name, self.log, self.message = name, log, message

    def __str__(self) -> str:
        return f"{self.name}: {self.message} (log: {self.log})"


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
            print(f"started {now()} on {platform.node()} (pid {os.getpid()}, "
                  f"CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')})", flush=True)
            summary = run_pipeline(cell, tmp, report)
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
        if is_interruption(err):
            # not a failure: keep the periodic checkpoint (and this attempt's output) for the next attempt
            _save_log(log_file, tmp, partial / PARTIAL_LOG,
                      f"\nINTERRUPTED ({type(err).__name__}) at {now()}; the next attempt resumes "
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


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    text = text[0] if text else ""
    if isinstance(err, SystemExit):
        return text or f"exit status {err.code}"
    name = type(err).__name__
    return text if name in ("PolarInputError",) else f"{name}: {text}"


if __name__ == "__main__":  # run one cell from its JSON description: python -m polargs_plugin.ablation.cell CELL.json
    cell = Cell.from_dict(json.loads(Path(sys.argv[1]).read_text()))
    try:
        print(json.dumps(run_cell(cell)["figures"], indent=2))
    except CellFailed as failure:
        print(f"error: {failure}", file=sys.stderr)
        sys.exit(1)
