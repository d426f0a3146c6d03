"""`polargs ablate --executor submitit` without a cluster: submitit's debug executor (in this
process) and local executor (a process per job), resubmission, --retry-failed, --status, and a
preempted job that resumes from its periodic checkpoint (docs/cluster.md).

Tiny runs (6 views of 32 px, 60 iterations, <= 800 Gaussians; five in this process, one as a
submitit job in two attempts): about 75 s on 2 cores shared with a load of 8, far less when idle.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import sys
import time
from pathlib import Path

import pytest

from polargs_plugin.ablation import cell as cell_module
from polargs_plugin.ablation import resume as resume_module
from polargs_plugin.ablation.cell import Cell
from polargs_plugin.ablation.executors import (
    CellStatus,
    SubmititOptions,
    _job_error,
    format_status,
    grid_status,
    submit_grid,
    visible_gpus,
    wait_jobs,
)
from polargs_plugin.ablation.grid import _init_worker
from polargs_plugin.cli import main
from polargs_plugin.service.runs import CHECKPOINT_NAME

SCENE = "glossy_plane_sphere"
TINY = ["--views", "6", "--size", "32x32", "--factor", "0.002", "--eval-samples", "20000",
        "--train-set", "num_init_points=300", "--train-set", "density.max_gaussians=800", "--quiet"]
DEBUG = ["--executor", "submitit", "--submitit-cluster", "debug"]
# training figures, and the mesh figures of a mesh written in canonical order (cell.canonical_mesh_order)
FIGURES = ("chamfer", "accuracy", "completeness", "fscore", "normal_mae_deg", "psnr", "loss", "iterations",
           "num_gaussians", "appended_total")


def _names(out: Path) -> set[str]:
    return {p.name for p in out.iterdir() if (p / "summary.json").is_file()}


# ------------------------------------------------------------------------------- no training
def test_missing_submitit_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "submitit", None)  # import submitit -> ImportError
    assert main(["ablate", "--scenes", SCENE, "--variants", "base", "--out", str(tmp_path / "a"), *DEBUG]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: --executor submitit needs the submitit package: pip install 'polargs_plugin[cluster]'"
    assert main(["ablate", "--scenes", SCENE, "--out", str(tmp_path / "a"), "--slurm-additional-parameters", "nokey"]) == 2
    assert "--slurm-additional-parameters: expected KEY=VALUE" in capsys.readouterr().err
    assert main(["ablate", "--status", str(tmp_path / "nope")]) == 2
    assert main(["ablate", "--scenes", SCENE]) == 2
    assert "--out: required" in capsys.readouterr().err


def test_gpu_assignment_and_helpers(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,6")
    assert visible_gpus("1") == ["6"] and visible_gpus("none") == [] and visible_gpus(None, "cpu") == []
    with pytest.raises(ValueError, match="not among the 2 visible"):
        visible_gpus("2")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert visible_gpus("0,3") == ["0", "3"]
    ids: queue.Queue = queue.Queue()
    ids.put("3")
    monkeypatch.setattr("polargs_plugin.ablation.grid._QUEUE", None)
    _init_worker(None, 1, ids)  # a pool worker takes its GPU before CUDA starts
    assert os.environ.pop("CUDA_VISIBLE_DEVICES") == "3"
    trace = ("Job (task=0) failed during processing with trace:\n----\nTraceback (most recent call last):\n"
             "polargs_plugin.ablation.cell.CellFailed: x__base__hull__s0: RuntimeError: boom (log: /o/logs/x.log)\n----\n"
             "You can check full logs with 'job.stderr(0)'")
    assert _job_error(RuntimeError(trace)) == "x__base__hull__s0: RuntimeError: boom (log: /o/logs/x.log)"
    table = format_status([CellStatus("a", "done", "/o/a/run.log"), CellStatus("b", "failed", "/o/logs/b.log", "12_1", "FAILED")])
    assert table.splitlines()[1].startswith("failed   b ") and "12_1" in table and table.endswith("2 cells: 1 done, 0 running, 1 failed, 0 missing")


# ---------------------------------------------------------------------------------- training
BAD = f"{SCENE}__reg__hull__s1"


def _grid_args(out: Path) -> list[str]:
    return ["ablate", "--scenes", SCENE, "--variants", "base,reg", "--seeds", "0,1", "--out", str(out), *TINY, *DEBUG]


@pytest.fixture(scope="module")
def debug_grid(tmp_path_factory):
    """A 2x2 grid (base, reg x seeds 0, 1) through submitit's debug executor, one cell raising:
    (folder, exit status, captured stdout + stderr)."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("debug") / "grid"
    real_run = cell_module.run_pipeline

    def flaky(cell, tmp, report):
        if cell.name == BAD:
            raise RuntimeError("injected failure")
        return real_run(cell, tmp, report)

    stdout, stderr = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        patch.setattr(cell_module, "run_pipeline", flaky)
        status = main(_grid_args(out))
    return out, status, stdout.getvalue(), stderr.getvalue()


@pytest.mark.slow
def test_debug_array_failure_resubmit_and_retry(debug_grid, monkeypatch, capsys):
    """One cell raises and is reported failed with its log, the rest finish; a resubmission runs
    nothing; after the fix --retry-failed runs only that cell."""
    out, status, stdout, stderr = debug_grid
    args, bad = _grid_args(out), BAD
    log = out / "logs" / f"{bad}.log"
    assert status == 1
    assert "3 run(s) finished, 0 skipped (already done), 1 failed" in stdout
    assert f"{bad}: RuntimeError: injected failure (log: {log})" in stderr
    assert "injected failure" in log.read_text() and "Traceback" in log.read_text()
    assert _names(out) == {f"{SCENE}__{v}__hull__s{s}" for v in ("base", "reg") for s in (0, 1)} - {bad}
    jobs = json.loads((out / "jobs.json").read_text())
    assert len(jobs["submissions"]) == 1 and len(jobs["submissions"][0]["job_ids"]) == 4  # one array
    assert {e["cluster"] for e in jobs["cells"].values()} == {"debug"}

    assert main(["ablate", "--status", str(out)]) == 0
    status = capsys.readouterr().out
    assert f"failed   {bad}" in status and str(log) in status and "injected failure" in status
    assert status.strip().endswith("4 cells: 3 done, 0 running, 1 failed, 0 missing")

    stamps = {p: p.stat().st_mtime_ns for p in out.glob("*/summary.json")}
    monkeypatch.setattr(cell_module, "run_pipeline", None)  # nothing may run
    assert main(args) == 1  # nothing new: the failed cell waits for --retry-failed
    captured = capsys.readouterr()
    assert "nothing to submit: 3 done, 1 failed (--retry-failed resubmits the failed ones)" in captured.err
    assert "1 failed (left alone)" in captured.out
    assert len(json.loads((out / "jobs.json").read_text())["submissions"]) == 1
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/summary.json")} == stamps

    monkeypatch.undo()  # the fix
    assert main([*args, "--retry-failed"]) == 0
    captured = capsys.readouterr()
    assert "1 run(s) finished, 3 skipped (already done), 0 failed" in captured.out
    jobs = json.loads((out / "jobs.json").read_text())
    assert len(jobs["submissions"]) == 2 and len(jobs["submissions"][1]["job_ids"]) == 1
    assert jobs["cells"][bad]["history"] and {p: p.stat().st_mtime_ns for p in out.glob("*/summary.json") if p in stamps} == stamps
    assert not log.exists() and list((out / "logs" / "previous").glob(f"{bad}.*.log"))
    assert main(["ablate", "--status", str(out)]) == 0
    assert capsys.readouterr().out.strip().endswith("4 cells: 4 done, 0 running, 0 failed, 0 missing")
    assert "| reg |" in (out / "results.md").read_text()


def test_a_lost_requeue_exit_ends_the_next_step_with_the_requeue_status():
    """When the preemption handler's own exit is swallowed on the way (a finaliser drops what it
    raises), the next training step ends the run with the status the handler was exiting with
    (submitit's local controller requeues on it), and without one known, as an interruption."""
    step = resume_module._recording_trainer_class().step
    try:
        resume_module.mark_interrupted(exit_code=144)
        with pytest.raises(SystemExit) as exit_info:
            step(None)  # raises before touching the trainer
        assert exit_info.value.code == 144
        assert resume_module.is_interruption(exit_info.value)
        resume_module.mark_interrupted()
        with pytest.raises(KeyboardInterrupt):
            step(None)
    finally:
        resume_module.mark_interrupted(False)
    assert resume_module._EXIT_CODE is None and not resume_module.is_interruption(SystemExit(144))


@pytest.mark.slow
def test_preempted_local_job_resumes_to_the_same_figures(debug_grid, tmp_path, capsys):
    """submitit's local executor: the job is preempted (USR2, as Slurm sends) after its first
    periodic checkpoint, requeued by submitit, resumes from the checkpoint and ends with the
    figures of an uninterrupted run of the same cell (the debug grid's, same seed)."""
    grid = debug_grid[0]
    reference = Cell.from_dict(json.loads((grid / f"{SCENE}__base__hull__s0" / "summary.json").read_text())["cell"])
    cell = Cell.from_dict({**reference.to_dict(), "out": str(tmp_path / "cluster"), "checkpoint_every": 1})
    expected = json.loads((reference.run_dir / "summary.json").read_text())["figures"]

    submitted = submit_grid([cell], SubmititOptions(cluster="local", timeout_min=60))
    (_, job), = submitted.submitted
    # state.json is written before the checkpoint (atomically renamed into place): wait for the
    # checkpoint, else the preemption can land between the two and the next attempt starts over
    checkpoint = cell.partial_dir / CHECKPOINT_NAME
    deadline = time.time() + 120
    while not checkpoint.is_file() and time.time() < deadline and not job.done():
        time.sleep(0.05)
    assert checkpoint.is_file(), job.stderr()
    # Frozen right after its first checkpoint, so that it cannot finish before the preemption below.
    task_pid, = {int(p.name.rsplit("-", 1)[1]) for p in Path(cell.out).glob(f".tmp-{cell.name}-*")}
    os.kill(task_pid, signal.SIGSTOP)
    status, = grid_status(cell.out)
    assert (status.state, status.job_id) == ("running", job.job_id) and status.cell["variant"] == "base"
    again = submit_grid([cell], SubmititOptions(cluster="local", timeout_min=60))
    assert not again.submitted and again.skipped == {"running": [cell.name]}  # not submitted twice
    # Slurm's preemption / timeout signal to the job's task (submitit's LocalJob._interrupt signals
    # the local controller, which does not forward it): checkpoint() + requeue, then a fresh attempt
    os.kill(task_pid, signal.SIGUSR2)
    os.kill(task_pid, signal.SIGCONT)

    result = wait_jobs(submitted.submitted, poll_s=0.2)
    assert result.ok and len(result.finished) == 1, job.stderr()
    summary = json.loads((cell.run_dir / "summary.json").read_text())
    assert summary["resumed_from"] and 0 < summary["resumed_from"][0] <= 60, summary["resumed_from"]
    assert summary["provenance"]["job"]["scheduler"] == "submitit-local"
    assert {k: summary["figures"][k] for k in FIGURES} == {k: expected[k] for k in FIGURES}
    assert (cell.run_dir / "curves.csv").read_text() == (reference.run_dir / "curves.csv").read_text()
    run_log = (cell.run_dir / "run.log").read_text()
    assert "INTERRUPTED" in run_log and "resume: loaded" in run_log
    assert "Requeued" in (job.paths.stdout.read_text() + job.paths.stderr.read_text())
    assert not (Path(cell.out) / ".partial").exists()
    assert main(["ablate", "--status", cell.out]) == 0
    assert f"done     {cell.name}" in capsys.readouterr().out


def test_slurm_array_submission_with_fake_slurm(tmp_path, monkeypatch, capsys):
    """The Slurm path without a cluster: fake srun / sbatch / sacct on PATH. One sbatch call for
    the grid (a job array with the requested options), jobs.json, running / failed states from
    sacct, and a resubmission that leaves running cells alone."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "sbatch_calls"
    sacct = tmp_path / "sacct_out"
    sacct.write_text("JobID|State|NodeList\n")
    for name, body in {
        "srun": "exit 0",
        "sbatch": f'cat "$1" >> {calls}; echo "Submitted batch job 4242"',
        "sacct": f"cat {sacct}",
    }.items():
        (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    out = tmp_path / "grid"
    args = ["ablate", "--scenes", f"mine={tmp_path}/data:{tmp_path}/gt.ply", "--variants", "base,reg", "--seeds", "0,1",
            "--out", str(out), "--executor", "submitit", "--slurm-partition", "gpu", "--gpus-per-task", "1",
            "--cpus-per-task", "8", "--timeout-min", "90", "--mem-gb", "32", "--slurm-array-parallelism", "2",
            "--slurm-additional-parameters", "account=proj", "qos=high", "--slurm-setup", "module load cuda"]
    assert main(args) == 0  # submits and returns (no --wait on Slurm)
    captured = capsys.readouterr()
    assert "submitted 4 cell(s) as job array 4242" in captured.err and f"polargs ablate --status {out}" in captured.out
    script = calls.read_text()
    assert script.count("#SBATCH --array=0-3%2") == 1  # ONE array for the grid
    for line in ("#SBATCH --partition=gpu", "#SBATCH --gpus-per-task=1", "#SBATCH --cpus-per-task=8", "#SBATCH --time=90",
                 "#SBATCH --mem=32GB", "#SBATCH --account=proj", "#SBATCH --qos=high", "module load cuda"):
        assert line in script, line
    jobs = json.loads((out / "jobs.json").read_text())["cells"]
    assert sorted(e["job_id"] for e in jobs.values()) == [f"4242_{i}" for i in range(4)]

    statuses = {s.name: s for s in grid_status(out)}
    assert {s.state for s in statuses.values()} == {"running"}  # sacct knows nothing yet: submitted
    first = jobs["mine__base__hull__s0"]["job_id"]
    sacct.write_text("JobID|State|NodeList\n4242_[1-3]|RUNNING|n1\n" + f"{first}|OUT_OF_MEMORY|n2\n")
    from submitit import SlurmJob

    SlurmJob.watcher.clear()
    statuses = {s.name: s for s in grid_status(out)}
    failed = statuses["mine__base__hull__s0"]
    assert (failed.state, failed.job_state, failed.log) == ("failed", "OUT_OF_MEMORY", jobs["mine__base__hull__s0"]["stderr"])
    assert sum(s.state == "running" for s in statuses.values()) == 3
    assert main(args) == 0
    assert "nothing to submit: 1 failed, 3 running (--retry-failed resubmits the failed ones)" in capsys.readouterr().err
    SlurmJob.watcher.clear()
    assert main([*args, "--retry-failed"]) == 0
    assert "submitted 1 cell(s)" in capsys.readouterr().err
    jobs = json.loads((out / "jobs.json").read_text())["cells"]
    assert jobs["mine__base__hull__s0"]["history"][0]["job_id"] == first
