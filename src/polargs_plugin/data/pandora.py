"""PANDORA real scenes (akshatdave/pandora, ``dataio/Ours.py`` layout): reader and writer.

Layout (one scene folder)::

    images_stokes/01_s0.hdr          Radiance RGBE, RGB: s0
    images_stokes/01_s0p1.hdr        s0 + s1   (RGBE cannot store negative values)
    images_stokes/01_s0p2.hdr        s0 + s2
    mask/01.png                      object mask (optional)
    cameras.npz                      world_mat_<name> / scale_mat_<name> (IDR), name = "01" ...
    images/01.png                    sRGB pictures for COLMAP (not needed to build views)

Conversions made by :func:`read_pandora`:

- Stokes: PANDORA (and NeRSP/PolGS reading PANDORA) decode s0 = 0.5 hdr_s0,
  s1 = 0.5 hdr_s0p1 - s0, s2 = 0.5 hdr_s0p2 - s0: a half-intensity radiance, which is our training
  colour s0 / 2. We keep the full intensity, s0 = hdr_s0, s1 = hdr_s0p1 - hdr_s0,
  s2 = hdr_s0p2 - hdr_s0, i.e. twice PANDORA's values (:data:`PANDORA_STOKES_FACTOR` = 2 x
  :data:`PANDORA_LOADER_FACTOR`). DoLP and AoLP are unchanged. RGBE keeps about 8 significant
  bits per pixel (error up to max-channel x 2^-7), so s1 and s2 carry that absolute error.
- AoLP direction: none (PANDORA's Stokes frame is counter-clockwise for un-rolled cameras).
- Channels: ``.hdr`` and PNG are converted from OpenCV's BGR to RGB.
- Cameras: as NeRSP (IDR P = world_mat @ scale_mat, ``cv2.decomposeProjectionMatrix``,
  :data:`~polargs_plugin.data.cameras.IDR_PIXEL_CENTER_OFFSET`).
- Mask: first channel above half of full scale.
- Scale check: the 8-bit ``images/<name>.png`` of the first views is compared with s0 / 2
  (:func:`~polargs_plugin.data.checks.image_scale_ratio`); a mismatch beyond 25 % is warned about.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polargs_plugin.data import cameras as cam
from polargs_plugin.data.imageio_utils import check_stokes, linear_to_srgb, read_hdr, to_hwc, write_hdr, write_png
from polargs_plugin.data.views import ViewCollector, read_mask, warn_unused_files
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View

__all__ = ["PANDORA_LOADER_FACTOR", "PANDORA_STOKES_FACTOR", "read_pandora", "write_pandora"]

PANDORA_LOADER_FACTOR = 0.5
"""What PANDORA's own loader multiplies the stored HDR values by (half-intensity radiance)."""

PANDORA_STOKES_FACTOR = 2 * PANDORA_LOADER_FACTOR
"""Stored (decoded) HDR Stokes times this factor = our Stokes (s0 = full intensity)."""

_NEGATIVE_TOLERANCE = 1e-6
"""Relative float rounding below zero tolerated in s0 + s1, s0 + s2 when writing."""


def read_pandora(folder: str | os.PathLike, normalize: bool = True, check_scale: bool = True,
                 resolution: int = 1) -> list[View]:
    """Read a PANDORA scene folder into views.

    Args:
        folder: the scene folder holding ``images_stokes/`` and ``cameras.npz``.
        normalize: cameras in the unit-sphere frame (world_mat @ scale_mat) if True, in the
            capture frame (world_mat) if False.
        resolution: read at this resolution (1, 2, 4, 8 divide the size, above 8: a target
            width; :mod:`polargs_plugin.data.resolution`); float images are kept as float16.

    Returns:
        One :class:`View` per ``images_stokes/*_s0.hdr`` (sorted), named by its prefix.
    """
    folder = Path(folder)
    npz_path = folder / "cameras.npz"
    arrays = cam.load_npz(npz_path)
    stokes_dir = folder / "images_stokes"
    names = sorted(p.name[: -len("_s0.hdr")] for p in stokes_dir.glob("*_s0.hdr"))
    if not names:
        raise PolarInputError(stokes_dir, "no *_s0.hdr files")
    components = [*stokes_dir.glob("*_s0p1.hdr"), *stokes_dir.glob("*_s0p2.hdr")]
    warn_unused_files(folder, components, set(names), lambda path: path.name.rsplit("_", 1)[0], "no _s0.hdr of that view")
    collector = ViewCollector(folder, check_scale, resolution)
    for name in names:
        paths = [stokes_dir / f"{name}_{s}.hdr" for s in ("s0", "s0p1", "s0p2")]
        s0, s0p1, s0p2 = check_stokes([read_hdr(p) for p in paths], paths)
        stokes = np.stack([s0, s0p1 - s0, s0p2 - s0]) * PANDORA_STOKES_FACTOR
        K, w2c = cam.idr_camera(arrays, f"world_mat_{name}", f"scale_mat_{name}", npz_path, normalize)
        mask_paths = sorted((folder / "mask").glob(f"{name}.*"))
        mask = read_mask(mask_paths[0], stokes.shape[-2:]) if mask_paths else None
        collector.check_picture([folder / "images" / f"{name}.png"], stokes, mask)
        collector.add(name, K, w2c, stokes, mask)
    return collector.finish()


def _non_negative(array: np.ndarray, what: str, view: View) -> np.ndarray:
    floor = -_NEGATIVE_TOLERANCE * max(float(np.abs(array).max()), 1.0)
    if array.min() < floor:
        raise PolarInputError(view.source or view.name, f"view {view.name}: {what} is negative (DoLP > 1?)")
    return np.maximum(array, 0.0)


def write_pandora(views: list[View], folder: str | os.PathLike, scale_mat: np.ndarray | None = None) -> Path:
    """Write RGB views as a PANDORA scene folder; each file is written atomically.

    Views are named 01, 02, ... (1-based, as NeRSP reads PANDORA). ``scale_mat`` as in
    :func:`~polargs_plugin.data.nersp.write_nersp`. ``images/`` holds sRGB 8-bit pictures of
    s0 / 2 clipped to [0, 1].
    """
    folder = Path(folder)
    scale_mat = np.eye(4) if scale_mat is None else np.asarray(scale_mat, dtype=np.float64)
    cameras = {}
    for index, view in enumerate(views):
        name = f"{index + 1:02d}"
        if view.stokes.shape[1] != 3:
            raise PolarInputError(view.source or view.name, f"view {view.name}: PANDORA stores RGB, got {view.stokes.shape[1]} channels")
        s0, s1, s2 = (to_hwc(p) for p in view.stokes.detach().cpu().double() / PANDORA_STOKES_FACTOR)
        write_hdr(folder / "images_stokes" / f"{name}_s0.hdr", _non_negative(s0, "s0", view))
        write_hdr(folder / "images_stokes" / f"{name}_s0p1.hdr", _non_negative(s0 + s1, "s0 + s1", view))
        write_hdr(folder / "images_stokes" / f"{name}_s0p2.hdr", _non_negative(s0 + s2, "s0 + s2", view))
        write_png(folder / "images" / f"{name}.png", linear_to_srgb(to_hwc(view.image.cpu())), 8)
        if view.mask is not None:
            write_png(folder / "mask" / f"{name}.png", view.mask[0].cpu().numpy().astype(np.uint8) * 255, 8)
        cameras[name] = (view.K.double().cpu().numpy(), view.world_to_camera.double().cpu().numpy())
    cam.write_idr_cameras(folder / "cameras.npz", cameras, scale_mat)
    return folder
