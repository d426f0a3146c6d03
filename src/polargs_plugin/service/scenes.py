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

__all__ = ["SceneRequest", "GeneratedScene", "generate_scene_folder", "scene_statistics"]

#: Files that mark a folder as a scene folder that ``overwrite`` may replace.
SCENE_MARKERS = ("scene.json", "cameras.json")


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

    def render(self, progress: bool = False) -> "SyntheticScene":
        """Render the scene (the generator's defaults for every setting left None)."""
        from polargs_plugin.data.family import FAMILY, generate_family_scene
        from polargs_plugin.data.synthetic import generate_scene

        given = {"noise_std": self.noise_std, "quantize_bits": self.bits, "mask": self.mask}
        given = {k: v for k, v in given.items() if v is not None}
        if self.scene == FAMILY:
            size = None if self.width is None and self.height is None else (self.width or self.height, self.height or self.width)
            return generate_family_scene(self.seed, num_views=self.views, size=size, progress=progress, **given)
        if self.refractive_index is not None:
            given["refractive_index"] = self.refractive_index
        return generate_scene(self.scene, num_views=self.views or 24, width=self.width or 128, height=self.height or 128,
                              seed=self.seed, progress=progress, **given)


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


def generate_scene_folder(request: SceneRequest, out: Path, overwrite: bool = False, progress: bool = False) -> GeneratedScene:
    """Render ``request`` and write it to the scene folder ``out`` (docs/dataset-format.md).

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
        pictures = _write_pictures(scene, staging) if request.pictures else 0
        _move_in(staging, out, overwrite)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return GeneratedScene(out, scene, pictures, rendered - start, time.perf_counter() - rendered)


def scene_statistics(scene: "SyntheticScene") -> dict[str, Any]:
    """What a user checks first: the object's share of the pixels, the highlights' and the
    overexposed pixels' share of the object, the median DoLP on the object, and (when the scene
    has its per-view visibility) the shares of the object's seen surface area in each visibility
    class (``visibility``: {many, few, grazing}; docs/evaluation.md) and the unseen share."""
    import torch

    from polargs_plugin.data.visibility import class_fractions, classify_counts, triangle_counts
    from polargs_plugin.optics.stokes import dolp_from_stokes

    mask = torch.stack([v.mask for v in scene.views])
    dolp = torch.stack([dolp_from_stokes(v.stokes.mean(dim=1, keepdim=True)) for v in scene.views])

    def fraction(masks: list) -> float:
        return float(torch.stack(masks).sum() / mask.sum().clamp(min=1))

    stats = {
        "object_fraction": float(mask.float().mean()),
        "mesh_vertices": len(scene.mesh_vertices),
        "highlight_fraction": fraction(scene.highlight_masks),
        "overexposed_fraction": fraction(scene.overexposed_masks),
        "dolp_median": float(dolp[mask].median()),
    }
    if scene.visibility is not None:
        vertices, triangles = scene.object_mesh()
        centres = [v.camera_center.double().numpy() for v in scene.views]
        well, grazing, area = triangle_counts(vertices, triangles, scene.visibility, centres)
        codes = classify_counts(well, grazing)
        stats["visibility"] = class_fractions(codes, area)
        stats["unseen_fraction"] = float(area[codes < 0].sum() / area.sum())
    return stats
