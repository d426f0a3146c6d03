"""One check of a run's ``provenance`` record against what this process itself reports: the
modules' own versions, ``git rev-parse HEAD`` of the source tree, the cores and thread counts."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

import numpy as np
import torch

import polargs_plugin


def check_provenance(record: dict, *, command: str | None = None, threads: int | None = None) -> None:
    """Assert that ``record`` names this machine, these libraries, this source tree; ``command``
    (when given) is the command line it must hold and ``threads`` torch's thread count of the run."""
    versions = record["versions"]
    assert (versions["python"], versions["torch"], versions["numpy"]) == (
        platform.python_version(), torch.__version__, np.__version__)
    source = Path(polargs_plugin.__file__).resolve().parent
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=source, capture_output=True, text=True)
    assert record["git"]["commit"] == (head.stdout.strip() if head.returncode == 0 else None)
    machine = record["machine"]
    assert machine["host"] == platform.node() and machine["cores_available"] == len(os.sched_getaffinity(0))
    assert record["threads"]["environment"]["OMP_NUM_THREADS"] == os.environ.get("OMP_NUM_THREADS")
    if threads is not None:
        assert record["threads"]["torch"] == threads
    if command is not None:
        assert record["command"] == command
