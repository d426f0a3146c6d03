"""Where the cells of an ablation grid run: this machine's process pool (``--executor local``,
:func:`polargs_plugin.ablation.grid.run_grid`, one run per visible GPU) or a cluster through
submitit (``--executor submitit``: one Slurm job array for the grid; docs/cluster.md).

Every executor runs the same function on the same plain data (:func:`~polargs_plugin.ablation.cell.run_cell`
on a :class:`~polargs_plugin.ablation.cell.Cell`), which writes the same run folder, so the
gather step (which reads run folders only) mixes local and cluster results in one table.

Bookkeeping of the cluster jobs: ``<out>/jobs.json`` (written atomically, under a lock) maps each
cell to the job that runs or ran it (job id, cluster, log paths, earlier job ids). A cell's state
(:func:`grid_status`) comes from the files and, for a recorded job, from submitit's view of it:

- ``done``: its run folder exists;
- ``running``: its job is pending / running / requeued (for a Slurm job whose state sacct does not
  know, as long as the job has left no result: it may just have been submitted);
- ``failed``: ``<out>/logs/<name>.log`` exists (run_cell's failure log), or its job ended without a
  run folder (killed: out of memory, cancelled, node failure; the log is then submitit's);
- ``missing``: none of the above (never submitted, or interrupted outside a job).

A resubmission submits the missing cells only; ``--retry-failed`` submits the failed ones only.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence, TextIO

from polargs_plugin.ablation.cell import Cell, CellFailed, is_done, mark_interrupted, read_summary, run_cell
from polargs_plugin.ablation.resume import PARTIAL_DIR, PARTIAL_STATE
from polargs_plugin.service.runs import SUMMARY_NAME

__all__ = [
    "JOBS_FILE", "SUBMITIT_DIR", "CLUSTERS", "CellJob", "CellStatus", "SubmititOptions", "SubmitResult",
    "ExecutorUnavailable", "grid_status", "format_status", "submit_grid", "wait_jobs", "visible_gpus",
    "require_submitit",
]

JOBS_FILE = "jobs.json"
JOBS_FORMAT = "polargs-ablation-jobs-v1"
SUBMITIT_DIR = "submitit"
CLUSTERS = ("auto", "slurm", "local", "debug")
STATES = ("done", "running", "failed", "missing")

#: Slurm states of a job that may still write its run folder.
_SLURM_ACTIVE = {"PENDING", "RUNNING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "CONFIGURING", "COMPLETING",
                 "SUSPENDED", "RESIZING", "SIGNALING", "STAGE_OUT", "STOPPED", "PREEMPTED", "READY", "UNKNOWN"}


class ExecutorUnavailable(RuntimeError):
    """The requested executor cannot run here (submitit missing, no Slurm, bad parameter)."""


def require_submitit():
    """The submitit module, or ExecutorUnavailable with the install command."""
    try:
        import submitit
    except ImportError:
        raise ExecutorUnavailable("--executor submitit needs the submitit package: pip install 'polargs_plugin[cluster]'") from None
    return submitit


# ------------------------------------------------------------------------------- the job
class CellJob:
    """What a submitit job runs: ``run_cell`` on one cell given as plain data (checkpointable).

    On preemption or timeout submitit calls :meth:`checkpoint` and requeues the job; the requeued
    job calls the same cell again and ``run_cell`` resumes from the run's own periodic checkpoint
    (``<out>/.partial/<name>/``), so nothing but the cell description needs to be pickled.

    Args:
        raise_failures: raise :class:`CellFailed` when the cell fails (the job is then FAILED for
            the scheduler, with the traceback in its log). False returns the failure as data
            (submitit's debug executor opens a debugger on an exception).
    """

    def __init__(self, raise_failures: bool = True):
        self.raise_failures = raise_failures

    def __call__(self, cell_data: dict[str, Any]) -> dict[str, Any]:
        cell = Cell.from_dict(cell_data)
        try:
            summary = run_cell(cell)
        except CellFailed as failure:
            print(f"error: {failure}", file=sys.stderr, flush=True)
            if self.raise_failures:
                raise
            return {"name": cell.name, "ok": False, "log": failure.log, "message": failure.message}
        print(f"done {cell.name}: {cell.run_dir}", flush=True)
        return {"name": cell.name, "ok": True, "run_dir": str(cell.run_dir), "figures": summary.get("figures")}

    def checkpoint(self, cell_data: dict[str, Any]):
        """submitit's preemption / timeout hook: the same call again (run_cell resumes by itself)."""
        from submitit.helpers import DelayedSubmission

        # the SystemExit that follows passes through run_cell as an interruption
        mark_interrupted(exit_code=_requeue_exit_code())
        return DelayedSubmission(self, cell_data)


def _requeue_exit_code() -> int:
    """The status with which submitit's handler ends a job it requeues: the local executor's own
    code (its controller requeues on it), else -1 (Slurm requeues through scontrol before the exit)."""
    import submitit
    from submitit.local.local import LOCAL_REQUEUE_RETURN_CODE

    return LOCAL_REQUEUE_RETURN_CODE if submitit.JobEnvironment().cluster == "local" else -1


# ----------------------------------------------------------------------------- jobs.json
class _JobStore:
    """``<out>/jobs.json`` under an exclusive lock (``<out>/.jobs.lock``)."""

    def __init__(self, out: Path):
        self.out = Path(out)
        self.path = self.out / JOBS_FILE

    @contextlib.contextmanager
    def locked(self) -> Iterator[dict[str, Any]]:
        """The store's data; written back (atomically) when the block ends without an error."""
        self.out.mkdir(parents=True, exist_ok=True)
        with open(self.out / ".jobs.lock", "a") as lock:
            with contextlib.suppress(ImportError, OSError):
                import fcntl

                fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            data = self.read()
            before = json.dumps(data, sort_keys=True)
            yield data
            if json.dumps(data, sort_keys=True) != before:
                from polargs_plugin.io import atomic_write

                with atomic_write(self.path) as handle:
                    json.dump(data, handle, indent=2)

    def read(self) -> dict[str, Any]:
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            data = {}
        except ValueError as err:
            raise ExecutorUnavailable(f"{self.path}: not readable JSON ({err}); fix or delete it") from None
        data.setdefault("format", JOBS_FORMAT)
        data.setdefault("cells", {})
        data.setdefault("submissions", [])
        return data


# --------------------------------------------------------------------------------- status
@dataclass
class CellStatus:
    """One cell's state (``done`` / ``running`` / ``failed`` / ``missing``), with where to look."""

    name: str
    state: str
    log: str | None = None
    job_id: str | None = None
    job_state: str | None = None
    note: str | None = None
    cell: dict[str, Any] | None = None


def _job_state(entry: dict[str, Any], slurm_jobs: dict[str, Any]) -> tuple[bool, str]:
    """(active, state) of a recorded job, from submitit (sacct for Slurm) and the job's files."""
    cluster, job_id = entry.get("cluster"), str(entry.get("job_id"))
    result = Path(entry.get("result") or "/nonexistent")
    if cluster == "slurm":
        job = slurm_jobs.get(job_id)
        state = "UNKNOWN" if job is None else str(job.state)
        state = state.split()[0] if state else "UNKNOWN"  # "CANCELLED by 123"
        if state == "UNKNOWN" and result.exists():
            return False, "ENDED"
        return state in _SLURM_ACTIVE, state
    if cluster == "local":  # the job id is the pid of submitit's controller process on this host
        if result.exists():
            return False, "FINISHED"
        if entry.get("host") not in (None, _host()):
            return True, "UNKNOWN (other host)"
        return (True, "RUNNING") if _controller_alive(int(job_id)) else (False, "ENDED")
    return False, "ENDED"  # debug jobs run inside the submitting process


def _controller_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError, OverflowError, ValueError):
        return False
    with contextlib.suppress(OSError):
        if "\nState:\tZ" in Path(f"/proc/{pid}/status").read_text():
            return False
        return b"submitit" in Path(f"/proc/{pid}/cmdline").read_bytes()
    return True


def _host() -> str:
    import platform

    return platform.node()


def _slurm_jobs(entries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """submitit SlurmJob objects of the active-looking Slurm entries (one sacct call for all)."""
    ids = [(e["folder"], str(e["job_id"])) for e in entries if e.get("cluster") == "slurm"]
    if not ids:
        return {}
    try:
        submitit = require_submitit()
    except ExecutorUnavailable:
        return {}
    return {job_id: submitit.SlurmJob(folder=folder, job_id=job_id) for folder, job_id in ids}


def grid_status(out: str | os.PathLike, cells: Sequence[Cell] | None = None, jobs: dict[str, Any] | None = None) -> list[CellStatus]:
    """The state of every cell of ``out``: ``cells`` (default: those of ``<out>/grid.json``, of
    ``<out>/jobs.json``, and every run folder / failure log / partial run found)."""
    out = Path(out)
    if jobs is None:
        jobs = _JobStore(out).read()
    entries: dict[str, dict[str, Any]] = jobs.get("cells", {})
    known: dict[str, dict[str, Any] | None] = {}
    if cells is not None:
        known.update({c.name: c.to_dict() for c in cells})
    else:
        with contextlib.suppress(OSError, ValueError, KeyError):
            for data in json.loads((out / "grid.json").read_text())["cells"]:
                known[Cell.from_dict(data).name] = data
        for name, entry in entries.items():
            known.setdefault(name, entry.get("cell"))
        if out.is_dir():
            for folder in out.iterdir():
                if not folder.name.startswith(".") and (folder / SUMMARY_NAME).is_file():
                    known.setdefault(folder.name, None)
        for path in sorted(out.glob("logs/*.log")):
            known.setdefault(path.name[: -len(".log")], None)
        for path in sorted(out.glob(f"{PARTIAL_DIR}/*")):
            known.setdefault(path.name, None)
    slurm = _slurm_jobs([entries[n] for n in known if n in entries and not (out / n / SUMMARY_NAME).is_file()])
    statuses = []
    for name, data in known.items():
        entry = entries.get(name)
        job_id = None if entry is None else str(entry.get("job_id"))
        run_dir, fail_log = out / name, out / "logs" / f"{name}.log"
        status = CellStatus(name, "missing", job_id=job_id, cell=data)
        if (run_dir / SUMMARY_NAME).is_file():
            status.state, status.log = "done", str(run_dir / "run.log")
            statuses.append(status)
            continue
        active, state = _job_state(entry, slurm) if entry else (False, None)
        status.job_state = state
        if active:
            status.state, status.log = "running", entry.get("stdout")
        elif fail_log.is_file():
            status.state, status.log = "failed", str(fail_log)
            status.note = _last_line(fail_log, "FAILED: ")
        elif entry is not None:
            status.state, status.log = "failed", entry.get("stderr")
            status.note = f"job {job_id} ended ({state}) without a run folder or a failure log"
        partial = out / PARTIAL_DIR / name / PARTIAL_STATE
        if status.state in ("running", "missing") and partial.is_file():
            with contextlib.suppress(OSError, ValueError, KeyError):
                status.note = f"checkpoint at iteration {json.loads(partial.read_text())['iteration']}"
        statuses.append(status)
    return statuses


def _last_line(path: Path, prefix: str) -> str | None:
    with contextlib.suppress(OSError):
        for line in reversed(path.read_text(errors="replace").splitlines()):
            if line.startswith(prefix):
                return line[len(prefix):].strip()
    return None


def format_status(statuses: Sequence[CellStatus]) -> str:
    """A table of the states (one line per cell) and a count line."""
    if not statuses:
        return "no cells (no grid.json, jobs.json, run folders or logs here)"
    width = max(len(s.name) for s in statuses)
    jobw = max([len(s.job_id or "-") for s in statuses] + [3])
    lines = [f"{'state':8s} {'cell':{width}s} {'job':{jobw}s} log"]
    order = {state: i for i, state in enumerate(("failed", "running", "missing", "done"))}
    for s in sorted(statuses, key=lambda s: (order[s.state], s.name)):
        job = s.job_id or "-"
        extra = []
        if s.job_state and s.state != "done":
            extra.append(s.job_state)
        if s.note:
            extra.append(s.note)
        lines.append(f"{s.state:8s} {s.name:{width}s} {job:{jobw}s} {s.log or '-'}" + (f"  ({'; '.join(extra)})" if extra else ""))
    counts = {state: sum(s.state == state for s in statuses) for state in STATES}
    lines.append(f"{len(statuses)} cells: " + ", ".join(f"{counts[state]} {state}" for state in STATES))
    return "\n".join(lines)


# ------------------------------------------------------------------------------ submission
@dataclass
class SubmititOptions:
    """``--executor submitit`` settings (None: the cluster's default)."""

    cluster: str = "auto"
    partition: str | None = None
    gpus_per_task: int | None = None  # None: 1 on Slurm, 0 elsewhere
    cpus_per_task: int | None = None  # None: the cells' threads
    timeout_min: int = 240
    mem_gb: float | None = None
    array_parallelism: int | None = None
    additional_parameters: dict[str, Any] = field(default_factory=dict)
    setup: list[str] = field(default_factory=list)
    max_requeue: int = 3
    name: str = "polargs-ablate"


@dataclass
class SubmitResult:
    """What :func:`submit_grid` did."""

    cluster: str
    submitted: list[tuple[Cell, Any]] = field(default_factory=list)  # (cell, submitit Job)
    skipped: dict[str, list[str]] = field(default_factory=dict)  # state -> cell names left alone

    @property
    def array_id(self) -> str | None:
        if not self.submitted:
            return None
        return str(self.submitted[0][1].job_id).split("_")[0]


def _executor(out: Path, options: SubmititOptions, threads: int):
    submitit = require_submitit()
    cluster = None if options.cluster in (None, "auto") else options.cluster
    try:
        executor = submitit.AutoExecutor(folder=out / SUBMITIT_DIR, cluster=cluster,
                                         slurm_max_num_timeout=options.max_requeue)
    except RuntimeError as err:  # "Could not detect srun"
        raise ExecutorUnavailable(f"--submitit-cluster {options.cluster}: {err}") from None
    name = executor.cluster
    gpus = options.gpus_per_task if options.gpus_per_task is not None else (1 if name == "slurm" else 0)
    params: dict[str, Any] = {"name": options.name, "timeout_min": int(options.timeout_min),
                              "cpus_per_task": int(options.cpus_per_task or threads), "tasks_per_node": 1, "nodes": 1}
    if options.mem_gb is not None:
        params["mem_gb"] = options.mem_gb
    if name == "slurm":
        if gpus:
            params["slurm_gpus_per_task"] = int(gpus)
        if options.partition:
            params["slurm_partition"] = options.partition
        if options.array_parallelism:
            params["slurm_array_parallelism"] = int(options.array_parallelism)
        if options.additional_parameters:
            params["slurm_additional_parameters"] = dict(options.additional_parameters)
        if options.setup:
            params["slurm_setup"] = list(options.setup)
    elif name == "local" and gpus:
        params["gpus_per_node"] = int(gpus)
    try:
        executor.update_parameters(**params)
    except (ValueError, NameError, AssertionError) as err:
        raise ExecutorUnavailable(f"submitit parameters: {str(err).splitlines()[0]}") from None
    return executor, name


@contextlib.contextmanager
def _thread_env(threads: int) -> Iterator[None]:
    """Thread counts the jobs inherit (sbatch and submitit's local executor copy the environment)."""
    keys = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS")
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: str(max(1, threads)) for k in keys})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def submit_grid(cells: Sequence[Cell], options: SubmititOptions, retry_failed: bool = False) -> SubmitResult:
    """Submit the cells that need it as ONE job array; record the jobs in ``<out>/jobs.json``.

    Left alone: done cells, running cells (their job is still pending / running) and, unless
    ``retry_failed``, failed ones; with ``retry_failed`` only the failed ones are submitted.
    """
    outs = {c.out for c in cells}
    if len(outs) != 1:
        raise ValueError("submit_grid: the cells of one grid share one folder")
    out = Path(outs.pop())
    threads = max(c.threads for c in cells)
    executor, cluster = _executor(out, options, threads)
    result = SubmitResult(cluster)
    store = _JobStore(out)
    with store.locked() as jobs:
        selected = []
        for status, cell in zip(grid_status(out, cells, jobs), cells):
            wanted = "failed" if retry_failed else "missing"
            if status.state == wanted:
                selected.append(cell)
            else:
                result.skipped.setdefault(status.state, []).append(cell.name)
        if not selected:
            return result
        with _thread_env(threads):
            submitted = executor.map_array(CellJob(raise_failures=cluster != "debug"), [c.to_dict() for c in selected])
        now = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        jobs["submissions"].append({"time": now, "cluster": cluster, "retry_failed": retry_failed,
                                    "job_ids": [str(j.job_id) for j in submitted]})
        for cell, job in zip(selected, submitted):
            old = jobs["cells"].get(cell.name)
            history = [] if old is None else old.get("history", []) + [{k: old.get(k) for k in ("job_id", "cluster", "submitted")}]
            jobs["cells"][cell.name] = {
                "job_id": str(job.job_id), "cluster": cluster, "submitted": now, "host": _host(),
                "folder": str(executor.folder), "stdout": str(job.paths.stdout), "stderr": str(job.paths.stderr),
                "result": str(job.paths.result_pickle), "cell": cell.to_dict(), "history": history,
            }
            result.submitted.append((cell, job))
        if retry_failed:  # the failure logs describe the previous attempt: kept in logs/previous/
            stamp = now.replace(":", "")
            for cell in selected:
                if cell.log_path.is_file():
                    previous = cell.log_path.parent / "previous" / f"{cell.name}.{stamp}.log"
                    previous.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(cell.log_path, previous)
    return result


def wait_jobs(submitted: Sequence[tuple[Cell, Any]], stream: TextIO | None = None, poll_s: float = 1.0):
    """Wait for submitted jobs (debug jobs run here, one after the other); a line per finished job.

    Returns a :class:`~polargs_plugin.ablation.grid.GridResult` (finished / failed)."""
    from polargs_plugin.ablation.grid import GridResult, _finished_line

    stream = stream or sys.stderr
    result = GridResult()
    pending = list(submitted)
    while pending:
        still = []
        for cell, job in pending:
            try:
                finished = job.done()
            except Exception:  # noqa: BLE001 - a state query failing is not the job failing
                finished = False
            if not finished:
                still.append((cell, job))
                continue
            message = None
            try:
                value = job.result()
                if isinstance(value, dict) and not value.get("ok", True):
                    message = value.get("message")
            except Exception as err:  # noqa: BLE001 - the job's exception, as submitit reports it
                message = _job_error(err)
            if is_done(cell):
                summary = read_summary(cell.run_dir)
                result.finished.append((cell, summary))
                print(_finished_line(cell, summary), file=stream, flush=True)
            else:
                if cell.log_path.is_file():
                    log = str(cell.log_path)
                    message = _last_line(cell.log_path, "FAILED: ") or message
                else:
                    log = str(job.paths.stderr)
                message = message or f"job {job.job_id} ended without a run folder"
                result.failed.append((cell, log, message))
                print(f"FAILED  {cell.name}: {message} (log: {log})", file=stream, flush=True)
        pending = still
        if pending:
            time.sleep(poll_s)
    return result


def _job_error(err: BaseException) -> str:
    """One line from submitit's FailedJobError (the traceback's last line) or another error."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip() and not set(line.strip()) <= {"-"}]
    for line in reversed(lines):
        if "CellFailed: " in line:
            return line.split("CellFailed: ", 1)[1].strip()
    for line in reversed(lines):
        if not line.startswith(("You can check", "or at paths", "- /", "File ")):
            return line
    return type(err).__name__


# ------------------------------------------------------------------------------ local GPUs
def visible_gpus(spec: str | None = None, device: str | None = None) -> list[str]:
    """GPU ids for the local executor's workers (one ``CUDA_VISIBLE_DEVICES`` each).

    ``spec``: ``"0,1,3"`` (ids as this process sees them: entries of its own
    ``CUDA_VISIBLE_DEVICES`` when set), ``"none"``, or None: every visible GPU when CUDA is
    available and ``device`` is not ``cpu``."""
    if spec is not None and spec.strip().lower() in ("none", ""):
        return []
    if device is not None and not device.startswith("cuda"):
        return []
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    listed = [g.strip() for g in env.split(",") if g.strip()] if env is not None else None
    if spec is not None:
        ids = [g.strip() for g in spec.split(",") if g.strip()]
        if listed is None:
            return ids
        bad = [g for g in ids if not g.isdigit() or int(g) >= len(listed)]
        if bad:
            raise ValueError(f"--gpus: {', '.join(bad)} not among the {len(listed)} visible GPU(s) (CUDA_VISIBLE_DEVICES={env})")
        return [listed[int(g)] for g in ids]
    try:
        import torch

        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    except Exception:  # noqa: BLE001
        count = 0
    if listed is not None:
        return listed[:count]
    return [str(i) for i in range(count)]
