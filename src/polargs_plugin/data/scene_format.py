"""The project's own polarimetric scene folder: writer and validating reader.

Layout (docs/dataset-format.md has the full description)::

    <folder>/
      cameras.json                  format, version, width, height, bit depth, per view K + world_to_camera
      scene.json                    generator meta (free-form JSON)
      polar/<view>_<angle>.png      RGB angle images, angle in 000 045 090 135; 8- or 16-bit
      masks/<view>.png              8-bit object mask (255 = object)
      normals/<view>.npy            float32 (H, W, 3) camera-frame GT normals
      depth/<view>.npy              float32 (H, W) camera-z GT depth
      diffuse/<view>.npy            float32 (H, W, 3) GT diffuse colour (s0 / 2 units)
      specular/<view>.npy           float32 (H, W, 3) GT specular colour
      highlights/<view>.png         8-bit highlight mask
      overexposed/<view>.png        8-bit overexposure mask
      mesh.ply                      GT mesh of the whole scene (object + floor), world frame
      gt_mesh.ply                   evaluation GT: the object only (docs/evaluation.md)
      visibility.npz                which view sees which triangle of gt_mesh.ply (bit-packed)

Every file is written atomically and ``cameras.json`` is written last, so a folder that has it
is complete. Readers validate everything and raise :class:`~polargs_plugin.io.PolarInputError`
naming the file and the problem.
"""

from __future__ import annotations

import json
import re
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.compact import AngleImages, Deferred
from polargs_plugin.data.imageio_utils import warn_narrow_range
from polargs_plugin.data.resolution import prepare_view, target_size
from polargs_plugin.data.views import warn_unused_files
from polargs_plugin.io import PolarInputError, atomic_path, atomic_write
from polargs_plugin.optics.stokes import POLARIZER_ANGLES_DEG
from polargs_plugin.types import View

if TYPE_CHECKING:
    # Reading a scene's views for training needs neither: open3d (which has no wheels for every
    # Python a trainer runs on) is imported only where a mesh is read or written.
    import open3d as o3d

    from polargs_plugin.data.synthetic import SyntheticScene

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "CAMERAS_FILE",
    "write_scene",
    "SceneWriter",
    "write_meshes",
    "read_scene_folder",
    "read_scene",
    "read_gt_mesh",
    "is_scene_folder",
    "MESH_FILE",
    "GT_MESH_FILE",
    "VISIBILITY_FILE",
    "read_visibility",
]

FORMAT_NAME = "polargs-scene"
FORMAT_VERSION = 1
CAMERAS_FILE = "cameras.json"
META_FILE = "scene.json"
MESH_FILE = "mesh.ply"
GT_MESH_FILE = "gt_mesh.ply"
VISIBILITY_FILE = "visibility.npz"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
_ROTATION_TOL = 1e-5


# ---------------------------------------------------------------------------------------------
# Writing.


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write an (H, W) or (H, W, 3) RGB uint8/uint16 array as PNG, atomically."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"{path}: cv2.imwrite failed")


def _write_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.save(tmp, np.ascontiguousarray(array, dtype=np.float32))


def _mask_png(mask: Tensor) -> np.ndarray:
    return mask[0].numpy().astype(np.uint8) * 255


def _hwc(image: Tensor) -> np.ndarray:
    return image.detach().cpu().permute(1, 2, 0).numpy()


def _angle_path(folder: Path, view_name: str, angle: int) -> Path:
    return folder / "polar" / f"{view_name}_{angle:03d}.png"


def write_scene(scene: SyntheticScene, folder: str | Path) -> Path:
    """Write a :class:`SyntheticScene` as a scene folder (each file atomically, cameras last).

    Angle images are stored at ``scene.meta["quantize_bits"]`` bits (8 or 16; 16 when absent), so
    quantised images round-trip exactly.

    Args:
        scene: the scene to write.
        folder: output folder (created; existing files with the same names are replaced).

    Returns:
        the folder path.
    """
    writer = SceneWriter(folder, int(scene.meta.get("quantize_bits", 16)))
    writer.add(scene)
    return writer.finish(scene)


class SceneWriter:
    """Writes a scene folder view by view (:func:`write_scene` in parts, e.g. for views rendered
    one at a time by :func:`~polargs_plugin.data.synthetic.generate_scene_views`).

    Args:
        folder: output folder (created; existing files with the same names are replaced).
        bits: bit depth of the angle images, 8 or 16.
    """

    def __init__(self, folder: str | Path, bits: int):
        if bits not in (8, 16):
            raise ValueError(f"quantize_bits must be 8 or 16 to write PNG angle images, got {bits}")
        self.folder, self.bits = Path(folder), bits
        self.size: tuple[int, int] | None = None  # (H, W) of the first view
        self.cameras: list[dict] = []
        self.visibility: list[np.ndarray] = []  # per part, (views, F) rows of the object's triangles

    def add(self, scene: SyntheticScene) -> None:
        """Write the files of every view of ``scene`` (all views share one size)."""
        folder = self.folder
        dtype, levels = (np.uint8, 255) if self.bits == 8 else (np.uint16, 65535)
        for index, view in enumerate(scene.views):
            self.size = self.size or (view.height, view.width)
            if (view.height, view.width) != self.size:
                raise ValueError(f"view {view.name} is {view.width}x{view.height}, expected {self.size[1]}x{self.size[0]}")
            for angle, image in zip(POLARIZER_ANGLES_DEG, scene.angle_images[index]):
                pixels = np.round(np.clip(_hwc(image), 0.0, 1.0) * levels).astype(dtype)
                _write_png(_angle_path(folder, view.name, angle), pixels)
            if view.mask is not None:
                _write_png(folder / "masks" / f"{view.name}.png", _mask_png(view.mask))
            if view.normal_gt is not None:
                _write_npy(folder / "normals" / f"{view.name}.npy", _hwc(view.normal_gt))
            if view.depth_gt is not None:
                _write_npy(folder / "depth" / f"{view.name}.npy", view.depth_gt[0].numpy())
            _write_npy(folder / "diffuse" / f"{view.name}.npy", _hwc(scene.diffuse_gt[index]))
            _write_npy(folder / "specular" / f"{view.name}.npy", _hwc(scene.specular_gt[index]))
            _write_png(folder / "highlights" / f"{view.name}.png", _mask_png(scene.highlight_masks[index]))
            _write_png(folder / "overexposed" / f"{view.name}.png", _mask_png(scene.overexposed_masks[index]))
            self.cameras.append(
                {
                    "name": view.name,
                    "K": view.K.to(torch.float64).tolist(),
                    "world_to_camera": view.world_to_camera.to(torch.float64).tolist(),
                }
            )
        if scene.visibility is not None:
            self.visibility.append(np.asarray(scene.visibility, dtype=bool))

    def finish(self, scene: SyntheticScene) -> Path:
        """Write the meshes and the meta of ``scene``, then ``cameras.json`` (last: a folder that
        has it is complete); the folder path."""
        from polargs_plugin.data.synthetic import triangle_ranges

        if self.size is None:
            raise ValueError("the scene has no views")
        write_meshes(scene, self.folder)
        if self.visibility:
            _write_visibility(self.folder / VISIBILITY_FILE, np.concatenate(self.visibility))
        with atomic_write(self.folder / META_FILE) as handle:
            meta = {"name": scene.name, **scene.meta}
            if scene.object_triangles is not None:
                meta["object_triangles"] = triangle_ranges(scene.object_triangles)
            json.dump(meta, handle, indent=2)
        header = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "width": self.size[1],
            "height": self.size[0],
            "bit_depth": self.bits,
            "angles_deg": list(POLARIZER_ANGLES_DEG),
            "color": "RGB",
            "views": self.cameras,
        }
        with atomic_write(self.folder / CAMERAS_FILE) as handle:
            json.dump(header, handle, indent=1)
        return self.folder


def write_meshes(scene: SyntheticScene, folder: str | Path) -> None:
    """The scene's whole mesh as ``mesh.ply`` and the object alone as ``gt_mesh.ply`` (the
    evaluation ground truth), each written atomically."""
    import open3d as o3d

    folder = Path(folder)
    for name, (vertices, triangles) in (
        (MESH_FILE, (scene.mesh_vertices, scene.mesh_triangles)),
        (GT_MESH_FILE, scene.object_mesh()),
    ):
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
            o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)),
        )
        with atomic_path(folder / name) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
                raise OSError(f"{folder / name}: open3d could not write the mesh")


def _write_visibility(path: Path, visibility: np.ndarray) -> None:
    """visibility.npz: ``bits`` (the (V, F) bool array, bit-packed along F) and ``shape``."""
    visibility = np.asarray(visibility, dtype=bool)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, bits=np.packbits(visibility, axis=1), shape=np.asarray(visibility.shape, np.int64))


# ---------------------------------------------------------------------------------------------
# Reading.


def read_visibility(folder: str | Path, num_views: int, num_triangles: int) -> np.ndarray | None:
    """The (num_views, num_triangles) bool per-view visibility of ``gt_mesh.ply``'s triangles, or
    None when the folder has none (written before it existed, or not by the generator).

    Raises:
        PolarInputError: unreadable, or its shape does not fit the views and the mesh.
    """
    path = Path(folder) / VISIBILITY_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            bits, shape = data["bits"], tuple(int(v) for v in data["shape"])
    except (OSError, ValueError, KeyError) as err:
        raise PolarInputError(path, f"unreadable visibility ({err})") from None
    if shape != (num_views, num_triangles) or bits.shape != (num_views, (num_triangles + 7) // 8):
        raise PolarInputError(path, f"visibility has shape {shape}, expected ({num_views}, {num_triangles}): "
                              "views x triangles of gt_mesh.ply")
    return np.unpackbits(bits, axis=1, count=num_triangles).astype(bool)


def is_scene_folder(folder: str | Path) -> bool:
    """True if ``folder`` holds a ``cameras.json`` of this format (cheap check for format sniffing)."""
    path = Path(folder) / CAMERAS_FILE
    if not path.is_file():
        return False
    try:
        return json.loads(path.read_text()).get("format") == FORMAT_NAME
    except (OSError, ValueError, AttributeError):
        return False


def _matrix(entry: dict, key: str, shape: tuple[int, int], path: Path, view: str) -> np.ndarray:
    try:
        matrix = np.asarray(entry[key], dtype=np.float64)
    except KeyError:
        raise PolarInputError(path, f"view {view!r} has no {key!r}") from None
    except (TypeError, ValueError):
        raise PolarInputError(path, f"view {view!r}: {key} is not a numeric matrix") from None
    if matrix.shape != shape:
        raise PolarInputError(path, f"view {view!r}: {key} has shape {matrix.shape}, expected {shape}")
    if not np.isfinite(matrix).all():
        raise PolarInputError(path, f"view {view!r}: {key} has non-finite entries")
    return matrix


def _check_camera(K: np.ndarray, w2c: np.ndarray, path: Path, view: str) -> None:
    if abs(np.linalg.det(K)) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise PolarInputError(path, f"view {view!r}: K is singular or has non-positive focal lengths")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise PolarInputError(path, f"view {view!r}: K is not an upper-triangular pinhole matrix with last row (0, 0, 1)")
    if not np.allclose(w2c[3], [0.0, 0.0, 0.0, 1.0]):
        raise PolarInputError(path, f"view {view!r}: world_to_camera last row is not (0, 0, 0, 1)")
    rotation = w2c[:3, :3]
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(rotation) < 0:
        raise PolarInputError(path, f"view {view!r}: world_to_camera rotation is singular or not a proper rotation")


def _read_header(folder: Path) -> dict:
    if not folder.is_dir():
        raise PolarInputError(folder, "not a folder")
    path = folder / CAMERAS_FILE
    if not path.is_file():
        raise PolarInputError(path, "missing (not a polargs scene folder, or writing did not finish)")
    try:
        header = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise PolarInputError(path, f"unreadable JSON ({err})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise PolarInputError(path, f"not a {FORMAT_NAME} cameras file (format={header.get('format') if isinstance(header, dict) else None!r})")
    version = header.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
        raise PolarInputError(path, f"unsupported format_version {version!r} (this reader knows 1..{FORMAT_VERSION})")
    for key in ("width", "height"):
        if not isinstance(header.get(key), int) or header[key] < 1:
            raise PolarInputError(path, f"{key} must be a positive integer, got {header.get(key)!r}")
    if header.get("bit_depth") not in (8, 16):
        raise PolarInputError(path, f"bit_depth must be 8 or 16, got {header.get('bit_depth')!r}")
    if list(header.get("angles_deg", [])) != list(POLARIZER_ANGLES_DEG):
        raise PolarInputError(path, f"angles_deg must be {list(POLARIZER_ANGLES_DEG)}, got {header.get('angles_deg')!r}")
    views = header.get("views")
    if not isinstance(views, list) or not views:
        raise PolarInputError(path, "no views listed")
    names = set()
    for entry in views:
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise PolarInputError(path, f"bad view name {name!r} (letters, digits, _ . - only)")
        if name in names:
            raise PolarInputError(path, f"duplicate view name {name!r}")
        names.add(name)
    return header


def _read_png(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise PolarInputError(path, f"missing {what}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise PolarInputError(path, f"unreadable {what} (not a PNG image)")
    if image.ndim == 3:
        if image.shape[2] != 3:
            raise PolarInputError(path, f"{what} has {image.shape[2]} channels, expected 3 (RGB) or 1")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


def _read_angles(folder: Path, name: str, header: dict) -> AngleImages:
    """The four angle images of a view as read (8/16-bit integers, (4, C, H, W)), validated."""
    images, first, peak = [], None, 0
    for angle in POLARIZER_ANGLES_DEG:
        path = _angle_path(folder, name, angle)
        image = _read_png(path, f"{angle} deg angle image of view {name!r}")
        if image.dtype not in (np.uint8, np.uint16):
            raise PolarInputError(path, f"dtype {image.dtype}, expected uint8 or uint16")
        if first is None:
            bits = 8 * image.dtype.itemsize
            if bits != header["bit_depth"]:  # read by the dtype's range, it would be 257 times too dark or bright
                raise PolarInputError(path, f"{bits}-bit image, but {CAMERAS_FILE} declares bit_depth {header['bit_depth']}")
            first = (path, image)
            if image.shape[:2] != (header["height"], header["width"]):
                raise PolarInputError(
                    path, f"size {image.shape[1]}x{image.shape[0]} differs from cameras.json {header['width']}x{header['height']}"
                )
        elif image.dtype != first[1].dtype or image.shape != first[1].shape:
            raise PolarInputError(
                path, f"{image.dtype} {image.shape} differs from {first[0].name} ({first[1].dtype} {first[1].shape})"
            )
        if image.max() == 0:
            raise PolarInputError(path, "image is all dark (every pixel 0)")
        peak = max(peak, int(image.max()))
        images.append(image)
    warn_narrow_range(peak, header["bit_depth"], first[0], f"{CAMERAS_FILE} declares bit_depth {header['bit_depth']}")
    stacked = np.stack(images)
    if stacked.ndim == 3:
        stacked = stacked[..., None]
    angles = torch.from_numpy(np.ascontiguousarray(stacked.transpose(0, 3, 1, 2)))
    return AngleImages(angles, np.iinfo(stacked.dtype).max)


def _read_mask(path: Path, shape: tuple[int, int], what: str) -> Tensor:
    image = _read_png(path, what)
    if image.ndim != 2 or image.shape != shape:
        raise PolarInputError(path, f"{what} has shape {image.shape}, expected a single-channel {shape[1]}x{shape[0]} image")
    return torch.from_numpy(image > 0).unsqueeze(0)


def _open_npy(path: Path, shape: tuple[int, ...], what: str, mmap: bool = False) -> np.ndarray:
    """The array of a GT ``.npy`` file, its shape and dtype checked (``mmap``: its header only is read now)."""
    try:
        array = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise PolarInputError(path, f"unreadable {what} ({err})") from None
    if array.shape != shape:
        raise PolarInputError(path, f"{what} has shape {array.shape}, expected {shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise PolarInputError(path, f"{what} has dtype {array.dtype}, expected float")
    return array


def _read_npy(path: Path, shape: tuple[int, ...], what: str) -> Tensor:
    array = _open_npy(path, shape, what)
    if not np.isfinite(array).all():
        raise PolarInputError(path, f"{what} has NaN or infinite values")
    tensor = torch.from_numpy(array.astype(np.float32))
    return tensor.permute(2, 0, 1).contiguous() if tensor.ndim == 3 else tensor.unsqueeze(0)


def _deferred_npy(path: Path, shape: tuple[int, ...], what: str) -> Deferred:
    """A GT map left in its ``.npy`` file until read (:func:`_read_npy` then, which checks its
    values); its shape and dtype are checked now from the file's header."""
    _open_npy(path, shape, what, mmap=True)
    channels = shape[2] if len(shape) == 3 else 1
    return Deferred(partial(_read_npy, path, shape, what), (channels, *shape[:2]))


def _read_views(folder: Path, header: dict, resolution: int = 1) -> list[View]:
    """The views of a validated header, at ``resolution`` (:mod:`polargs_plugin.data.resolution`)."""
    cameras_path = folder / CAMERAS_FILE
    shape = (header["height"], header["width"])
    views = []
    for entry in header["views"]:
        name = entry["name"]
        K = _matrix(entry, "K", (3, 3), cameras_path, name)
        w2c = _matrix(entry, "world_to_camera", (4, 4), cameras_path, name)
        _check_camera(K, w2c, cameras_path, name)
        mask_path, normal_path, depth_path = (
            folder / "masks" / f"{name}.png",
            folder / "normals" / f"{name}.npy",
            folder / "depth" / f"{name}.npy",
        )
        view = View(
            name=name,
            K=torch.from_numpy(K),
            world_to_camera=torch.from_numpy(w2c),
            stokes=_read_angles(folder, name, header),
            mask=_read_mask(mask_path, shape, "mask") if mask_path.exists() else None,
            normal_gt=_deferred_npy(normal_path, (*shape, 3), "GT normal map") if normal_path.exists() else None,
            depth_gt=_deferred_npy(depth_path, shape, "GT depth map") if depth_path.exists() else None,
            source=str(folder),
        )
        views.append(prepare_view(view, resolution))
    return views


def read_scene_folder(folder: str | Path, resolution: int = 1) -> list[View]:
    """Read a scene folder into :class:`View` objects (Stokes from the angle images).

    Masks, GT normals and GT depth are loaded when their files exist. The views keep the
    integer angle images (their Stokes are decoded from them on each read, bit for bit the
    float32 Stokes of the images); the GT maps stay in their files until read, their headers
    checked now and their values when read (:mod:`polargs_plugin.compact`).

    Args:
        folder: the scene folder.
        resolution: read at this resolution (1, 2, 4, 8 divide the size, above 8: a target
            width; :mod:`polargs_plugin.data.resolution`).

    Returns:
        the views in ``cameras.json`` order; K and world_to_camera float64, stokes (3, C, H, W)
        float32.

    Raises:
        PolarInputError: missing or unreadable file, size/dtype mismatch between angle images,
            an all-dark angle image, NaN/inf in a GT map, or non-finite/singular cameras.
    """
    folder = Path(folder)
    header = _read_header(folder)
    _check_resolution(folder / CAMERAS_FILE, header, resolution)
    views = _read_views(folder, header, resolution)
    _warn_unlisted_views(folder, {view.name for view in views})
    return views


#: The per-view folders of a scene folder (each file named after its view; ``polar/`` adds the angle).
_VIEW_FOLDERS = ("polar", "masks", "normals", "depth", "diffuse", "specular", "highlights", "overexposed")


def _view_of_file(path: Path) -> str:
    """The view a per-view file belongs to: ``polar/<view>_<angle>.png``, else ``<folder>/<view>.<ext>``."""
    return path.stem.rsplit("_", 1)[0] if path.parent.name == "polar" else path.stem


def _warn_unlisted_views(folder: Path, listed: set[str]) -> None:
    """One warning naming the per-view files of views ``cameras.json`` does not list."""
    files = [path for sub in _VIEW_FOLDERS if (folder / sub).is_dir() for path in (folder / sub).iterdir()
             if path.is_file() and not path.name.startswith(".")]
    warn_unused_files(folder, files, listed, _view_of_file, f"their views are not listed in {CAMERAS_FILE}", stacklevel=4)


def _check_resolution(path: Path, header: dict, resolution: int) -> None:
    try:
        target_size(header["width"], header["height"], resolution)
    except ValueError as err:
        raise PolarInputError(path, f"--resolution: {err}") from None


def read_gt_mesh(folder: str | Path, object_only: bool = True) -> o3d.geometry.TriangleMesh:
    """A ground-truth mesh of a scene folder (world frame).

    Args:
        folder: the scene folder.
        object_only: the evaluation ground truth ``gt_mesh.ply`` (the object without floor or
            backdrop; folders written before it existed fall back to ``mesh.ply``) if True,
            the whole scene ``mesh.ply`` if False.

    Raises:
        PolarInputError: the file is missing, unreadable or has no triangles.
    """
    import open3d as o3d

    folder = Path(folder)
    path = folder / MESH_FILE
    if object_only and (folder / GT_MESH_FILE).is_file():
        path = folder / GT_MESH_FILE
    if not path.is_file():
        raise PolarInputError(path, "missing ground-truth mesh")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise PolarInputError(path, "mesh has no triangles (unreadable or empty)")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise PolarInputError(path, "mesh has non-finite vertices")
    return mesh


def read_scene(folder: str | Path) -> SyntheticScene:
    """Read back everything :func:`write_scene` wrote, as a :class:`SyntheticScene`.

    Raises:
        PolarInputError: as :func:`read_scene_folder`, or a missing/malformed GT file or meta.
    """
    from polargs_plugin.data.synthetic import SyntheticScene, mask_from_ranges

    folder = Path(folder)
    header = _read_header(folder)
    views = _read_views(folder, header)
    angle_images = [view.stored("stokes").intensities() for view in views]
    shape = (header["height"], header["width"])
    meta_path = folder / META_FILE
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise PolarInputError(meta_path, "missing scene meta") from None
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise PolarInputError(meta_path, f"unreadable JSON ({err})") from None
    if not isinstance(meta, dict):
        raise PolarInputError(meta_path, "scene meta must be a JSON object")
    mesh = read_gt_mesh(folder, object_only=False)
    ranges = meta.get("object_triangles")
    try:
        object_triangles = None if ranges is None else mask_from_ranges(ranges, len(mesh.triangles))
    except (TypeError, ValueError) as err:
        raise PolarInputError(meta_path, f"bad object_triangles ({err})") from None

    def npy(sub: str, name: str, what: str) -> Tensor:
        path = folder / sub / f"{name}.npy"
        if not path.is_file():
            raise PolarInputError(path, f"missing {what}")
        return _read_npy(path, (*shape, 3), what)

    return SyntheticScene(
        name=str(meta.pop("name", folder.name)),
        views=views,
        angle_images=angle_images,
        diffuse_gt=[npy("diffuse", v.name, "GT diffuse colour") for v in views],
        specular_gt=[npy("specular", v.name, "GT specular colour") for v in views],
        highlight_masks=[_read_mask(folder / "highlights" / f"{v.name}.png", shape, "highlight mask") for v in views],
        overexposed_masks=[_read_mask(folder / "overexposed" / f"{v.name}.png", shape, "overexposure mask") for v in views],
        mesh_vertices=np.asarray(mesh.vertices, dtype=np.float64),
        mesh_triangles=np.asarray(mesh.triangles, dtype=np.int64),
        meta=meta,
        object_triangles=object_triangles,
        visibility=read_visibility(folder, len(views), len(read_gt_mesh(folder).triangles)),
    )
