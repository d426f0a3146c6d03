"""Writing a bundled synthetic scene as a scene folder, atomically (``polargs generate``)."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Literal

from polargs_plugin.io import PolarInputError, current_umask

if TYPE_CHECKING:
    from polargs_plugin.data.synthetic import SyntheticScene
    from polargs_plugin.types import View

__all__ = ["SceneRequest", "GeneratedScene", "SceneStatistics", "generate_scene_folder", "scene_statistics", "EXPORTS",
           "EXPORT_POINTS"]

#: Trainer inputs ``generate_scene_folder`` can write beside the scene: ``colmap`` is the input of
#: the graphdeco-family trainers (``OUT/colmap``: images and a sparse model).
EXPORTS: tuple[str, ...] = ("colmap",)
#: Sparse points of the COLMAP export, drawn from the ground-truth mesh's vertices.
EXPORT_POINTS = 1000

#: Files that mark a folder as a scene folder that ``overwrite`` may replace.
SCENE_MARKERS = ("scene.json", "cameras.json", "gt_mesh.ply")


@dataclass(frozen=True)
class SceneRequest:
    """A bundled scene, or a scene of the procedural family, to render (``polargs generate --help``
    lists the scenes; docs/scene-family.md describes the family).

    Attributes:
        scene: the scene's name, or ``family`` (the family scene of ``seed``).
        views: number of cameras; None: 24 for a bundled scene, the seed's for the family.
        width, height: image size in pixels; None: 128x128 for a bundled scene, the seed's for the family.
        seed: sensor-noise seed (default 0); for the family also the scene's seed.
        noise_std: Gaussian noise std per angle image, [0, 1] units; None: the generator's 0.005,
            the seed's for the family.
        bits: sensor bit depth, 8 or 16; None: the generator's 8.
        refractive_index: n of the Fresnel DoLP; None: the generator's 1.5 (a family scene's
            materials have their own).
        mask: what the masks mark: ``object`` (default) or ``surface`` (every surface, a floor too).
        pictures: also write AoLP / DoLP pictures per view and an overview under ``pictures/``.
        mosaic: write a polar folder of division-of-focal-plane raw frames instead of a scene
            folder: ``rgb`` (IMX250MYR: RGGB Bayer under the polarizer grid) or ``mono``
            (IMX250MZR, the channel mean), one ``raw/<view>.png`` per view at ``bits`` bits, with
            ``masks/``, the ground-truth meshes and (``cameras``) the cameras as a COLMAP model
            ``sparse/0``. The frame is the rendered size (a 2448x2048 frame holds 1224x1024 per
            polarizer angle). None (default): a scene folder.
        cameras: with ``mosaic``, write the COLMAP model (default True; False leaves it to SfM).
        floor_texture: a key of :data:`~polargs_plugin.data.scenes.FLOOR_TEXTURES` for the floor
            of a scene that has one (``speckle`` gives SfM features); None: the scene's own.
    """

    scene: str
    views: int | None = None
    width: int | None = None
    height: int | None = None
    seed: int = 0
    noise_std: float | None = None
    bits: int | None = None
    refractive_index: float | None = None
    mask: Literal["object", "surface"] | None = None
    pictures: bool = False
    mosaic: Literal["mono", "rgb"] | None = None
    cameras: bool = True
    floor_texture: str | None = None

    def render(self, progress: bool = False) -> "SyntheticScene":
        """Render the scene (the generator's defaults for every setting left None)."""
        from polargs_plugin.data.synthetic import assemble_scene

        return assemble_scene(self.render_views(progress))

    def render_views(self, progress: bool = False) -> Iterator["SyntheticScene"]:
        """:meth:`render` one view at a time (each item holds the next view)."""
        from polargs_plugin.data.family import FAMILY, generate_family_scene_views
        from polargs_plugin.data.synthetic import generate_scene_views

        given = {"noise_std": self.noise_std, "quantize_bits": self.bits, "mask": self.mask,
                 "floor_texture": self.floor_texture}
        given = {k: v for k, v in given.items() if v is not None}
        if self.scene == FAMILY:
            size = None if self.width is None and self.height is None else (self.width or self.height, self.height or self.width)
            return generate_family_scene_views(self.seed, num_views=self.views, size=size, progress=progress, **given)
        if self.refractive_index is not None:
            given["refractive_index"] = self.refractive_index
        return generate_scene_views(self.scene, num_views=self.views or 24, width=self.width or 128,
                                    height=self.height or 128, seed=self.seed, progress=progress, **given)


@dataclass
class GeneratedScene:
    """A scene folder just written.

    Attributes:
        folder: the scene folder.
        name: the scene's name.
        meta: the generator's description of the scene (``scene.json``).
        num_views: views written.
        statistics: :func:`scene_statistics` of the scene.
        pictures: number of pictures written.
        render_seconds, write_seconds: wall times.
    """

    folder: Path
    name: str
    meta: dict[str, Any]
    num_views: int
    statistics: dict[str, Any]
    pictures: int
    render_seconds: float
    write_seconds: float


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise PolarInputError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise PolarInputError(out, "exists and is not empty; choose another --out, or pass --overwrite to replace the scene in it")
        if not any((out / name).is_file() for name in SCENE_MARKERS):
            raise PolarInputError(out, f"--overwrite replaces scene folders only (with {' or '.join(SCENE_MARKERS)}); "
                                  "this one is not: remove it yourself if it should go")


class _Pictures:
    """AoLP / DoLP pictures of each view as it is written, and an overview of a few views (rows:
    s0 / AoLP / DoLP / AoLP-with-DoLP columns) at the end."""

    def __init__(self, folder: Path):
        self.folder, self.count, self.rows = folder / "pictures", 0, []
        self.index = 0

    def add(self, view: "View", num_views: int) -> None:
        from polargs_plugin.viz import polar_panels, save_polar_pictures

        self.count += len(save_polar_pictures(view.stokes, self.folder, view.name))
        if self.index % max(1, num_views // 4) == 0 and len(self.rows) < 4:
            panels = polar_panels(view.stokes)
            self.rows.append([panels[k] for k in ("s0", "aolp", "dolp", "aolp_dolp")])
        self.index += 1

    def finish(self) -> int:
        from polargs_plugin.viz import save_contact_sheet

        save_contact_sheet(self.rows, self.folder / "overview.png")
        return self.count + 1


def _move_in(staging: Path, out: Path, overwrite: bool) -> None:
    """Move the complete scene ``staging`` to ``out``: replacing it when ``overwrite``; otherwise a
    folder that appeared meanwhile (another process generating the same scene) wins."""
    os.chmod(staging, 0o777 & ~current_umask())  # mkdtemp made it 0700
    old = None
    if out.exists() and overwrite:
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old / "scene")
    try:
        os.rename(staging, out)
    except OSError:
        if overwrite or not out.is_dir():
            raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


class _ColmapExport:
    """The scene as COLMAP input in ``folder``: each view's picture as it is written, the sparse
    model (with :data:`EXPORT_POINTS` ground-truth mesh vertices as its points) at the end."""

    def __init__(self, folder: Path, seed: int):
        self.folder, self.seed, self.cameras = folder, seed, {}

    def add(self, view: "View") -> None:
        from polargs_plugin.data.colmap import write_colmap_image

        self.cameras.update(write_colmap_image(self.folder, view))

    def finish(self, scene: "SyntheticScene") -> None:
        import numpy as np

        from polargs_plugin.data.colmap import write_colmap_models

        vertices = np.asarray(scene.mesh_vertices, dtype=np.float64)
        rng = np.random.default_rng(self.seed)
        chosen = rng.choice(len(vertices), size=min(EXPORT_POINTS, len(vertices)), replace=False)
        write_colmap_models(self.folder, self.cameras, vertices[np.sort(chosen)])


def generate_scene_folder(request: SceneRequest, out: Path, overwrite: bool = False, progress: bool = False,
                          export: str | None = None) -> GeneratedScene:
    """Render ``request`` and write it to the scene folder ``out`` (docs/dataset-format.md), or,
    with ``request.mosaic``, to a polar folder of raw frames (docs/readers.md).

    ``export="colmap"`` also writes ``out/colmap``, the scene as a graphdeco-family trainer's
    input (``images/``, ``sparse/0`` with points drawn from the ground-truth mesh), whose image
    names are the view names, so that ``out`` is the ``POLARGS_DATA`` of a patched trainer
    reading ``out/colmap``.

    Views are rendered and written one at a time (a scene of any size needs the memory of one
    view). The scene is written beside ``out`` and moved into place when complete, so ``out``
    holds a whole scene or nothing. An existing non-empty ``out`` is refused unless
    ``overwrite`` and it is a scene folder, which is then replaced as a whole.

    Raises:
        PolarInputError: naming ``out``: not a folder, not empty, not writable; ``--mosaic`` with
            a size the mosaic cannot hold; ``--floor-texture`` for a scene without a floor.
    """
    out = Path(out)
    _check_out(out, overwrite)
    _check_mosaic_size(request)
    _check_floor_texture(request)
    if export is not None and export not in EXPORTS:
        raise PolarInputError("--export", f"unknown export {export!r} (choose one of {', '.join(EXPORTS)})")
    if export is not None and request.mosaic is not None:
        raise PolarInputError("--export", "not with --mosaic (a raw folder's cameras are its sparse/0 already)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.generating-", dir=out.parent))
    except OSError as err:
        raise PolarInputError(out, f"cannot write there ({err.strerror or err})") from None
    try:
        writer = _writer(request, staging)
        statistics = SceneStatistics()
        pictures = _Pictures(staging) if request.pictures else None
        exporter = _ColmapExport(staging / export, request.seed) if export is not None else None
        rendering = writing = 0.0
        start = time.perf_counter()
        for part in request.render_views(progress):
            rendered = time.perf_counter()
            rendering += rendered - start
            writer.add(part)
            statistics.add(part)
            for view in part.views:
                if pictures is not None:
                    pictures.add(view, part.meta["num_views"])
                if exporter is not None:
                    exporter.add(view)
            start = time.perf_counter()
            writing += start - rendered
        writer.finish(part)
        if exporter is not None:
            exporter.finish(part)
        count = pictures.finish() if pictures is not None else 0
        _move_in(staging, out, overwrite)
        writing += time.perf_counter() - start
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return GeneratedScene(out, part.name, part.meta, part.meta["num_views"], statistics.figures(part), count, rendering,
                          writing)


def _check_floor_texture(request: SceneRequest) -> None:
    if request.floor_texture is None:
        return
    from polargs_plugin.data.family import FAMILY, family_scene
    from polargs_plugin.data.scenes import build_scene, with_floor_texture

    spec = family_scene(request.seed).spec if request.scene == FAMILY else build_scene(request.scene)
    try:
        with_floor_texture(spec, request.floor_texture)
    except ValueError as err:
        raise PolarInputError("--floor-texture", str(err)) from None


def _check_mosaic_size(request: SceneRequest) -> None:
    if request.mosaic is None:
        return
    if request.width is None or request.height is None:
        raise PolarInputError("--size", f"give the frame's size with --mosaic (a {request.scene} scene draws its own)")
    step = {"mono": 2, "rgb": 4}[request.mosaic]
    if request.width % step or request.height % step:
        raise PolarInputError("--size", f"a {request.mosaic} mosaic needs a width and height divisible by {step}, "
                              f"got {request.width}x{request.height}")


def _writer(request: SceneRequest, folder: Path) -> Any:
    """What writes each rendered part: a scene folder, or a polar folder of raw frames."""
    from polargs_plugin.data.scene_format import SceneWriter

    bits = request.bits or 8
    if request.mosaic is None:
        return SceneWriter(folder, bits)
    return _MosaicWriter(folder, request.mosaic, bits, request.cameras)


class _MosaicWriter:
    """A rendered scene as DoFP raw frames: a polar folder (raw/, masks/, sparse/0) with its GT meshes."""

    def __init__(self, folder: Path, pattern: str, bits: int, cameras: bool):
        from polargs_plugin.data.polar_folder import PolarFolderWriter

        self.folder, self.pattern, self.cameras = folder, pattern, cameras
        self.writer = PolarFolderWriter(folder, mode="raw", pattern=pattern, bit_depth=bits)

    def add(self, part: "SyntheticScene") -> None:
        for view, angles in zip(part.views, part.angle_images):
            if self.pattern == "mono":  # a mono sensor sees the colours' mean
                angles = angles.mean(dim=1, keepdim=True)
                view = view.replaced(stokes=view.stokes.mean(dim=1, keepdim=True))
            self.writer.add(view, angles)

    def finish(self, part: "SyntheticScene") -> None:
        from polargs_plugin.data.scene_format import write_meshes

        write_meshes(part, self.folder)
        self.writer.finish(cameras=self.cameras)


class SceneStatistics:
    """:func:`scene_statistics`, gathered one rendered part at a time."""

    def __init__(self) -> None:
        self.pixels = self.object = self.highlights = self.overexposed = 0
        self.dolps: list = []
        self.visibility: list = []  # (views, F') rows of the parts that carry them
        self.centres: list = []  # the camera centres of those rows

    def add(self, part: "SyntheticScene") -> None:
        from polargs_plugin.optics.stokes import dolp_from_stokes

        for view, highlight, over in zip(part.views, part.highlight_masks, part.overexposed_masks):
            mask = view.mask
            self.pixels += mask.numel()
            self.object += int(mask.sum())
            self.highlights += int(highlight.sum())
            self.overexposed += int(over.sum())
            self.dolps.append(dolp_from_stokes(view.stokes.mean(dim=1, keepdim=True))[mask])
        if part.visibility is not None:
            self.visibility.append(part.visibility)
            self.centres += [view.camera_center.double().numpy() for view in part.views]

    def figures(self, scene: "SyntheticScene") -> dict[str, Any]:
        """The figures, ``scene`` (any part) giving the mesh."""
        import numpy as np
        import torch

        from polargs_plugin.data.visibility import class_fractions, classify_counts, triangle_counts

        inside = max(self.object, 1)
        stats = {
            "object_fraction": self.object / max(self.pixels, 1),
            "mesh_vertices": len(scene.mesh_vertices),
            "highlight_fraction": self.highlights / inside,
            "overexposed_fraction": self.overexposed / inside,
            "dolp_median": float(torch.cat(self.dolps).median()),
        }
        if self.visibility:
            vertices, triangles = scene.object_mesh()
            well, grazing, area = triangle_counts(vertices, triangles, np.concatenate(self.visibility), self.centres)
            codes = classify_counts(well, grazing)
            stats["visibility"] = class_fractions(codes, area)
            stats["unseen_fraction"] = float(area[codes < 0].sum() / area.sum())
        return stats


def scene_statistics(scene: "SyntheticScene") -> dict[str, Any]:
    """What a user checks first: the object's share of the pixels, the highlights' and the
    overexposed pixels' share of the object, the median DoLP on the object, and (when the scene
    has its per-view visibility) the shares of the object's seen surface area in each visibility
    class (``visibility``: {many, few, grazing}; docs/evaluation.md) and the unseen share."""
    statistics = SceneStatistics()
    statistics.add(scene)
    return statistics.figures(scene)
