"""A run folder written by ``polargs train`` (or a cell of ``polargs ablate``), and reading it back.

A run folder holds ``checkpoint.pt`` (resumable), ``fingerprint.json`` (what the run is trained
on), ``maps/`` (the PolarGS maps cache), ``summary.json`` (settings and final figures) and, while a
training runs, ``train.lock`` (docs/cli.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from polargs_plugin.io import PolarInputError
from polargs_plugin.service.data import DATASET_NOT_FOUND, Dataset, load_dataset, options_from_record
from polargs_plugin.service.fingerprints import compare_fingerprints, fingerprint, read_fingerprint

if TYPE_CHECKING:
    from polargs_plugin.backends.reference.model import GaussianModel

__all__ = ["CHECKPOINT_NAME", "SUMMARY_NAME", "FINGERPRINT_NAME", "LOCK_NAME", "MESH_NAME", "METRICS_NAME",
           "Run", "load_run", "read_summary"]

CHECKPOINT_NAME = "checkpoint.pt"
SUMMARY_NAME = "summary.json"
FINGERPRINT_NAME = "fingerprint.json"
LOCK_NAME = "train.lock"
MESH_NAME = "tsdf_mesh.ply"
METRICS_NAME = "metrics.json"


@dataclass
class Run:
    """A trained run, read back.

    Attributes:
        folder: the run folder.
        model: the trained Gaussians (on the CPU).
        dataset: the training views, read again as the run read them.
        summary: the run's ``summary.json``.
    """

    folder: Path
    model: "GaussianModel"
    dataset: Dataset
    summary: dict[str, Any]

    @property
    def views(self) -> list:
        return self.dataset.views


def read_summary(run_dir: Path) -> dict[str, Any]:
    """A run folder's ``summary.json``; PolarInputError naming the file when missing or not JSON."""
    path = Path(run_dir) / SUMMARY_NAME
    if not path.is_file():
        raise PolarInputError(path, "missing; is this a finished `polargs train` run folder?")
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise PolarInputError(path, f"unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(summary, dict):
        raise PolarInputError(path, "not a run summary (expected a JSON object)")
    return summary


def load_run(run_dir: str | Path, data: str | Path | None = None) -> Run:
    """The model and training views of a run folder.

    The views come from the dataset named in ``summary.json`` (or ``data``, the same dataset
    moved since), read with the reader options the run recorded (re-rendered for
    ``synthetic:NAME``); the Gaussians from ``checkpoint.pt``, whose view names must match the
    dataset's, and the cameras and images those of the run's ``fingerprint.json`` (when it has
    one), so a ``data`` that is not the run's dataset is refused.

    Raises:
        PolarInputError: naming the file: a missing or unreadable summary or checkpoint, a dataset
            that is no longer where the run recorded it (the message names ``--data``), or a
            dataset whose views are not the ones the run was trained on (other names, or other
            cameras or images under the same names).
    """
    from polargs_plugin.backends.reference.model import GaussianModel
    from polargs_plugin.backends.reference.trainer import read_checkpoint

    run_dir = Path(run_dir)
    summary_path, checkpoint_path = run_dir / SUMMARY_NAME, run_dir / CHECKPOINT_NAME
    for path in (summary_path, checkpoint_path):
        if not path.is_file():
            raise PolarInputError(path, "missing; is this a finished `polargs train` run folder?")
    summary = read_summary(run_dir)
    try:
        spec, options = str(summary["dataset"]), options_from_record(summary.get("reader") or {})
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise PolarInputError(summary_path, f"no dataset entry ({type(err).__name__}: {err})") from err
    spec = spec if data is None else str(data)
    checkpoint = read_checkpoint(checkpoint_path)
    try:
        dataset = load_dataset(spec, options)
    except PolarInputError as err:
        if data is not None or err.problem != DATASET_NOT_FOUND:
            raise
        raise PolarInputError(err.path, f"{DATASET_NOT_FOUND} (the one {summary_path} names); if it moved, give its "
                              "new place with --data NEW_PATH") from None
    if [v.name for v in dataset.views] != checkpoint["view_names"]:
        raise PolarInputError(checkpoint_path, f"was trained on other views than those of {spec}")
    _check_same_data(run_dir / FINGERPRINT_NAME, spec, dataset)
    return Run(run_dir, GaussianModel.from_checkpoint(checkpoint["model"]), dataset, summary)


def _check_same_data(path: Path, spec: str, dataset: Dataset) -> None:
    """Refuse a dataset whose cameras or images are not those of the run's fingerprint.json (other
    data under the same view names); a run without one (written before fingerprints) passes."""
    stored = read_fingerprint(path)
    if stored is None:
        return
    problem = compare_fingerprints(stored, fingerprint(dataset.views))
    if problem is not None:
        raise PolarInputError(path, f"{spec} is not the data this run was trained on: {problem}")
