"""Where a run's figures come from: library versions, source commit, command line, machine, threads.

Every run folder's ``summary.json`` carries :func:`provenance` under ``"provenance"`` (``polargs
train``, each ablation run, ``polargs dryrun``'s work folder). The same code and seed can train to
figures a seed's spread apart on two machines whose libraries or thread counts differ; these
fields say whether they did.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

__all__ = ["RECORDED_DISTRIBUTIONS", "provenance", "library_versions", "source_commit", "machine", "thread_counts",
           "job_info"]

#: The distributions whose versions a run records: the package and the libraries its figures
#: come from (training, PatchMatch, meshing, evaluation).
RECORDED_DISTRIBUTIONS: tuple[str, ...] = (
    "polargs_plugin", "torch", "numpy", "scipy", "numba", "kornia", "opencv-python-headless", "open3d",
)

#: The environment variables that set thread counts or OpenMP's behaviour before start-up.
THREAD_VARIABLES: tuple[str, ...] = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OMP_WAIT_POLICY")


def provenance(command: str | None = None) -> dict[str, Any]:
    """Everything below in one dict: ``versions``, ``git``, ``command`` (the command line that
    started the run, shell-quoted; by default this process's ``sys.argv``), ``machine``,
    ``threads`` and ``job`` (None outside a cluster job).

    >>> record = provenance("polargs train data --out runs/a")
    >>> sorted(record), record["command"]
    (['command', 'git', 'job', 'machine', 'threads', 'versions'], 'polargs train data --out runs/a')
    """
    return {
        "versions": library_versions(),
        "git": source_commit(),
        "command": shlex.join(sys.argv) if command is None else command,
        "machine": machine(),
        "threads": thread_counts(),
        "job": job_info(),
    }


def library_versions() -> dict[str, str | None]:
    """Python's version and the installed version of each of :data:`RECORDED_DISTRIBUTIONS`
    (None for one not installed as a distribution, e.g. the package run from a source tree on
    ``PYTHONPATH``)."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in RECORDED_DISTRIBUTIONS:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def source_commit() -> dict[str, Any]:
    """``{"commit", "dirty"}`` of the git checkout this package runs from (both None outside one)."""
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


def machine() -> dict[str, Any]:
    """Host name, operating system, processor and the cores this process may use."""
    from polargs_plugin.threads import available_cores

    return {"host": platform.node(), "system": platform.platform(), "processor": platform.processor() or None,
            "machine": platform.machine(), "cpu_count": os.cpu_count(), "cores_available": available_cores()}


def thread_counts() -> dict[str, Any]:
    """torch's intra-op threads, numba's threads (None where a library is not loaded: reading them
    would load it) and the thread variables of the environment."""
    torch, numba = sys.modules.get("torch"), sys.modules.get("numba")
    return {
        "torch": torch.get_num_threads() if torch is not None else None,
        "numba": numba.get_num_threads() if numba is not None else None,
        "environment": {name: os.environ.get(name) for name in THREAD_VARIABLES},
    }


def job_info() -> dict[str, Any] | None:
    """The cluster job this process runs in (Slurm, submitit's local or debug executor), or None."""
    env = os.environ
    if "SLURM_JOB_ID" in env:
        job = env.get("SLURM_ARRAY_JOB_ID")
        return {"scheduler": "slurm", "job_id": f"{job}_{env.get('SLURM_ARRAY_TASK_ID')}" if job else env["SLURM_JOB_ID"],
                "node": env.get("SLURMD_NODENAME")}
    for key, name in (("SUBMITIT_LOCAL_JOB_ID", "submitit-local"), ("SUBMITIT_DEBUG_JOB_ID", "submitit-debug")):
        if key in env:
            return {"scheduler": name, "job_id": env[key], "node": platform.node()}
    return None
