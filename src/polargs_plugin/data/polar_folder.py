"""A plain folder of polarization captures with a COLMAP model: reader and writer.

Layout (``images/`` may be left out and its content put in the folder itself)::

    images/<name>_0.png  <name>_45.png  <name>_90.png  <name>_135.png     four-angle images
      or images/0/<name>.png  images/45/  images/90/  images/135/         one folder per angle
      or raw/<name>.png (or .tif, .npy)                                    DoFP raw mosaics
    masks/<name>.png                                                       optional object masks
    sparse/0/cameras.txt images.txt  (or .bin; also sparse/ or the folder)  COLMAP model

Angle images may be 8/16-bit PNG/TIFF (grey or RGB; an alpha channel is dropped) or float EXR.
Raw mosaics are 2-D 8/16-bit images or ``.npy`` arrays, demosaiced by
:func:`polargs_plugin.optics.mosaic.demosaic_polar` (``pattern`` "mono" or "rgb", or "auto": told
from the frames). The pattern is checked against every frame
(:func:`polargs_plugin.optics.pattern.check_mosaic_pattern`: inside the polarizer super-pixels a
colour IMX250MYR frame has the 2x2 Bayer colour structure, a mono IMX250MZR frame has none), so a
mono frame read as colour, or the reverse, is an error naming the frame.

Conversions made by :func:`read_polar_folder`:

- Intensities: integer images / (2^bit_depth - 1) (default bit depth: that of the dtype), BGR ->
  RGB; Stokes by the closed form s0 = (I0+I45+I90+I135)/2, s1 = I0 - I90, s2 = I45 - I135 (no
  factor: s0 is the full intensity). AoLP direction: none, provided the polarizer angles are
  measured counter-clockwise on screen from image +x, as on Sony DoFP sensors.
- Cameras: COLMAP world-to-camera (qvec, tvec) in OpenCV axes; COLMAP's pixel centres are at
  +0.5 (upper-left pixel centre (0.5, 0.5)) like ours, so K is taken unchanged. Camera models
  with distortion are accepted only when every distortion coefficient is zero
  (:mod:`polargs_plugin.data.colmap`).
- Image to camera matching: by file stem of the COLMAP image name; a trailing ``_0``, ``_45``,
  ``_90`` or ``_135`` is ignored, so a model built on the 0-degree images also fits.
- Without a model and with ``sfm=True`` (the ``sfm`` extra, pycolmap), SfM runs on sRGB 8-bit
  pictures of s0 / 2 and writes its model (text) to ``sparse/0``. It needs at least
  :data:`~polargs_plugin.data.sfm.SFM_MIN_VIEWS` overlapping views of the object; fewer, or fewer registered, is an error
  that says how many were found and registered.
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from polargs_plugin.compact import AngleImages, Plain, Stored
from polargs_plugin.data.colmap import ColmapCamera, find_colmap_model, read_colmap_model, write_colmap_text
from polargs_plugin.data.imageio_utils import (
    UINT_MAX,
    linear_to_srgb,
    read_exr,
    read_image,
    read_npy,
    to_hwc,
    warn_narrow_range,
    write_png,
)
from polargs_plugin.data.resolution import prepare_view, scale_intrinsics, target_size
from polargs_plugin.data.sfm import run_sfm
from polargs_plugin.data.views import read_mask
from polargs_plugin.io import PolarInputError
from polargs_plugin.optics.mosaic import MOSAIC_PATTERNS, demosaic_polar, mosaic_from_intensities
from polargs_plugin.optics.pattern import (
    MONO_BELOW,
    RGB_ABOVE,
    classify_mosaic,
    mosaic_colour_evidence,
    pattern_mismatch,
)
from polargs_plugin.optics.stokes import POLARIZER_ANGLES_DEG, intensities_from_stokes, stokes_from_intensities
from polargs_plugin.types import View

__all__ = ["read_polar_folder", "write_polar_folder", "PolarFolderWriter"]

_IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".jpg", ".jpeg")
_RAW_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
_ANGLE_NAMES = tuple(str(a) for a in POLARIZER_ANGLES_DEG)


def _read_angle_image(path: Path, bit_depth: int | None) -> tuple[np.ndarray, float | None, np.dtype, int | None]:
    """(H, W, C) values of an angle image as stored, the level of full intensity (None: float data,
    already in intensity units), the file's dtype and its largest value (None for float data)."""
    if path.suffix.lower() == ".exr":
        array = read_exr(path)
        return array, None, array.dtype, None
    raw = read_image(path)
    _check_bit_depth(bit_depth, raw.dtype, path)
    scale = UINT_MAX[raw.dtype] if bit_depth is None else 2**bit_depth - 1
    if raw.max() > scale:
        raise PolarInputError(path, f"values up to {raw.max()} exceed the {bit_depth}-bit range")
    array = raw[..., None] if raw.ndim == 2 else raw[..., :3]
    return array, scale, raw.dtype, int(raw.max())


def _check_bit_depth(bit_depth: int | None, dtype: np.dtype, path: Path) -> None:
    """Refuse a bit depth above what the file's integer type holds: its data would read
    ``2^(bit_depth - bits)`` times too dark."""
    bits = 8 * np.dtype(dtype).itemsize
    if bit_depth is not None and bit_depth > bits:
        raise PolarInputError(path, f"{bits}-bit file, but --bit-depth {bit_depth} was given: it holds at most {bits} bits")


def _warn_narrow_view(peak: int | None, dtype: np.dtype, bit_depth: int | None, path: Path) -> None:
    """:func:`warn_narrow_range` for a view's integer images (``peak``: their largest value)."""
    if peak is None:
        return
    declared = f"--bit-depth {bit_depth}" if bit_depth is not None else f"the file's {8 * np.dtype(dtype).itemsize}-bit type"
    warn_narrow_range(peak, bit_depth or 8 * np.dtype(dtype).itemsize, path, declared + "; --bit-depth 8 if the data is 8-bit")


def _files_by_stem(directory: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    if not directory.is_dir():
        return {}
    return {p.stem: p for p in sorted(directory.iterdir()) if p.suffix.lower() in suffixes and not p.name.startswith(".")}


def _angle_sets(root: Path) -> dict[str, list[Path]]:
    """{name: [path at 0, 45, 90, 135]} from per-angle folders or ``<name>_<angle>`` files."""
    folders = [root / a for a in _ANGLE_NAMES]
    if any(f.is_dir() for f in folders):
        per_angle = [_files_by_stem(f, _IMAGE_SUFFIXES) for f in folders]
        names = sorted(set().union(*per_angle))
        expected = [(folder, files) for folder, files in zip(folders, per_angle)]
    else:
        files = _files_by_stem(root, _IMAGE_SUFFIXES)
        per_angle = [{} for _ in _ANGLE_NAMES]
        for stem, path in files.items():
            base, _, angle = stem.rpartition("_")
            if base and angle in _ANGLE_NAMES:
                per_angle[_ANGLE_NAMES.index(angle)][base] = path
        names = sorted(set().union(*per_angle))
        expected = [(root, files) for files in per_angle]
    sets = {}
    for name in names:
        paths = [files.get(name) for _, files in expected]
        for (folder, _), angle, path in zip(expected, _ANGLE_NAMES, paths):
            if path is None:
                missing = folder / f"{name}.*" if folder.name == angle else folder / f"{name}_{angle}.*"
                raise PolarInputError(missing, f"missing the {angle}-degree image of view {name}")
        sets[name] = paths
    return sets


def _image_root(folder: Path) -> Path:
    return folder / "images" if (folder / "images").is_dir() else folder


def _stokes_from_angles(paths: list[Path], bit_depth: int | None) -> Stored:
    """The Stokes of four angle images: the integer images themselves (:class:`AngleImages`) when
    they are 8/16-bit, else float32 Stokes."""
    images = [_read_angle_image(p, bit_depth) for p in paths]
    first_array, first_scale, first_dtype, _ = images[0]
    for (array, _, dtype, _), path in zip(images, paths):
        if array.shape != first_array.shape or dtype != first_dtype:
            raise PolarInputError(
                path, f"{array.shape[:2]} {dtype} image differs from {paths[0].name} ({first_array.shape[:2]} {first_dtype})"
            )
    stacked = np.stack([array.transpose(2, 0, 1) for array, _, _, _ in images])
    if not stacked.max() > 0:
        raise PolarInputError(paths[0], "all-dark view: every angle image is zero")
    peaks = [peak for _, _, _, peak in images if peak is not None]
    _warn_narrow_view(max(peaks) if peaks else None, first_dtype, bit_depth, paths[0])
    if first_scale is not None:
        return AngleImages(torch.from_numpy(np.ascontiguousarray(stacked)), first_scale)
    return Plain(stokes_from_intensities(torch.from_numpy(stacked.astype(np.float32))))


def _read_raw(path: Path) -> np.ndarray:
    raw = read_npy(path) if path.suffix.lower() == ".npy" else read_image(path)
    if not raw.max() > 0:
        raise PolarInputError(path, "all-dark raw mosaic")
    return raw


def _stokes_from_raw(path: Path, pattern: str, bit_depth: int | None) -> Stored:
    """The Stokes of a raw mosaic: its demosaiced integer levels (:class:`AngleImages`) when the
    frame is integer, else float32 Stokes."""
    raw = _read_raw(path)
    if raw.dtype in UINT_MAX and (bit_depth is None or bit_depth <= 8 * raw.dtype.itemsize):
        _warn_narrow_view(int(raw.max()), raw.dtype, bit_depth, path)
    intensities = demosaic_polar(raw, pattern=pattern, bit_depth=bit_depth, source=str(path))
    if np.issubdtype(raw.dtype, np.floating):
        return Plain(stokes_from_intensities(intensities))
    full = 2**bit_depth - 1 if bit_depth is not None else UINT_MAX[raw.dtype]
    # the demosaiced integer levels, exactly: (level / full) * full lies within 0.5 of the level
    levels = torch.round(intensities * full).to(torch.uint16 if full > 255 else torch.uint8)
    return AngleImages(levels, full)


def _resolve_pattern(
    paths: dict[str, Path], pattern: str, bit_depth: int | None, check: bool
) -> tuple[str, dict[str, float | None]]:
    """The mosaic pattern of a folder's raw frames: ``pattern`` checked against each frame, or
    told from them (``"auto"``). Returns (pattern, {name: colour evidence}). The frames are read
    one at a time."""
    if pattern != "auto" and not check:
        return pattern, {}
    evidence = {name: mosaic_colour_evidence(_read_raw(path), bit_depth, str(path)) for name, path in paths.items()}
    if pattern != "auto":
        for name, value in evidence.items():
            problem = pattern_mismatch(value, pattern)
            if problem is not None:
                raise PolarInputError(paths[name], problem)
        return pattern, evidence
    found = {name: classify_mosaic(value) for name, value in evidence.items()}
    mono = [name for name, kind in found.items() if kind == "mono"]
    rgb = [name for name, kind in found.items() if kind == "rgb"]
    if mono and rgb:
        raise PolarInputError(
            paths[rgb[0]],
            f"looks like a colour (IMX250MYR) mosaic while {paths[mono[0]].name} looks mono (IMX250MZR) "
            f"({len(rgb)} colour, {len(mono)} mono frames); one folder holds one sensor's frames: give the pattern (--pattern)",
        )
    if not (mono or rgb):
        known = [v for v in evidence.values() if v is not None]
        what = f"at most {100 * max(known):.0f} % of the bright blocks of a frame" if known else "no frame bright or large enough"
        raise PolarInputError(
            paths[next(iter(paths))].parent,
            f"cannot tell mono (IMX250MZR) from colour (IMX250MYR) mosaics: Bayer colour structure in {what} "
            f"(mono < {100 * MONO_BELOW:.0f} %, colour > {100 * RGB_ABOVE:.0f} %); give the pattern (--pattern mono or rgb)",
        )
    return ("mono" if mono else "rgb"), evidence


def _camera_for(name: str, model: dict[str, ColmapCamera]) -> ColmapCamera | None:
    by_stem = {}
    for image_name, camera in model.items():
        stem = Path(image_name).stem
        base, _, angle = stem.rpartition("_")
        by_stem.setdefault(stem, camera)
        if base and angle in _ANGLE_NAMES:
            by_stem.setdefault(base, camera)
    return by_stem.get(name)


def _stokes_readers(
    folder: Path, pattern: str | None, bit_depth: int | None, check_pattern: bool, info: dict
) -> dict[str, Callable[[], Stored]]:
    """{name: a function reading that view's Stokes} from the folder's angle images or, without
    them, its raw mosaics; the mosaic pattern used and the frames' colour evidence go into ``info``."""
    angle_sets = _angle_sets(_image_root(folder))
    raw_files = {} if angle_sets else _files_by_stem(folder / "raw", _RAW_SUFFIXES)
    if not angle_sets and not raw_files:
        raise PolarInputError(
            folder, "no polarization images: expected <name>_0/45/90/135 files, 0/ 45/ 90/ 135/ folders, or raw/ mosaics"
        )
    if raw_files and pattern not in (*MOSAIC_PATTERNS, "auto"):
        raise PolarInputError(
            folder / "raw", f"unknown mosaic pattern {pattern!r}; pass pattern= one of {(*MOSAIC_PATTERNS, 'auto')} (polargs: --pattern)"
        )
    readers = {name: partial(_stokes_from_angles, paths, bit_depth) for name, paths in angle_sets.items()}
    used_pattern, evidence = None, {}
    if raw_files:
        used_pattern, evidence = _resolve_pattern(raw_files, pattern, bit_depth, check_pattern)
        readers.update({name: partial(_stokes_from_raw, path, used_pattern, bit_depth) for name, path in raw_files.items()})
    info.update(pattern=used_pattern, colour_evidence=evidence, sfm=False)
    return readers


def _sfm_picture(stokes: Tensor) -> np.ndarray:
    """The sRGB 8-bit picture of s0 / 2 that SfM matches."""
    return np.rint(linear_to_srgb(to_hwc(stokes[0] / 2)) * 255).astype(np.uint8)


def _read_views(folder: Path, readers: dict[str, Callable[[], Stored]], resolution: int,
                pictures: Path | None) -> dict[str, tuple[View, tuple[int, int]]]:
    """{name: (view whose camera is still to be set, size (W, H) of its files)} at ``resolution``,
    read one view at a time; with ``pictures``, each view's full-size SfM picture is written there."""
    mask_paths = _files_by_stem(folder / "masks", (".png", ".tif", ".tiff"))
    views = {}
    for name, read in readers.items():
        stored = read()
        height, width = stored.shape[-2:]
        if pictures is not None:
            write_png(pictures / f"{name}.png", _sfm_picture(stored.decode()), 8)
        mask = read_mask(mask_paths[name], (height, width), matched="the images") if name in mask_paths else None
        camera = torch.eye(4, dtype=torch.float64)  # set from the COLMAP model once it is known
        view = View(name=name, K=camera[:3, :3].clone(), world_to_camera=camera, stokes=stored, mask=mask, source=str(folder))
        views[name] = (prepare_view(view, resolution), (width, height))
    return views


def _registered_views(views: dict[str, tuple[View, tuple[int, int]]], model_dir: Path) -> tuple[list[View], list[str]]:
    """The views the COLMAP model in ``model_dir`` has cameras for, with those cameras (K scaled
    to the views' resolution), and the names of those it has none for."""
    model = read_colmap_model(model_dir)
    registered, unregistered = [], []
    for name, (view, (width, height)) in views.items():
        camera = _camera_for(name, model)
        if camera is None:
            unregistered.append(name)
            continue
        if (camera.width, camera.height) != (width, height):
            raise PolarInputError(model_dir, f"camera of {name} is {camera.width}x{camera.height}, images are {width}x{height}")
        K = scale_intrinsics(torch.from_numpy(camera.K.copy()), (width, height), (view.width, view.height))
        registered.append(view.replaced(K=K, world_to_camera=torch.from_numpy(camera.world_to_camera.copy())))
    return registered, unregistered


def read_polar_folder(
    folder: str | os.PathLike,
    pattern: str | None = None,
    bit_depth: int | None = None,
    sfm: bool = False,
    check_pattern: bool = True,
    info: dict | None = None,
    resolution: int = 1,
) -> list[View]:
    """Read four-angle images or raw mosaics plus a COLMAP model into views.

    Views are read one at a time and kept compact (:mod:`polargs_plugin.compact`): 8/16-bit
    angle images and integer raw frames as their integer (demosaiced) levels; float data, and
    images averaged by ``resolution``, as float16.

    Args:
        folder: the capture folder (layout in the module docstring).
        pattern: mosaic layout for ``raw/``: "mono", "rgb" or "auto" (told from the frames; an
            error when they cannot tell); required when reading mosaics.
        bit_depth: significant bits of integer images (e.g. 12 for 12-bit data in 16-bit files);
            None uses the full range of the file's dtype.
        sfm: when no COLMAP model exists, run pycolmap SfM and write ``sparse/0`` (cameras of the
            files' size; with a ``resolution`` other than 1 the features are found on pictures
            scaled down to the training width).
        check_pattern: check a given pattern against every raw frame (a mono frame read as "rgb"
            is an error, and the reverse); off for colour frames of grey, white-balanced scenes,
            which cannot be told from mono ones.
        info: a dict to fill with what was found: ``pattern`` (the one used for raw/, or None),
            ``colour_evidence`` ({view: fraction}, see ``mosaic_colour_evidence``), ``model``
            (the COLMAP model folder), ``sfm`` (True when SfM built it now) and, then,
            ``sfm_seconds`` (its wall time).
        resolution: read at this resolution (1, 2, 4, 8 divide the size, above 8: a target
            width; :mod:`polargs_plugin.data.resolution`).

    Returns:
        One :class:`View` per registered image (sorted by name); images that the model does
        not register are skipped with a warning. stokes (3, C, H, W), C = 1 or 3.
    """
    folder = Path(folder)
    info = {} if info is None else info
    readers = _stokes_readers(folder, pattern, bit_depth, check_pattern, info)
    model_dir = find_colmap_model(folder)
    if model_dir is None and not sfm:
        raise PolarInputError(
            folder, "no COLMAP model (sparse/0/cameras.txt|.bin, images.txt|.bin); pass sfm=True (polargs: --sfm) to run SfM"
        )
    with tempfile.TemporaryDirectory(prefix="polargs-sfm-") as scratch:
        pictures = Path(scratch) if model_dir is None else None
        views = _read_views(folder, readers, resolution, pictures)
        if pictures is not None:
            started = time.perf_counter()
            width = next(iter(views.values()))[1][0]
            max_size = None if resolution == 1 else target_size(width, width, resolution)[0]
            model_dir = run_sfm(pictures, folder / "sparse" / "0", max_image_size=max_size)
            info.update(sfm=True, sfm_seconds=time.perf_counter() - started)
    info["model"] = str(model_dir)
    registered, unregistered = _registered_views(views, model_dir)
    if unregistered:
        warnings.warn(f"{folder}: {len(unregistered)} views have no camera in {model_dir}: {unregistered[:10]}", stacklevel=2)
    if not registered:
        raise PolarInputError(model_dir, "registers none of the images")
    return registered


def write_polar_folder(
    views: list[View],
    folder: str | os.PathLike,
    mode: str = "angles",
    pattern: str = "rgb",
    bit_depth: int = 16,
    per_angle_folders: bool = False,
    angle_images: list[torch.Tensor | None] | None = None,
) -> Path:
    """Write views as a polar folder with a COLMAP text model in ``sparse/0``; atomic per file.

    Args:
        views: views to write (names are kept; intensities I(beta) from Malus must lie in [0, 1]).
        folder: output folder.
        mode: "angles" (four images per view) or "raw" (one mosaic per view in ``raw/``).
        pattern: mosaic layout for ``mode="raw"`` ("mono" needs C = 1, "rgb" C = 3).
        bit_depth: 8 or 16 bits per PNG sample. 16-bit holds 8-bit-quantised data exactly
            (65535 = 257 x 255).
        per_angle_folders: ``images/0/<name>.png``... instead of ``images/<name>_0.png``.
        angle_images: optional per-view (4, C, H, W) images in [0, 1] to write as they are
            (e.g. ``SyntheticScene.angle_images``); views without one (None) get the Malus images
            of their Stokes, clipped to [0, 1]. Four measured images hold one more degree of
            freedom than (s0, s1, s2), so only the measured ones reproduce them exactly.

    Returns:
        ``folder``.
    """
    writer = PolarFolderWriter(folder, mode, pattern, bit_depth, per_angle_folders)
    for index, view in enumerate(views):
        writer.add(view, angle_images[index] if angle_images is not None else None)
    return writer.finish()


class PolarFolderWriter:
    """Writes a polar folder view by view (:func:`write_polar_folder` in parts); arguments as there.

    :meth:`finish` writes the COLMAP model of the views added (or, with ``cameras=False``,
    leaves it out, for SfM to build).
    """

    def __init__(self, folder: str | os.PathLike, mode: str = "angles", pattern: str = "rgb", bit_depth: int = 16,
                 per_angle_folders: bool = False):
        if mode not in ("angles", "raw"):
            raise ValueError(f"mode must be 'angles' or 'raw', got {mode!r}")
        if mode == "raw" and pattern not in MOSAIC_PATTERNS:
            raise ValueError(f"pattern must be one of {MOSAIC_PATTERNS}, got {pattern!r}")
        self.folder, self.mode, self.pattern, self.bit_depth = Path(folder), mode, pattern, bit_depth
        self.per_angle_folders = per_angle_folders
        self.model: dict[str, ColmapCamera] = {}

    def add(self, view: View, angle_images: torch.Tensor | None = None) -> None:
        """Write one view (its ``angle_images`` as they are, or the Malus images of its Stokes)."""
        folder = self.folder
        if angle_images is None:
            # Malus; clipping only matters where the views' Stokes come from saturated images
            intensities = intensities_from_stokes(view.stokes.detach().cpu().double()).clamp(0, 1)
        else:
            intensities = angle_images.detach().cpu().double()
            if intensities.shape != (4, view.channels, view.height, view.width):
                raise ValueError(f"angle images of view {view.name} have shape {tuple(intensities.shape)}, "
                                 "expected (4, C, H, W)")
        if self.mode == "raw":
            raw = mosaic_from_intensities(intensities, self.pattern)
            write_png(folder / "raw" / f"{view.name}.png", np.asarray(raw, dtype=np.float64), self.bit_depth)
        else:
            for angle, image in zip(_ANGLE_NAMES, intensities):
                name = f"{angle}/{view.name}.png" if self.per_angle_folders else f"{view.name}_{angle}.png"
                write_png(folder / "images" / name, to_hwc(image), self.bit_depth)
        if view.mask is not None:
            write_png(folder / "masks" / f"{view.name}.png", view.mask[0].cpu().numpy().astype(np.uint8) * 255, 8)
        self.model[f"{view.name}.png"] = ColmapCamera(
            view.K.double().cpu().numpy(), view.world_to_camera.double().cpu().numpy(), view.width, view.height
        )

    def finish(self, cameras: bool = True) -> Path:
        """Write the COLMAP model ``sparse/0`` of the views added (unless ``cameras`` is False); the folder."""
        if cameras:
            write_colmap_text(self.folder / "sparse" / "0", self.model)
        return self.folder
