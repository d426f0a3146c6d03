"""An ablation cell as plain data: what one training run of a grid is, where its folders lie."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from polargs_plugin.ablation.scenes import SceneSpec
from polargs_plugin.ablation.variants import VARIANTS, variant_configs
from polargs_plugin.service.runs import SUMMARY_NAME

__all__ = ["Cell", "INITS", "PARTIAL_DIR", "is_done", "partial_dir"]

#: Initial points of a run: the visual hull of the masks, SfM points, uniform in the look-at cube.
INITS: tuple[str, ...] = ("hull", "sfm", "random")
#: ``<out>/.partial/<name>/``: the periodic training checkpoint of a run in progress.
PARTIAL_DIR = ".partial"


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
        command: the command line that made the grid, recorded in the run's provenance (None:
            the running process's). Not part of the run's identity.
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
    command: str | None = None

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
        the checkpoint cadence and the command line (a checkpoint is resumed only by a cell with
        the same fingerprint)."""
        data = self.to_dict()
        for key in ("out", "threads", "checkpoint_every", "command"):
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


def is_done(cell: Cell) -> bool:
    """Whether the cell's run folder exists (it is complete by construction)."""
    return (cell.run_dir / SUMMARY_NAME).is_file()


def partial_dir(cell: Cell) -> Path:
    """``<out>/.partial/<name>/``: where a run in progress keeps its periodic checkpoint."""
    return Path(cell.out) / PARTIAL_DIR / cell.name
