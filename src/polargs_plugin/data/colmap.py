"""COLMAP sparse models: reader (text or binary, no pycolmap needed) and text writer.

Conventions: COLMAP stores world-to-camera (qvec (w, x, y, z), tvec) in OpenCV axes, and its
pixel centres are at +0.5 (the upper-left pixel's centre is (0.5, 0.5)) like ours, so K is taken
unchanged. Camera models with distortion are accepted only when every distortion coefficient
is zero (undistort first with ``colmap image_undistorter``).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from polargs_plugin.data import cameras as cam
from polargs_plugin.io import PolarInputError, atomic_write

if TYPE_CHECKING:
    from polargs_plugin.types import View

__all__ = ["ColmapCamera", "read_colmap_model", "write_colmap_text", "write_colmap_binary", "find_colmap_model",
           "write_colmap_scene"]

# COLMAP camera models: id -> (name, number of params).
# The pinhole params are f, cx, cy (1 focal) or fx, fy, cx, cy (2 focals); the rest is distortion.
_COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
_SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "FOV"}
_MODEL_PARAMS = dict(_COLMAP_MODELS.values())

@dataclass
class ColmapCamera:
    """One registered COLMAP image: K (3, 3), world_to_camera (4, 4), image size."""

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int


def _intrinsics(model: str, params: np.ndarray, source: str) -> np.ndarray:
    if model not in _MODEL_PARAMS or len(params) != _MODEL_PARAMS[model]:
        raise PolarInputError(source, f"camera model {model} with {len(params)} parameters is not supported")
    single = model in _SINGLE_FOCAL
    fx, fy, cx, cy = (params[0], params[0], params[1], params[2]) if single else params[:4]
    distortion = params[3:] if single else params[4:]
    if np.any(np.abs(distortion) > 0):
        raise PolarInputError(
            source, f"camera model {model} has non-zero distortion {distortion.tolist()}; undistort first (colmap image_undistorter)"
        )
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


def _read_text_model(model_dir: Path) -> tuple[dict, list]:
    """cameras.txt, images.txt -> ({camera_id: (model, W, H, params)}, [(name, qvec, tvec, camera_id)])."""

    def rows(path: Path) -> list[list[str]]:
        if not path.is_file():
            raise PolarInputError(path, "file not found")
        return [line.split() for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#")]

    cameras = {}
    for row in rows(model_dir / "cameras.txt"):
        try:
            cameras[int(row[0])] = (row[1], int(row[2]), int(row[3]), np.array(row[4:], dtype=np.float64))
        except (IndexError, ValueError):
            raise PolarInputError(model_dir / "cameras.txt", f"malformed camera line {' '.join(row)!r}") from None
    images = []
    # images.txt alternates image lines (10 fields) and points2D lines (3 fields per point, or
    # empty and dropped above), so the image lines are those with exactly 10 fields.
    for row in rows(model_dir / "images.txt"):
        if len(row) == 10 and row[0].isdigit():
            try:
                images.append((row[9], np.array(row[1:5], float), np.array(row[5:8], float), int(row[8])))
            except ValueError:
                raise PolarInputError(model_dir / "images.txt", f"malformed image line {' '.join(row)!r}") from None
    return cameras, images


def _read_binary_model(model_dir: Path) -> tuple[dict, list]:
    """cameras.bin, images.bin (COLMAP's little-endian binary model) -> as :func:`_read_text_model`."""
    cameras = {}
    path = model_dir / "cameras.bin"
    try:
        with open(path, "rb") as f:
            (count,) = struct.unpack("<Q", f.read(8))
            for _ in range(count):
                camera_id, model_id, width, height = struct.unpack("<iiQQ", f.read(24))
                if model_id not in _COLMAP_MODELS:
                    raise PolarInputError(path, f"unknown camera model id {model_id}")
                name, num_params = _COLMAP_MODELS[model_id]
                params = np.array(struct.unpack(f"<{num_params}d", f.read(8 * num_params)))
                cameras[camera_id] = (name, width, height, params)
        images = []
        path = model_dir / "images.bin"
        with open(path, "rb") as f:
            (count,) = struct.unpack("<Q", f.read(8))
            for _ in range(count):
                values = struct.unpack("<i7di", f.read(64))
                name = b""
                while (char := f.read(1)) not in (b"\x00", b""):
                    name += char
                (num_points,) = struct.unpack("<Q", f.read(8))
                f.seek(24 * num_points, os.SEEK_CUR)  # x, y (double) and point3D id (int64) each
                images.append((name.decode(), np.array(values[1:5]), np.array(values[5:8]), values[8]))
    except FileNotFoundError:
        raise PolarInputError(path, "file not found") from None
    except struct.error:
        raise PolarInputError(path, "truncated or malformed COLMAP binary file") from None
    return cameras, images


def read_colmap_model(model_dir: str | os.PathLike) -> dict[str, ColmapCamera]:
    """Parse a COLMAP sparse model (text or binary, no pycolmap needed).

    Returns:
        {image name as written in the model: ColmapCamera}.
    """
    model_dir = Path(model_dir)
    text = (model_dir / "cameras.txt").is_file()
    cameras, images = _read_text_model(model_dir) if text else _read_binary_model(model_dir)
    source = model_dir / ("images.txt" if text else "images.bin")
    result = {}
    for name, qvec, tvec, camera_id in images:
        if camera_id not in cameras:
            raise PolarInputError(source, f"image {name} refers to unknown camera {camera_id}")
        model, width, height, params = cameras[camera_id]
        K = _intrinsics(model, params, f"{model_dir}[camera {camera_id}]")
        if not (np.isfinite(qvec).all() and np.linalg.norm(qvec) > 0):
            raise PolarInputError(source, f"image {name}: invalid quaternion {qvec.tolist()}")
        w2c = np.eye(4)
        w2c[:3, :3] = cam.qvec_to_rotmat(qvec)
        w2c[:3, 3] = tvec
        cam.validate_camera(K, w2c, f"{source}[{name}]")
        result[name] = ColmapCamera(K, w2c, int(width), int(height))
    return result


def _numbers(values: np.ndarray) -> list[str]:
    return [repr(float(v)) for v in values]  # repr: shortest text that parses back exactly


def _model_rows(cameras: dict[str, ColmapCamera], points: np.ndarray | None, colors: np.ndarray | None
                ) -> tuple[list[tuple[int, np.ndarray, int, int]], list[tuple[int, np.ndarray, np.ndarray, str]],
                           list[tuple[int, np.ndarray, np.ndarray]]]:
    """The rows of a COLMAP model, one PINHOLE camera per image: cameras (id, fx fy cx cy, W, H),
    images (id, qvec, tvec, name; camera id = image id), points (id, xyz, rgb uint8)."""
    camera_rows, image_rows = [], []
    for index, (name, camera) in enumerate(cameras.items(), start=1):
        if abs(camera.K[0, 1]) > 1e-12:
            raise PolarInputError(name, "COLMAP cameras cannot hold a skewed K")
        camera_rows.append((index, camera.K[[0, 1, 0, 1], [0, 1, 2, 2]], camera.width, camera.height))  # fx, fy, cx, cy
        qvec = cam.rotmat_to_qvec(camera.world_to_camera[:3, :3])
        image_rows.append((index, qvec, camera.world_to_camera[:3, 3], name))
    point_rows = []
    if points is not None:
        rgb = np.full((len(points), 3), 128, dtype=np.uint8) if colors is None else np.asarray(colors, dtype=np.uint8)
        point_rows = list(zip(range(1, len(points) + 1), np.asarray(points, dtype=np.float64), rgb))
    return camera_rows, image_rows, point_rows


def write_colmap_text(
    model_dir: str | os.PathLike,
    cameras: dict[str, ColmapCamera],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write a COLMAP text model (PINHOLE cameras, one per image), atomically per file.

    Args:
        model_dir: the model folder (``sparse/0``).
        cameras: image name -> camera.
        points: optional (P, 3) 3D points (world frame), written without tracks; none by default.
        colors: (P, 3) uint8 colours of ``points`` (default mid-grey).
    """
    model_dir = Path(model_dir)
    camera_rows, image_rows, point_rows = _model_rows(cameras, points, colors)
    camera_lines = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    camera_lines += [" ".join([str(i), "PINHOLE", str(w), str(h), *_numbers(pinhole)]) for i, pinhole, w, h in camera_rows]
    image_lines = ["# Image list"]
    for index, qvec, tvec, name in image_rows:
        image_lines += [" ".join([str(index), *_numbers(qvec), *_numbers(tvec), str(index), name]), ""]  # no 2D points
    point_lines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"]
    point_lines += [" ".join([str(i), *_numbers(xyz), *(str(int(c)) for c in rgb), "0.0"]) for i, xyz, rgb in point_rows]
    for filename, lines in (("cameras.txt", camera_lines), ("images.txt", image_lines), ("points3D.txt", point_lines)):
        with atomic_write(model_dir / filename) as f:
            f.write("\n".join(lines) + "\n")
    return model_dir


_PINHOLE_ID = 1


def write_colmap_binary(
    model_dir: str | os.PathLike,
    cameras: dict[str, ColmapCamera],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """:func:`write_colmap_text`'s model in COLMAP's binary form (``cameras.bin``, ``images.bin``,
    ``points3D.bin``, little-endian, the layout COLMAP writes by default), the form some readers
    require (gsplat 1.5's COLMAP parser reads only that one)."""
    model_dir = Path(model_dir)
    camera_rows, image_rows, point_rows = _model_rows(cameras, points, colors)
    with atomic_write(model_dir / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(camera_rows)))
        for index, pinhole, width, height in camera_rows:
            f.write(struct.pack("<iiQQ4d", index, _PINHOLE_ID, width, height, *map(float, pinhole)))
    with atomic_write(model_dir / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(image_rows)))
        for index, qvec, tvec, name in image_rows:
            f.write(struct.pack("<i7di", index, *map(float, qvec), *map(float, tvec), index))
            f.write(name.encode() + b"\x00" + struct.pack("<Q", 0))  # no 2D points
    with atomic_write(model_dir / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(point_rows)))
        for index, xyz, rgb in point_rows:
            f.write(struct.pack("<Q3d3BdQ", index, *map(float, xyz), *map(int, rgb), 0.0, 0))  # error 0, no track
    return model_dir


def find_colmap_model(folder: str | os.PathLike) -> Path | None:
    """The first of ``sparse/0``, ``sparse``, ``.`` holding cameras + images (.txt or .bin)."""
    folder = Path(folder)
    for candidate in (folder / "sparse" / "0", folder / "sparse", folder):
        if any((candidate / f"cameras{ext}").is_file() and (candidate / f"images{ext}").is_file() for ext in (".txt", ".bin")):
            return candidate
    return None


def write_colmap_scene(folder: str | os.PathLike, views: "Sequence[View]", points: np.ndarray,
                       colors: np.ndarray | None = None) -> Path:
    """A scene as an upstream trainer's COLMAP input: ``images/<name>.png`` (the training colour
    s0 / 2 of each view, 8 bits) and the sparse model (PINHOLE cameras, ``points`` as the sparse
    points the trainer initialises from) twice: in ``sparse/0``, where graphdeco, GOF and 2DGS
    read it, and in ``sparse``, where PGSR does, each as text and as binary files (COLMAP's own
    default, the only form gsplat 1.5's parser reads). Image names are the view names, so a
    patched trainer finds each camera's polarimetric view by name."""
    from polargs_plugin.data.imageio_utils import write_png

    folder = Path(folder)
    cameras = {}
    for view in views:
        image = view.image.clamp(0.0, 1.0).permute(1, 2, 0).numpy()
        write_png(folder / "images" / f"{view.name}.png", image)
        cameras[f"{view.name}.png"] = ColmapCamera(
            view.K.double().numpy(), view.world_to_camera.double().numpy(), view.width, view.height
        )
    for model_dir in (folder / "sparse" / "0", folder / "sparse"):
        write_colmap_text(model_dir, cameras, points, colors)
        write_colmap_binary(model_dir, cameras, points, colors)
    return folder
