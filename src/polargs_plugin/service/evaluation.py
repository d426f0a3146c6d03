"""Evaluating a run or a mesh: Chamfer distance / F-score against a ground-truth mesh, normal MAE."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Sequence

from polargs_plugin.io import PolarInputError, write_json
from polargs_plugin.service.data import load_dataset
from polargs_plugin.service.runs import MESH_NAME, METRICS_NAME, Run, load_run

if TYPE_CHECKING:
    from polargs_plugin.types import View

__all__ = ["GT_MESH_NAMES", "EvalSettings", "gt_meshes", "evaluate", "metrics_path", "write_metrics", "normal_errors",
           "normal_mask"]

#: Mesh files looked up, in order, when the ground truth is a folder: the object-only evaluation
#: mesh the bundled scenes ship, then the whole-scene mesh.
GT_MESH_NAMES: tuple[str, ...] = ("gt_mesh.ply", "mesh.ply")
_STEPS = {"all": 3, "masks": 4, "object": 5}  # progress steps of each region's Chamfer


@dataclass(frozen=True)
class EvalSettings:
    """What ``polargs eval`` computes (docs/evaluation.md).

    Attributes:
        gt: ground-truth mesh file, or a folder holding one of :data:`GT_MESH_NAMES`; None: no
            Chamfer distance.
        normals: also the normal MAE of the rendered normals against the dataset's GT normal maps,
            or, for views without them, the normals ray-cast from ``gt`` (needs a run).
        region: ``object`` (predicted points inside the GT mesh's dilated silhouettes, GT points
            some view sees), ``masks`` (predicted points inside the views' dilated masks) or
            ``all``; None (default): ``object`` when cameras are known, else ``all``.
        cull: the old spelling of ``region="object"``.
        views: a dataset whose cameras (and masks) define the region for a mesh file.
        data: a run's dataset in a new place (moved since training; checked against the run's
            fingerprint), instead of the one its ``summary.json`` names.
        num_samples: points sampled per mesh (default 1e6).
        seed: sampling seed (default 0).
        max_dist: distances above this are dropped (DTU); None: 5 % of the GT box diagonal.
        fscore_threshold: the F-score's distance; None: 0.5 % of the GT box diagonal.
        units: name of the distance unit, for the report.
        cull_dilation: mask / silhouette dilation in pixels (default 2).
    """

    gt: Path | None = None
    normals: bool = False
    region: Literal["all", "masks", "object"] | None = None
    cull: bool = False
    views: str | None = None
    data: str | None = None
    num_samples: int = 1_000_000
    seed: int = 0
    max_dist: float | None = None
    fscore_threshold: float | None = None
    units: str = "scene units"
    cull_dilation: int = 2

    def resolved_region(self, have_views: bool) -> str:
        """The region evaluated when cameras are (``have_views``) or are not known."""
        if self.region is not None:
            return self.region
        return "object" if (self.cull or have_views) else "all"


def gt_meshes(path: Path) -> tuple[Path, Path | None]:
    """(evaluation GT mesh, the whole-scene mesh that may hide it or None) for a GT file or folder."""
    if not path.exists():
        raise PolarInputError(path, "ground-truth mesh or folder not found")
    if not path.is_dir():
        return path, None
    found = [path / name for name in GT_MESH_NAMES if (path / name).is_file()]
    if not found:
        raise PolarInputError(path, f"no ground-truth mesh in this folder (looked for {', '.join(GT_MESH_NAMES)})")
    occluder = path / "mesh.ply" if found[0].name == "gt_mesh.ply" and (path / "mesh.ply").is_file() else None
    return found[0], occluder


def normal_mask(view: View) -> Any:
    """(1, H, W) bool: the pixels where a view's normals are evaluated (inside its mask, where
    its ground-truth normal is set); the view must have ``normal_gt``."""
    valid = view.normal_gt.norm(dim=0, keepdim=True) > 0
    return valid if view.mask is None else view.mask.bool() & valid


def normal_errors(model: Any, views: Sequence[View], progress: bool = False,
                  object_pixels: Sequence[Any] | None = None) -> dict[str, float]:
    """Per-view normal MAE (degrees) of the normals ``model.render_output`` renders
    (:meth:`~polargs_plugin.backends.reference.model.GaussianModel.render_output`) inside the GT
    masks and, when given, ``object_pixels`` (one (H, W) bool array per view: where the GT object
    itself is seen)."""
    import torch
    from tqdm import tqdm

    from polargs_plugin.metrics import normal_mae

    per_view = {}
    with torch.no_grad():
        for index, view in enumerate(tqdm(views, desc="normal MAE", unit="view", disable=not progress)):
            if view.normal_gt is None:
                continue
            mask = normal_mask(view)
            if object_pixels is not None:
                mask = mask & torch.from_numpy(object_pixels[index])[None]
            if not bool(mask.any()):
                continue  # the object is out of this view
            normal = model.render_output(view).normal.cpu()
            per_view[view.name] = normal_mae([normal], [view.normal_gt.cpu()], [mask.cpu()])
    return per_view


def _check_request(target: Path, settings: EvalSettings, is_run: bool) -> str:
    """The region, after refusing what cannot be evaluated (before anything is loaded)."""
    if not is_run and not target.is_file():
        raise PolarInputError(target, "neither a run folder nor a mesh file")
    if settings.gt is None and not settings.normals:
        raise PolarInputError(target, "nothing to do; give --gt GT_MESH and/or --normals")
    if settings.normals and not is_run:
        raise PolarInputError(target, "--normals needs a run folder (a model to render), not a mesh file")
    if settings.data is not None and not is_run:
        raise PolarInputError(target, "--data names a run's moved dataset; for a mesh file give the cameras with --views")
    region = settings.resolved_region(is_run or settings.views is not None)
    if region != "all" and not is_run and settings.views is None:
        raise PolarInputError(target, f"--region {region} needs cameras: a run folder, or --views DATASET for a mesh file")
    if is_run and settings.gt is not None and not (target / MESH_NAME).is_file():
        raise PolarInputError(target / MESH_NAME, "no mesh in this run; run `polargs mesh` first")
    return region


@dataclass(frozen=True)
class _GroundTruth:
    """The GT meshes of an evaluation: the object, and the whole scene that may hide it (or None)."""

    path: Path
    mesh: Any
    scene_path: Path | None
    scene: Any

    @classmethod
    def read(cls, gt: Path) -> _GroundTruth:
        from polargs_plugin.mesh import read_mesh

        path, scene_path = gt_meshes(Path(gt))
        return cls(path, read_mesh(path), scene_path, None if scene_path is None else read_mesh(scene_path))

    def fill(self, views: Sequence[View], depth: bool, normals: bool) -> tuple[list[View], dict[str, str]]:
        """:func:`~polargs_plugin.metrics.with_mesh_maps`: the maps the views lack, ray-cast from the
        GT mesh, hidden by the whole scene."""
        from polargs_plugin.metrics import with_mesh_maps

        return with_mesh_maps(views, self.mesh, self.scene, depth=depth, normals=normals)


def _ray_cast(sources: dict[str, str]) -> bool:
    """Whether some of the maps of :meth:`_GroundTruth.fill` were ray-cast (the whole scene then hid the object)."""
    from polargs_plugin.metrics import RAY_CAST_SOURCE

    return any(RAY_CAST_SOURCE in source for source in sources.values())


def _chamfer(mesh_path: Path, settings: EvalSettings, region: str, views: Sequence[View] | None,
             truth: _GroundTruth, depth_source: str | None, progress: bool) -> dict[str, Any]:
    """The chamfer entry; ``depth_source``: where the views' GT depth maps came from (None: their own)."""
    from tqdm import tqdm

    from polargs_plugin.mesh import read_mesh
    from polargs_plugin.metrics import chamfer_distance

    pred, gt = read_mesh(mesh_path), truth.mesh
    occluder = truth.scene if region == "object" else None
    cull_views = None
    if region != "all":
        cull_views = list(views)
        if region == "masks":
            cull_views = [v for v in cull_views if v.mask is not None]
            if not cull_views:
                raise PolarInputError(mesh_path, "--region masks needs views with masks; these have none")
    with tqdm(total=_STEPS[region], desc="Chamfer", unit="step", disable=not progress) as bar:
        def step(name: str) -> None:
            if bar.n or name != "sampling":
                bar.update(1)
            bar.set_postfix_str(name)

        chamfer = chamfer_distance(
            pred, gt, num_samples=settings.num_samples, seed=settings.seed, max_dist=settings.max_dist,
            fscore_threshold=settings.fscore_threshold, cull_views=cull_views,
            cull_dilation_px=settings.cull_dilation, units=settings.units, region=region,
            occluder=occluder, progress=step, visibility_source=depth_source or "ground-truth depth maps",
        )
        bar.update(bar.total - bar.n)
    return {"chamfer": chamfer, "mesh": os.path.abspath(mesh_path), "gt": os.path.abspath(truth.path)}


def evaluate(target: Path, settings: EvalSettings, run: Run | None = None, progress: bool = False) -> dict[str, Any]:
    """The metrics of a run folder or a mesh file.

    Args:
        target: a run folder (its ``tsdf_mesh.ply`` is evaluated; the normals and the object
            region use its model and views) or a mesh file.
        settings: what to compute.
        run: the run already in memory (its folder is ``target``); None: read when needed.
        progress: show progress bars.

    Returns:
        ``{"target", "chamfer": {...}, "mesh", "gt", "occluder"?, "normal_mae_deg",
        "normal_mae_per_view", "normal_region", "normal_source"}`` (the parts asked for), as
        ``metrics.json`` holds it. Views without GT depth maps (or, for the normal MAE, GT normals)
        get the ones ray-cast from the GT mesh, hidden by the whole-scene mesh
        (:func:`~polargs_plugin.metrics.with_mesh_maps`); ``chamfer["visibility_classes"]["source"]``
        and ``normal_source`` say where the maps came from.

    Raises:
        PolarInputError: naming the file: nothing to evaluate, a missing mesh or GT, no GT normals.
        ValueError: the metrics' own checks (empty masks, everything culled, ...).
    """
    is_run = run is not None or target.is_dir()
    region = _check_request(target, settings, is_run)
    views: Sequence[View] | None = None
    if is_run and (settings.normals or (settings.gt is not None and region != "all")):
        run = run or load_run(target, settings.data)
        views = run.views
    if settings.views is not None:
        views = load_dataset(str(settings.views)).views
    metrics: dict[str, Any] = {"target": os.path.abspath(target)}  # valid from any folder
    truth = None if settings.gt is None else _GroundTruth.read(settings.gt)
    normal_views, sources = (run.views if settings.normals else None), {}
    if truth is not None:
        # views without GT depth maps (or normals) get the ones ray-cast from the GT mesh: the
        # visible-surface figures and the normal MAE need them
        if views is not None and region != "all":
            shared = settings.normals and settings.views is None  # the run's views for both
            views, sources = truth.fill(views, depth=True, normals=shared)
            normal_views = views if shared else normal_views
        if normal_views is not None and "normals" not in sources:
            normal_views, more = truth.fill(normal_views, depth=False, normals=True)
            sources.update(more)
        metrics.update(_chamfer(target / MESH_NAME if is_run else target, settings, region, views, truth,
                                sources.get("depth"), progress))
        if truth.scene is not None and (region == "object" or _ray_cast(sources)):
            metrics["occluder"] = os.path.abspath(truth.scene_path)
    if settings.normals:
        metrics.update(_normals(target, run.model, normal_views, sources.get("normals"), region, truth, progress))
    return metrics


def _normals(target: Path, model: Any, views: Sequence[View], normal_source: str | None, region: str,
             truth: _GroundTruth | None, progress: bool) -> dict[str, Any]:
    """The normal MAE entries; ``normal_source``: where the views' GT normals came from (None: their own)."""
    from polargs_plugin.metrics import mesh_silhouettes

    with_gt = [v for v in views if v.normal_gt is not None]
    if not with_gt:
        source = getattr(views[0], "source", "") or str(target) if views else str(target)
        raise PolarInputError(source, "--normals: the dataset has no ground-truth normal maps and no --gt mesh to "
                              "ray-cast them from (docs/readers.md lists which readers load them)")
    object_pixels = None
    if truth is not None and region == "object":
        # the same object as Chamfer's: a support plane in the masks (and GT normal maps) is left out
        object_pixels = mesh_silhouettes(truth.mesh, with_gt, truth.scene)
    per_view = normal_errors(model, with_gt, progress, object_pixels)
    if not per_view:
        raise PolarInputError(target, "--normals: no view has ground-truth normals inside its mask")
    return {"normal_mae_per_view": per_view, "normal_mae_deg": sum(per_view.values()) / len(per_view),
            "normal_region": "masks" if object_pixels is None else "object",
            "normal_source": normal_source or "ground-truth normal maps"}


def metrics_path(target: Path) -> Path:
    """Where ``polargs eval`` writes by default: ``RUN_DIR/metrics.json`` or ``MESH.metrics.json``."""
    return target / METRICS_NAME if target.is_dir() else target.with_name(target.stem + ".metrics.json")


def write_metrics(metrics: dict[str, Any], path: Path) -> Path:
    """Write ``metrics`` as strict JSON (NaN as null), atomically."""
    try:
        return write_json(path, metrics)
    except OSError as err:
        raise PolarInputError(path, f"cannot write the metrics ({err.strerror or err})") from None
