"""Reading a run's dataset: the reader options, what the reader found, and how to read it again."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from polargs_plugin.io import PolarInputError

if TYPE_CHECKING:
    from polargs_plugin.types import View

__all__ = ["ReaderOptions", "Dataset", "load_dataset", "dataset_location", "options_from_record", "SYNTHETIC_PREFIX",
           "PATTERNS", "DATASET_NOT_FOUND"]

#: ``synthetic:NAME`` names a bundled scene, rendered on the fly (24 views, 128x128).
SYNTHETIC_PREFIX = "synthetic:"
#: The problem :func:`load_dataset` reports for a path that does not exist.
DATASET_NOT_FOUND = "dataset not found"
#: Raw-mosaic patterns: mono (IMX250MZR), rgb (IMX250MYR), auto (told from the frames).
PATTERNS: tuple[str, ...] = ("auto", "mono", "rgb")
# How the command line spells each option, for messages about options that do not apply.
_FLAGS = {"pattern": "--pattern", "bit_depth": "--bit-depth", "sfm": "--sfm", "check_pattern": "--no-pattern-check",
          "resolution": "--resolution"}


@dataclass(frozen=True)
class ReaderOptions:
    """Options of the dataset readers, as ``polargs train`` takes them (docs/readers.md).

    Attributes:
        fmt: dataset format (``polargs``, ``neisf``, ``pandora``, ``nersp``, ``polar``) or
            ``"auto"`` (default): detected from the folder's files.
        pattern: raw mosaics of a polar folder: ``"mono"`` (IMX250MZR), ``"rgb"`` (IMX250MYR) or
            ``"auto"`` (told from the frames); None (default): the reader's default, auto.
        bit_depth: significant bits of integer images, e.g. 12 for 12-bit data in 16-bit files;
            None (default): the file's dtype, 8 or 16.
        sfm: a polar folder without a COLMAP model runs SfM (pycolmap) and writes ``sparse/0``
            (default False: a missing model is an error).
        check_pattern: check a given ``pattern`` against every frame (default True).
        resolution: the size training reads the images at, as the upstream trainers' ``-r``:
            1 (default), 2, 4 or 8 divide the width and height; a number above 8 is a target
            width. Images are area-averaged, masks and ground-truth maps sampled at the new
            pixel centres, K scaled with them (:mod:`polargs_plugin.data.resolution`); every
            dataset format, bundled scenes included.
    """

    fmt: str = "auto"
    pattern: Literal["auto", "mono", "rgb"] | None = None
    bit_depth: int | None = None
    sfm: bool = False
    check_pattern: bool = True
    resolution: int = 1

    def reader_kwargs(self) -> dict[str, Any]:
        """The options that differ from the defaults, as the readers' keyword arguments (no ``fmt``)."""
        given: dict[str, Any] = {}
        if self.pattern is not None:
            given["pattern"] = self.pattern
        if self.bit_depth is not None:
            given["bit_depth"] = self.bit_depth
        if self.sfm:
            given["sfm"] = True
        if not self.check_pattern:
            given["check_pattern"] = False
        if self.resolution != 1:
            given["resolution"] = self.resolution
        return given

    def to_dict(self) -> dict[str, Any]:
        """The options that differ from the defaults (``ReaderOptions(**d)`` gives them back)."""
        return {**({"fmt": self.fmt} if self.fmt != "auto" else {}), **self.reader_kwargs()}


@dataclass
class Dataset:
    """The views of a dataset and what the reader found reading them.

    Attributes:
        spec: the dataset as given: a folder, or ``synthetic:NAME``.
        views: the training views, in the project's conventions (docs/conventions.md).
        format: the format read (``synthetic`` for a bundled scene).
        options: the reader options used.
        pattern: a polar folder's raw-mosaic pattern (``mono`` / ``rgb``), None for other data.
        colour_evidence: for raw mosaics, the share of bright blocks with Bayer colour structure
            per frame that the pattern detection measured.
        sfm_model: the COLMAP model SfM wrote (None when no SfM ran).
        sfm_seconds: SfM's wall time (None when no SfM ran).
    """

    spec: str
    views: list[View]
    format: str
    options: ReaderOptions = field(default_factory=ReaderOptions)
    pattern: str | None = None
    colour_evidence: dict[str, float | None] = field(default_factory=dict)
    sfm_model: str | None = None
    sfm_seconds: float | None = None

    def record(self) -> dict[str, Any]:
        """The reader options that read the same views again, for a run's ``summary.json``:
        ``load_dataset(summary["dataset"], ReaderOptions(**summary["reader"]))``. The detected
        pattern is recorded; SfM is not (its model now lies in the dataset folder)."""
        record: dict[str, Any] = {}
        if self.format != "synthetic" and self.options.fmt != "auto":
            record["fmt"] = self.options.fmt
        if self.pattern is not None:
            record["pattern"] = self.pattern
        if self.options.bit_depth is not None:
            record["bit_depth"] = self.options.bit_depth
        if not self.options.check_pattern:
            record["check_pattern"] = False
        if self.options.resolution != 1:
            record["resolution"] = self.options.resolution
        return record

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(W, H) of the views when they all share one size, else None."""
        sizes = {(view.width, view.height) for view in self.views}
        return next(iter(sizes)) if len(sizes) == 1 else None


def load_dataset(spec: str, options: ReaderOptions | None = None) -> Dataset:
    """The views of ``spec``: a dataset folder (format detected) or ``synthetic:NAME``.

    Args:
        spec: a dataset folder in any supported format, or ``synthetic:NAME`` for a bundled scene.
        options: reader options (default: none given). For a polar folder with raw mosaics the
            pattern defaults to ``auto``. An option the dataset's reader does not take is an error.

    Raises:
        PolarInputError: naming the dataset: not found, unknown format or scene, an option that
            does not apply, no views, or the reader's own one-line errors.
    """
    options = options or ReaderOptions()
    _check_resolution(options.resolution)
    if spec.startswith(SYNTHETIC_PREFIX):
        return _load_synthetic(spec, options)
    path = Path(spec)
    if not path.exists():
        raise PolarInputError(path, DATASET_NOT_FOUND)
    from polargs_plugin.data.registry import FORMATS, detect_format, load_views, reader_options

    if options.fmt != "auto" and options.fmt not in FORMATS:
        raise PolarInputError(path, f"--format {options.fmt}: unknown format (known: auto, {', '.join(FORMATS)})")
    fmt = detect_format(path) if options.fmt == "auto" else options.fmt
    kwargs = options.reader_kwargs()
    known = reader_options(fmt)
    unknown = [k for k in kwargs if k not in known]
    if unknown:
        flags = ", ".join(_FLAGS[k] for k in unknown)
        raise PolarInputError(path, f"{flags}: only for polar folders (images or raw mosaics with a COLMAP model); this is a {fmt} dataset")
    info: dict[str, Any] = {}
    if "info" in known:
        kwargs.setdefault("pattern", "auto")
        kwargs["info"] = info
    views = load_views(path, fmt, **kwargs)
    if not views:
        raise PolarInputError(spec, "the dataset holds no views")
    return Dataset(spec=spec, views=views, format=fmt, options=options, pattern=info.get("pattern"),
                   colour_evidence=dict(info.get("colour_evidence") or {}),
                   sfm_model=str(info["model"]) if info.get("sfm") and info.get("model") else None,
                   sfm_seconds=info.get("sfm_seconds"))


def _check_resolution(resolution: int) -> None:
    from polargs_plugin.data.resolution import check_resolution

    try:
        check_resolution(resolution)
    except ValueError as err:
        raise PolarInputError(f"--resolution {resolution}", str(err)) from None


def _load_synthetic(spec: str, options: ReaderOptions) -> Dataset:
    from polargs_plugin.data.resolution import prepare_view
    from polargs_plugin.data.synthetic import SCENE_NAMES, generate_scene

    given = {k: v for k, v in options.reader_kwargs().items() if k != "resolution"}
    if given:
        flags = ", ".join(_FLAGS[k] for k in given)
        raise PolarInputError(spec, f"{flags} apply to dataset folders, not to a bundled synthetic scene")
    name = spec[len(SYNTHETIC_PREFIX):]
    if name not in SCENE_NAMES:
        raise PolarInputError(spec, f"unknown synthetic scene '{name}' (known: {', '.join(SCENE_NAMES)})")
    views = generate_scene(name, num_views=24, width=128, height=128).views
    if options.resolution != 1:  # at full size the rendered views stay as they are (float32, 1.5 MB)
        views = [prepare_view(view, options.resolution) for view in views]
    return Dataset(spec=spec, views=views, format="synthetic", options=options)


def dataset_location(spec: str) -> str:
    """How a run folder records its dataset: an absolute path (a relative one would name other
    data when read from another folder), or ``synthetic:NAME`` as it is."""
    return spec if spec.startswith(SYNTHETIC_PREFIX) else os.path.abspath(spec)


def options_from_record(record: dict[str, Any]) -> ReaderOptions:
    """The :class:`ReaderOptions` of a ``summary.json`` ``reader`` entry (see :meth:`Dataset.record`)."""
    known = set(asdict(ReaderOptions()))
    unknown = sorted(set(record) - known)
    if unknown:
        raise ValueError(f"unknown reader option(s) {', '.join(unknown)}")
    return ReaderOptions(**record)
