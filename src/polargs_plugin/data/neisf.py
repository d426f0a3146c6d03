"""NeISF / NeISF++ scenes (sony/NeISF, sony/NeISFpp): reader and writer.

Layout (one scene folder, ``images/<scene>/`` in the NeISF repository)::

    poses_bounds.npy                 (N, 17) LLFF: 3x5 [pose | (H, W, f)] + near, far
    images_s0/img_001.exr ...        float32 RGB EXR, names 1-based, 3 digits
    images_s1/  images_s2/           signed float32 RGB EXR
    masks/img_001.png                16-bit, valid where value / 65535 > 0.999 (optional)
    c_masks/                         NeISF++ conductor masks (ignored)

Conversions made by :func:`read_neisf`:

- Cameras: the 3x4 block is LLFF camera-to-world with columns [down, right, backwards] (this is
  how NeISF's code uses it; its README calls it world-to-camera). Converted to OpenCV
  world-to-camera. Intrinsics: single focal f, principal point at the image centre, which with
  our +0.5 pixel centres is (W/2, H/2) + :data:`NEISF_PIXEL_CENTER_OFFSET` (0). NeISF's own ray
  code casts rays through integer pixel coordinates relative to (W/2, H/2), half a pixel off
  from the renderer/LLFF cameras that made the data; we follow the data.
- Stokes: multiplied by :data:`NEISF_STOKES_FACTOR` = 1; NeISF defines s0 = (I0+I45+I90+I135)/2,
  s1 = I0 - I90, s2 = I45 - I135, exactly ours. AoLP direction: none (camera axes right/up/back
  as Mitsuba 3, counter-clockwise).
- Channels: EXR channels are read by name (R, G, B); mask PNG from BGR, its first (R) channel.
- Near/far bounds are ignored.
- Poses: NeISF refuses cameras farther than 1.1 x its bounding-sphere radius 3 from the origin
  (its ``preprocess_camera_normalization.py`` rescales them first). Such poses are read as they
  are, with a warning (:data:`NEISF_BOUNDING_RADIUS`).
- GT normals (optional, ``normals/img_XXX.png``, 16-bit, n = 2 v / 65535 - 1 as in NeISF's
  ``compute_metrics.py``): frame told from the silhouettes and converted to the OpenCV camera
  frame, as for NeRSP (:func:`~polargs_plugin.data.views.load_normal_gt`).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch

from polargs_plugin.data import cameras as cam
from polargs_plugin.data.imageio_utils import check_stokes, read_exr, read_npy, to_hwc, write_exr, write_npy, write_png
from polargs_plugin.data.views import ViewCollector, read_mask
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View

__all__ = ["NEISF_STOKES_FACTOR", "NEISF_PIXEL_CENTER_OFFSET", "NEISF_MASK_THRESHOLD", "read_neisf", "write_neisf"]

NEISF_STOKES_FACTOR = 1.0
"""Stored NeISF EXR Stokes times this factor = our Stokes."""

NEISF_PIXEL_CENTER_OFFSET = 0.0
"""Added to (W/2, H/2) to get our principal point (see the module docstring)."""

NEISF_MASK_THRESHOLD = 0.999
"""A mask pixel is valid where value / 65535 exceeds this (as NeISF)."""

NEISF_BOUNDING_RADIUS = 3.0
"""NeISF's bounding-sphere radius; its loader refuses camera centres beyond 1.1 x this."""

NEISF_NEAR_FAR = (0.0, 6.0)
"""Bounds written into poses_bounds.npy: NeISF's fixed near 0 and far 2 x its sphere radius 3."""


def _image_name(index: int) -> str:
    return f"img_{index + 1:03d}"


def _neisf_mask(first: np.ndarray) -> np.ndarray:
    """Valid mask pixels as NeISF tells them: 16-bit value / 65535 above the threshold."""
    return first / 65535.0 > NEISF_MASK_THRESHOLD


def read_neisf(folder: str | os.PathLike, resolution: int = 1) -> list[View]:
    """Read a NeISF/NeISF++ scene folder into views.

    Args:
        folder: the scene folder holding ``poses_bounds.npy`` and ``images_s0/``.
        resolution: read at this resolution (1, 2, 4, 8 divide the size, above 8: a target
            width; :mod:`polargs_plugin.data.resolution`); float images are kept as float16.

    Returns:
        One :class:`View` per pose row, named ``img_001`` ..., stokes (3, 3, H, W), mask
        (1, H, W) when ``masks/`` exists.
    """
    folder = Path(folder)
    poses_path = folder / "poses_bounds.npy"
    poses_bounds = read_npy(poses_path).astype(np.float64)
    if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
        raise PolarInputError(poses_path, f"shape {poses_bounds.shape}, expected (N, 17)")
    poses = poses_bounds[:, :15].reshape(-1, 3, 5)
    num_s0 = len(list((folder / "images_s0").glob("*.exr")))
    if num_s0 != len(poses):
        raise PolarInputError(folder / "images_s0", f"{num_s0} EXR files for {len(poses)} poses")
    centres = np.linalg.norm(poses[:, :, 3], axis=1)
    if centres.max() > NEISF_BOUNDING_RADIUS * 1.1:
        warnings.warn(
            f"{poses_path}: camera centres up to {centres.max():.3g} from the origin, outside NeISF's normalisation "
            f"(<= {NEISF_BOUNDING_RADIUS * 1.1:.3g}, sphere of radius {NEISF_BOUNDING_RADIUS:g}); NeISF itself refuses these "
            "poses until preprocess_camera_normalization.py rescales them. Read as they are.",
            stacklevel=2,
        )
    collector = ViewCollector(folder, resolution=resolution)
    for index, pose in enumerate(poses):
        name = _image_name(index)
        height, width, focal = pose[:, 4]
        source = f"{poses_path}[row {index}]"
        if not focal > 0 or height != round(height) or width != round(width) or height <= 0 or width <= 0:
            raise PolarInputError(source, f"invalid (H, W, f) = ({height}, {width}, {focal})")
        w2c = cam.llff_to_world_to_camera(pose[:, :4])
        K = np.array(
            [
                [focal, 0, width / 2 + NEISF_PIXEL_CENTER_OFFSET],
                [0, focal, height / 2 + NEISF_PIXEL_CENTER_OFFSET],
                [0, 0, 1],
            ]
        )
        cam.validate_camera(K, w2c, source)
        paths = [folder / f"images_{s}" / f"{name}.exr" for s in ("s0", "s1", "s2")]
        stokes = check_stokes([read_exr(p) for p in paths], paths) * NEISF_STOKES_FACTOR
        if stokes.shape[-2:] != (int(height), int(width)):
            raise PolarInputError(paths[0], f"size {stokes.shape[-2:]} differs from poses_bounds (H, W) = ({height:g}, {width:g})")
        mask = None
        if (folder / "masks").is_dir():
            mask = read_mask(folder / "masks" / f"{name}.png", stokes.shape[-2:], _neisf_mask)
        normal_path = folder / "normals" / f"{name}.png"
        normal_gt = collector.normal_gt(normal_path if normal_path.is_file() else None, mask, w2c, tuple(stokes.shape[-2:]))
        collector.add(name, K, w2c, stokes, mask, normal_gt)
    return collector.finish()


def write_neisf(views: list[View], folder: str | os.PathLike) -> Path:
    """Write views as a NeISF scene folder; each file is written atomically.

    The views must share one K of the NeISF form (fx = fy, principal point at the image centre)
    and have even H and W (NeISF requires it). NeISF itself also expects the cameras inside a
    radius-3 sphere around the object (its ``preprocess_camera_normalization.py``); this writer
    keeps the views' frame as is.
    """
    folder = Path(folder)
    write_masks = any(view.mask is not None for view in views)
    rows = []
    for index, view in enumerate(views):
        K = view.K.double().cpu().numpy()
        height, width = view.height, view.width
        expected = np.array(
            [
                [K[0, 0], 0, width / 2 + NEISF_PIXEL_CENTER_OFFSET],
                [0, K[0, 0], height / 2 + NEISF_PIXEL_CENTER_OFFSET],
                [0, 0, 1],
            ]
        )
        if np.abs(K - expected).max() > 1e-9 * max(1.0, K[0, 0]) or height % 2 or width % 2:
            raise PolarInputError(
                view.source or view.name,
                f"view {view.name}: NeISF needs fx = fy, principal point (W/2, H/2) and even H, W; got K={K.tolist()}, H={height}, W={width}",
            )
        block = cam.world_to_camera_to_llff(view.world_to_camera.double().cpu().numpy())
        hwf = np.array([[height], [width], [K[0, 0]]], dtype=np.float64)
        rows.append(np.concatenate([np.concatenate([block, hwf], axis=1).reshape(-1), NEISF_NEAR_FAR]))
        name = _image_name(index)
        stokes = view.stokes.detach().cpu().float() / NEISF_STOKES_FACTOR
        for s, plane in zip(("s0", "s1", "s2"), stokes):
            write_exr(folder / f"images_{s}" / f"{name}.exr", to_hwc(plane))
        if write_masks:
            valid = torch.ones(height, width, dtype=torch.bool) if view.mask is None else view.mask[0].cpu()
            mask = valid.numpy().astype(np.uint16) * 65535
            write_png(folder / "masks" / f"{name}.png", np.stack([mask] * 3, axis=-1), 16)
    write_npy(folder / "poses_bounds.npy", np.stack(rows))
    return folder
