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
    """A bundled scene to render (``polargs generate --help`` lists the scenes).

    Attributes:
        scene: the scene's name.
        views: number of cameras (default 24).
        width, height: image size in pixels (default 128x128).
        seed: sensor-noise seed (default 0).
        noise_std: Gaussian noise std per angle image, [0, 1] units; None: the generator's 0.005.
        bits: sensor bit depth, 8 or 16; None: the generator's 8.
        refractive_index: n of the Fresnel DoLP; None: the generator's 1.5.
        mask: what the masks mark: ``object`` (default) or ``surface`` (every surface, a floor too).
        pictures: also write AoLP / DoLP pictures per view and an overview under ``pictures/``.
        mosaic: write a polar folder of division-of-focal-plane raw frames instead of a scene
            folder: ``rgb`` (IMX250MYR: RGGB Bayer under the polarizer grid) or ``mono``
            (IMX250MZR, the channel mean), one ``raw/<view>.png`` per view at ``bits`` bits, with
            ``masks/``, the ground-truth meshes and (``cameras``) the cameras as a COLMAP model
            ``sparse/0``. The frame is the rendered size (a 2448x2048 frame holds 1224x1024 per
            polarizer angle). None (default): a scene folder.
        cameras: with ``mosaic``, write the COLMAP model (default True; False leaves it to SfM).
    """

    scene: str
    views: int = 24
    width: int = 128
    height: int = 128
    seed: int = 0
    noise_std: float | None = None
    bits: int | None = None
    refractive_index: float | None = None
    mask: Literal["object", "surface"] | None = None
    pictures: bool = False
    mosaic: Literal["mono", "rgb"] | None = None
    cameras: bool = True

    def render(self, progress: bool = False) -> "SyntheticScene":
        """Render the scene (the generator's defaults for every setting left None)."""
        from polargs_plugin.data.synthetic import generate_scene

        return generate_scene(self.scene, num_views=self.views, width=self.width, height=self.height, seed=self.seed,
                              progress=progress, **self._given())

    def render_views(self, progress: bool = False) -> Iterator["SyntheticScene"]:
        """:meth:`render` one view at a time (each item holds the next view)."""
        from polargs_plugin.data.synthetic import generate_scene_views

        return generate_scene_views(self.scene, num_views=self.views, width=self.width, height=self.height,
                                    seed=self.seed, progress=progress, **self._given())

    def _given(self) -> dict[str, Any]:
        given = {"noise_std": self.noise_std, "quantize_bits": self.bits, "refractive_index": self.refractive_index,
                 "mask": self.mask}
        return {k: v for k, v in given.items() if v is not None}


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

    def __init__(self, folder: Path, num_views: int):
        self.folder, self.count, self.rows = folder / "pictures", 0, []
        self.step = max(1, num_views // 4)
        self.index = 0

    def add(self, view: "View") -> None:
        from polargs_plugin.viz import polar_panels, save_polar_pictures

        self.count += len(save_polar_pictures(view.stokes, self.folder, view.name))
        if self.index % self.step == 0 and len(self.rows) < 4:
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
            a size the mosaic cannot hold.
    """
    out = Path(out)
    _check_out(out, overwrite)
    _check_mosaic_size(request)
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
        pictures = _Pictures(staging, request.views) if request.pictures else None
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
                    pictures.add(view)
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
    return GeneratedScene(out, part.name, part.meta, request.views, statistics.figures(part), count, rendering, writing)


def _check_mosaic_size(request: SceneRequest) -> None:
    step = {"mono": 2, "rgb": 4}.get(request.mosaic or "", 1)
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

    def add(self, part: "SyntheticScene") -> None:
        from polargs_plugin.optics.stokes import dolp_from_stokes

        for view, highlight, over in zip(part.views, part.highlight_masks, part.overexposed_masks):
            mask = view.mask
            self.pixels += mask.numel()
            self.object += int(mask.sum())
            self.highlights += int(highlight.sum())
            self.overexposed += int(over.sum())
            self.dolps.append(dolp_from_stokes(view.stokes.mean(dim=1, keepdim=True))[mask])

    def figures(self, scene: "SyntheticScene") -> dict[str, Any]:
        import torch

        inside = max(self.object, 1)
        return {
            "object_fraction": self.object / max(self.pixels, 1),
            "mesh_vertices": len(scene.mesh_vertices),
            "highlight_fraction": self.highlights / inside,
            "overexposed_fraction": self.overexposed / inside,
            "dolp_median": float(torch.cat(self.dolps).median()),
        }


def scene_statistics(scene: "SyntheticScene") -> dict[str, Any]:
    """What a user checks first: the object's share of the pixels, the highlights' and the
    overexposed pixels' share of the object, and the median DoLP on the object."""
    statistics = SceneStatistics()
    statistics.add(scene)
    return statistics.figures(scene)
