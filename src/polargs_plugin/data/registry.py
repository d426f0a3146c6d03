"""One entry point for every supported dataset: ``load_views(path)`` detects the format by its files.

Formats, in detection order (the first whose marker files exist wins):

========== ===================================================== ====================================
fmt        marker files                                          reader
========== ===================================================== ====================================
polargs    cameras.json (+ polar/)                               scene_format.read_scene_folder
neisf      poses_bounds.npy + images_s0/                         neisf.read_neisf
pandora    cameras.npz + images_stokes/*_s0.hdr                  pandora.read_pandora
nersp      cameras.npz + s0/*.npy (NeRSP or PolGS layout)        nersp.read_nersp
polar      <name>_0/45/90/135 images, 0/ 45/ 90/ 135/ or raw/    polar_folder.read_polar_folder
           (in the folder or in images/)
========== ===================================================== ====================================
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from pathlib import Path

from polargs_plugin.data.checks import warn_brightness_outliers
from polargs_plugin.data.neisf import read_neisf
from polargs_plugin.data.nersp import read_nersp
from polargs_plugin.data.pandora import read_pandora
from polargs_plugin.data.polar_folder import read_polar_folder
from polargs_plugin.data.scene_format import read_scene_folder
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View, validate_view

__all__ = ["FORMATS", "detect_format", "load_views", "reader_options"]


def _has_angle_images(folder: Path) -> bool:
    for root in (folder / "images", folder):
        if any((root / a).is_dir() for a in ("0", "45", "90", "135")):
            return True
        if root.is_dir() and any(p.stem.endswith("_0") for p in root.iterdir() if p.is_file()):
            return True
    return (folder / "raw").is_dir()


FORMATS: dict[str, tuple[str, Callable[[Path], bool], Callable[..., list[View]]]] = {
    "polargs": ("cameras.json", lambda f: (f / "cameras.json").is_file(), read_scene_folder),
    "neisf": (
        "poses_bounds.npy and images_s0/",
        lambda f: (f / "poses_bounds.npy").is_file() and (f / "images_s0").is_dir(),
        read_neisf,
    ),
    "pandora": (
        "cameras.npz and images_stokes/*_s0.hdr",
        lambda f: (f / "cameras.npz").is_file() and any((f / "images_stokes").glob("*_s0.hdr")),
        read_pandora,
    ),
    "nersp": (
        "cameras.npz and s0/*.npy",
        lambda f: (f / "cameras.npz").is_file() and any((f / "s0").glob("*.npy")),
        read_nersp,
    ),
    "polar": (
        "<name>_0.png ... <name>_135.png, 0/ 45/ 90/ 135/ folders (in the folder or images/), or raw/",
        _has_angle_images,
        read_polar_folder,
    ),
}
"""fmt -> (what its detection looks for, detector(folder) -> bool, reader(folder, **kwargs))."""


def detect_format(path: str | os.PathLike) -> str:
    """Name of the first format in :data:`FORMATS` whose marker files exist in ``path``."""
    folder = Path(path)
    if not folder.is_dir():
        raise PolarInputError(folder, "not a folder")
    for fmt, (_, detector, _) in FORMATS.items():
        if detector(folder):
            return fmt
    looked_for = "; ".join(f"{fmt}: {what}" for fmt, (what, _, _) in FORMATS.items())
    raise PolarInputError(folder, f"no known dataset format found. Looked for {looked_for}")


def reader_options(fmt: str) -> tuple[str, ...]:
    """Keyword options the reader of ``fmt`` takes (e.g. ``pattern``, ``bit_depth``, ``sfm`` for polar)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose one of {list(FORMATS)}")
    parameters = list(inspect.signature(FORMATS[fmt][2]).parameters.values())[1:]
    return tuple(p.name for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY))


def load_views(path: str | os.PathLike, fmt: str = "auto", **kwargs) -> list[View]:
    """Read any supported dataset folder into views in the project's conventions.

    Args:
        path: dataset folder (one scene/object).
        fmt: "auto" (detect) or one of :data:`FORMATS`.
        **kwargs: passed to the reader (e.g. ``normalize`` for nersp/pandora, ``pattern``,
            ``bit_depth``, ``sfm``, ``check_pattern``, ``info`` for polar; :func:`reader_options`).

    Returns:
        list of :class:`~polargs_plugin.types.View`; a warning names the views whose brightness
        is 4 times or more off the median view's (:func:`~polargs_plugin.data.checks.brightness_outliers`).

    Raises:
        PolarInputError: naming the folder: no known format, or an option its reader does not take.
    """
    if fmt == "auto":
        fmt = detect_format(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose 'auto' or one of {list(FORMATS)}")
    known = reader_options(fmt)
    unknown = [name for name in kwargs if name not in known]
    if unknown:
        raise PolarInputError(
            path, f"option(s) {', '.join(unknown)} do not apply to a {fmt} dataset (its reader takes: {', '.join(known) or 'none'})"
        )
    views = FORMATS[fmt][2](Path(path), **kwargs)
    for view in views:  # a NaN pixel in an EXR / HDR file must not reach training silently
        validate_view(view, "load_views")
    warn_brightness_outliers(views, str(path))  # nor a view read 257 times too dark
    return views
