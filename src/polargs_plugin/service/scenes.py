"""Writing a bundled synthetic scene as a scene folder, atomically (``polargs generate``)."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from polargs_plugin.io import PolarInputError, current_umask

if TYPE_CHECKING:
    from polargs_plugin.data.synthetic import SyntheticScene

__all__ = ["SceneRequest", "GeneratedScene", "generate_scene_folder", "scene_statistics", "EXPORTS", "EXPORT_POINTS"]

#: Trainer inputs ``generate_scene_folder`` can write beside the scene: ``colmap`` is the input of
#: the graphdeco-family trainers (``OUT/colmap``: images and a sparse model).
EXPORTS: tuple[str, ...] = ("colmap",)
#: Sparse points of the COLMAP export, drawn from the ground-truth mesh's vertices.
EXPORT_POINTS = 1000

#: Files that mark a folder as a scene folder that ``overwrite`` may replace.
SCENE_MARKERS = ("scene.json", "cameras.json")


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

    def render(self, progress: bool = False) -> "SyntheticScene":
        """Render the scene (the generator's defaults for every setting left None)."""
        from polargs_plugin.data.synthetic import generate_scene

        given = {"noise_std": self.noise_std, "quantize_bits": self.bits, "refractive_index": self.refractive_index,
                 "mask": self.mask}
        return generate_scene(self.scene, num_views=self.views, width=self.width, height=self.height, seed=self.seed,
                              progress=progress, **{k: v for k, v in given.items() if v is not None})


@dataclass
class GeneratedScene:
    """A scene folder just written.

    Attributes:
        folder: the scene folder.
        scene: the rendered scene (views, ground truth, metadata).
        pictures: number of pictures written.
        render_seconds, write_seconds: wall times.
    """

    folder: Path
    scene: "SyntheticScene"
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


def _write_pictures(scene: "SyntheticScene", folder: Path) -> int:
    from polargs_plugin.viz import polar_panels, save_contact_sheet, save_polar_pictures

    count = 0
    for view in scene.views:
        count += len(save_polar_pictures(view.stokes, folder / "pictures", view.name))
    # one overview picture: a few views as rows, s0 / AoLP / DoLP / AoLP-with-DoLP as columns
    step = max(1, len(scene.views) // 4)
    rows = [[polar_panels(v.stokes)[k] for k in ("s0", "aolp", "dolp", "aolp_dolp")] for v in scene.views[::step][:4]]
    save_contact_sheet(rows, folder / "pictures" / "overview.png")
    return count + 1


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


def _export_colmap(scene: "SyntheticScene", folder: Path, seed: int) -> None:
    """``folder`` = the scene as COLMAP input, with :data:`EXPORT_POINTS` mesh vertices as points."""
    import numpy as np

    from polargs_plugin.data.colmap import write_colmap_scene

    vertices = np.asarray(scene.mesh_vertices, dtype=np.float64)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(vertices), size=min(EXPORT_POINTS, len(vertices)), replace=False)
    write_colmap_scene(folder, scene.views, vertices[np.sort(chosen)])


def generate_scene_folder(request: SceneRequest, out: Path, overwrite: bool = False, progress: bool = False,
                          export: str | None = None) -> GeneratedScene:
    """Render ``request`` and write it to the scene folder ``out`` (docs/dataset-format.md).

    ``export="colmap"`` also writes ``out/colmap``, the scene as a graphdeco-family trainer's
    input (``images/``, ``sparse/0`` with points drawn from the ground-truth mesh), whose image
    names are the view names, so that ``out`` is the ``POLARGS_DATA`` of a patched trainer
    reading ``out/colmap``.

    The scene is written beside ``out`` and moved into place when complete, so ``out`` holds a
    whole scene or nothing. An existing non-empty ``out`` is refused unless ``overwrite`` and it is
    a scene folder, which is then replaced as a whole.

    Raises:
        PolarInputError: naming ``out``: not a folder, not empty, not writable.
    """
    from polargs_plugin.data.scene_format import write_scene

    out = Path(out)
    _check_out(out, overwrite)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.generating-", dir=out.parent))
    except OSError as err:
        raise PolarInputError(out, f"cannot write there ({err.strerror or err})") from None
    try:
        start = time.perf_counter()
        scene = request.render(progress)
        rendered = time.perf_counter()
        write_scene(scene, staging)
        if export is not None:
            if export not in EXPORTS:
                raise PolarInputError("--export", f"unknown export {export!r} (choose one of {', '.join(EXPORTS)})")
            _export_colmap(scene, staging / export, request.seed)
        pictures = _write_pictures(scene, staging) if request.pictures else 0
        _move_in(staging, out, overwrite)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return GeneratedScene(out, scene, pictures, rendered - start, time.perf_counter() - rendered)


def scene_statistics(scene: "SyntheticScene") -> dict[str, Any]:
    """What a user checks first: the object's share of the pixels, the highlights' and the
    overexposed pixels' share of the object, and the median DoLP on the object."""
    import torch

    from polargs_plugin.optics.stokes import dolp_from_stokes

    mask = torch.stack([v.mask for v in scene.views])
    dolp = torch.stack([dolp_from_stokes(v.stokes.mean(dim=1, keepdim=True)) for v in scene.views])

    def fraction(masks: list) -> float:
        return float(torch.stack(masks).sum() / mask.sum().clamp(min=1))

    return {
        "object_fraction": float(mask.float().mean()),
        "mesh_vertices": len(scene.mesh_vertices),
        "highlight_fraction": fraction(scene.highlight_masks),
        "overexposed_fraction": fraction(scene.overexposed_masks),
        "dolp_median": float(dolp[mask].median()),
    }
