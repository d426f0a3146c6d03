"""SMVP3D / RMVP3D in the NeRSP layout (and the PolGS variant): reader and writer.

Layout (one object folder)::

    cameras.npz                      world_mat_%d / scale_mat_%d, 0-based (NeRSP)
                                     or world_mat_%02d / scale_mat_%02d, 1-based (PolGS)
    s0/0000.npy s1/ s2/              float (H, W, 3) RGB Stokes
    input_azimuth_maps/0000.png      16-bit RGBA: AoLP * 65535 / pi, alpha = object mask
                                     (PolGS: train_input_azimuth_maps/)
    image/0000.png                   8-bit RGB picture (PolGS: train/); used only to check the Stokes scale
    normal/0000.npy                  optional GT normals (H, W, 3) float (also normals/, .exr, 16-bit .png)

Conversions made by :func:`read_nersp`:

- Cameras: P = world_mat @ scale_mat (or world_mat alone with ``normalize=False``), split by
  ``cv2.decomposeProjectionMatrix``, K / K[2, 2]; OpenCV axes already; principal point shifted by
  :data:`~polargs_plugin.data.cameras.IDR_PIXEL_CENTER_OFFSET` (0: taken as +0.5 centres). Each
  view gets its own K (NeRSP uses view 0's K for all). NeRSP's extra recentring
  (``normalize_camera``) and PolGS's 180-degree world rotation for SMVP3D are similarity
  transforms of the world and are *not* applied.
- Stokes: multiplied by :data:`NERSP_STOKES_FACTOR` = 1. The stored s0 is the full intensity
  (Mitsuba 3's s0; the real data's (I0+I45+I90+I135)/2), which is our s0. NeRSP's loader halves
  all three, which gives its own half-intensity radiance, i.e. our training colour s0 / 2; PolGS
  does not halve. DoLP and AoLP do not depend on this factor. When ``image/`` holds the 8-bit
  picture of a view, the scale is checked against it (:func:`~polargs_plugin.data.checks.image_scale_ratio`
  on the first :data:`~polargs_plugin.data.views.SCALE_CHECK_VIEWS` views) and a mismatch beyond 25 % is warned about.
- AoLP direction: none. NeRSP and PolGS fit the stored s1, s2 with PANDORA's Stokes model, whose
  reference frame (x_o horizontal, y_o = x_o x o pointing down for an upright camera) gives a
  diffuse AoLP counter-clockwise from image +x towards image up, our convention. (NeRSP's
  tangent vectors r1 sin a - r2 cos a treat the azimuth maps as clockwise with y down; the
  maps are not used here.) ``polargs check`` tests the direction on the data's silhouettes.
- GT normals (optional, ``normal/`` or ``normals/``, ``.npy`` / ``.exr`` float or 16-bit PNG
  coding n = 2 v / 65535 - 1): the frame (OpenCV camera, OpenGL camera or world) is told from
  the silhouettes (:func:`~polargs_plugin.data.checks.orient_normal_map`) and converted to the
  OpenCV camera frame; a frame other than OpenCV is reported with a warning.
- Channels: ``.npy`` arrays are RGB already; PNGs are converted from OpenCV's BGR(A).
- Mask: alpha of the azimuth map, valid where non-zero (as NeRSP's ``astype(bool)``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from polargs_plugin.data import cameras as cam
from polargs_plugin.data.imageio_utils import (
    check_stokes,
    linear_to_srgb,
    read_image,
    read_npy,
    to_hwc,
    write_npy,
    write_png,
)
from polargs_plugin.data.views import ViewCollector, warn_unused_files
from polargs_plugin.io import PolarInputError
from polargs_plugin.optics.stokes import aolp_from_stokes
from polargs_plugin.types import View

__all__ = ["NERSP_STOKES_FACTOR", "AZIMUTH_MAP_SCALE", "NORMAL_DIRS", "read_nersp", "write_nersp"]

NORMAL_DIRS = ("normal", "normals")
"""Folders searched, in order, for GT normal maps ``<stem>.npy`` / ``.exr`` / ``.png``."""

NERSP_STOKES_FACTOR = 1.0
"""Stored NeRSP/PolGS ``.npy`` Stokes times this factor = our Stokes (s0 = full intensity)."""

AZIMUTH_MAP_SCALE = 65535 / np.pi
"""16-bit code per radian of AoLP in ``input_azimuth_maps`` (channel 0)."""

_LAYOUTS = {
    "nersp": {"azimuth": "input_azimuth_maps", "image": "image"},
    "polgs": {"azimuth": "train_input_azimuth_maps", "image": "train"},
}


def _camera_keys(arrays: dict[str, np.ndarray], path: Path) -> tuple[str, int]:
    """Key format and index base: NeRSP ``%d`` 0-based or PolGS ``%02d`` 1-based."""
    if "world_mat_0" in arrays:
        return "{:d}", 0
    if "world_mat_01" in arrays:
        return "{:02d}", 1
    raise PolarInputError(path, "has neither world_mat_0 (NeRSP, 0-based) nor world_mat_01 (PolGS, 1-based)")


def _azimuth_mask(path: Path, shape: tuple[int, int]) -> torch.Tensor:
    """The object mask of one view: the alpha of its azimuth map, valid where non-zero."""
    azimuth = read_image(path)
    if azimuth.ndim != 3 or azimuth.shape[2] not in (2, 4):
        raise PolarInputError(path, "azimuth map has no alpha channel (the object mask)")
    if azimuth.shape[:2] != shape:
        raise PolarInputError(path, f"size {azimuth.shape[:2]} differs from the Stokes {shape}")
    return torch.from_numpy(azimuth[..., -1] > 0)[None]


def _normal_file(folder: Path, stem: str) -> Path | None:
    for sub in NORMAL_DIRS:
        for suffix in (".npy", ".exr", ".png"):
            path = folder / sub / f"{stem}{suffix}"
            if path.is_file():
                return path
    return None


def read_nersp(folder: str | os.PathLike, normalize: bool = True, check_scale: bool = True,
               resolution: int = 1) -> list[View]:
    """Read an SMVP3D/RMVP3D object folder (NeRSP or PolGS layout) into views.

    Args:
        folder: the object folder holding ``cameras.npz`` and ``s0/ s1/ s2/``.
        normalize: cameras in the unit-sphere frame (world_mat @ scale_mat, as NeRSP/PolGS
            train) if True, in the capture frame (world_mat) if False.
        check_scale: compare the Stokes with the 8-bit pictures and warn on a mismatch.
        resolution: read at this resolution (1, 2, 4, 8 divide the size, above 8: a target
            width; :mod:`polargs_plugin.data.resolution`); float images are kept as float16.

    Returns:
        One :class:`View` per ``s0/*.npy`` (sorted), named by the file stem; ``stokes``
        (3, 3, H, W), ``mask`` (1, H, W) from the azimuth map's alpha when that folder exists,
        ``normal_gt`` (3, H, W) OpenCV camera frame when a normal map exists.
    """
    folder = Path(folder)
    npz_path = folder / "cameras.npz"
    arrays = cam.load_npz(npz_path)
    key_format, base = _camera_keys(arrays, npz_path)
    azimuth_dir = next(
        (folder / lay["azimuth"] for lay in _LAYOUTS.values() if (folder / lay["azimuth"]).is_dir()), None
    )
    stems = sorted(p.stem for p in (folder / "s0").glob("*.npy"))
    if not stems:
        raise PolarInputError(folder / "s0", "no .npy Stokes files")
    components = [path for sub in ("s1", "s2") if (folder / sub).is_dir() for path in (folder / sub).glob("*.npy")]
    warn_unused_files(folder, components, set(stems), lambda path: path.stem, "no s0/ file of that view")
    collector = ViewCollector(folder, check_scale, resolution)
    for stem in stems:
        if not stem.isdigit():
            raise PolarInputError(folder / "s0" / f"{stem}.npy", "file name is not a view index like 0000.npy")
        paths = [folder / s / f"{stem}.npy" for s in ("s0", "s1", "s2")]
        stokes = check_stokes([read_npy(p).astype(np.float32) for p in paths], paths) * NERSP_STOKES_FACTOR
        key = key_format.format(int(stem) + base)
        K, w2c = cam.idr_camera(arrays, f"world_mat_{key}", f"scale_mat_{key}", npz_path, normalize)
        mask = None if azimuth_dir is None else _azimuth_mask(azimuth_dir / f"{stem}.png", stokes.shape[-2:])
        normal_gt = collector.normal_gt(_normal_file(folder, stem), mask, w2c, tuple(stokes.shape[-2:]))
        collector.check_picture([folder / lay["image"] / f"{stem}.png" for lay in _LAYOUTS.values()], stokes, mask)
        collector.add(stem, K, w2c, stokes, mask, normal_gt)
    return collector.finish()


def write_nersp(
    views: list[View],
    folder: str | os.PathLike,
    variant: str = "nersp",
    scale_mat: np.ndarray | None = None,
) -> Path:
    """Write views in the NeRSP (or PolGS) layout; each file is written atomically.

    Args:
        views: views to write, in order (files are numbered 0000, 0001, ...).
        folder: output object folder.
        variant: "nersp" (0-based ``%d`` camera keys, ``image/``, ``input_azimuth_maps/``) or
            "polgs" (1-based ``%02d`` keys, ``train/``, ``train_input_azimuth_maps/``).
        scale_mat: (4, 4) IDR scale matrix (capture frame from unit-sphere frame); identity
            if None. The views' cameras are taken to be in the unit-sphere frame.

    Returns:
        ``folder``. ``image/`` holds sRGB 8-bit pictures of s0 / 2 clipped to [0, 1];
        ``normal/`` the views' GT normals (OpenCV camera frame, ``.npy``) when they have them.
    """
    if variant not in _LAYOUTS:
        raise ValueError(f"variant must be one of {sorted(_LAYOUTS)}, got {variant!r}")
    layout = _LAYOUTS[variant]
    key_format, base = ("{:d}", 0) if variant == "nersp" else ("{:02d}", 1)
    folder = Path(folder)
    scale_mat = np.eye(4) if scale_mat is None else np.asarray(scale_mat, dtype=np.float64)
    cameras = {}
    for index, view in enumerate(views):
        stem = f"{index:04d}"
        stokes = view.stokes.detach().cpu().float() / NERSP_STOKES_FACTOR
        for name, plane in zip(("s0", "s1", "s2"), stokes):
            write_npy(folder / name / f"{stem}.npy", to_hwc(plane))
        write_png(folder / layout["image"] / f"{stem}.png", linear_to_srgb(to_hwc(view.image.cpu())), 8)
        if view.normal_gt is not None:
            write_npy(folder / NORMAL_DIRS[0] / f"{stem}.npy", to_hwc(view.normal_gt.detach().cpu().float()))
        aolp = aolp_from_stokes(view.stokes.detach().cpu().mean(dim=1, keepdim=True))[0].numpy()
        code = np.rint(aolp * AZIMUTH_MAP_SCALE).astype(np.uint16)
        alpha = np.full_like(code, 65535) if view.mask is None else view.mask[0].cpu().numpy().astype(np.uint16) * 65535
        write_png(folder / layout["azimuth"] / f"{stem}.png", np.stack([code, code, code, alpha], axis=-1), 16)
        cameras[key_format.format(index + base)] = (view.K.double().cpu().numpy(), view.world_to_camera.double().cpu().numpy())
    cam.write_idr_cameras(folder / "cameras.npz", cameras, scale_mat)
    return folder
