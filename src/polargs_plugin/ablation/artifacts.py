"""What a cell writes beside its model for the report: the curves, two views' renders, the PC
inputs and the mesh's signed distance to the ground truth (docs/ablation.md)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING, Any

from polargs_plugin.io import atomic_write

if TYPE_CHECKING:  # metrics imports open3d: loaded only when a cell evaluates
    from polargs_plugin.metrics import MeshLike

__all__ = ["CURVES_NAME", "EVAL_CULL_DILATION", "REPORT_VIEW_COUNT", "write_curves", "report_view_indices", "write_report_data",
           "mesh_error"]

#: The per-iteration curves of a run folder (:func:`write_curves`).
CURVES_NAME = "curves.csv"

#: `polargs eval`'s silhouette dilation (pixels) for the object region, the cells' default
EVAL_CULL_DILATION = 2


def write_curves(path: Path, curve: list[dict[str, float]]) -> None:
    """curves.csv: iteration, loss, psnr, num_gaussians, appended, appended_total, then the hooks' terms."""
    fixed = ["iteration", "loss", "psnr", "num_gaussians", "appended", "appended_total"]
    extra = sorted({k for row in curve for k in row} - set(fixed))
    total = 0
    with atomic_write(path) as handle:
        writer = csv.writer(handle)
        writer.writerow(fixed + extra)
        for row in curve:
            total += row["appended"]
            values = [row["iteration"], row["loss"], row["psnr"], row["num_gaussians"], row["appended"], total]
            writer.writerow([_fmt(v) for v in values] + [_fmt(row.get(k, "")) for k in extra])


def _fmt(value: Any) -> Any:
    return f"{value:.6g}" if isinstance(value, float) else value


#: views shown side by side in the report
REPORT_VIEW_COUNT = 2


def report_view_indices(num_views: int) -> list[int]:
    """The two views shown side by side in the report: the first and the middle one."""
    return sorted({0, num_views // 2})[:REPORT_VIEW_COUNT]


def write_report_data(trainer, tmp: Path, gt_mesh: Path, occluder: Path | None, cull: bool) -> None:
    """views.npz, pc_maps.npz (PC variants) and mesh_error.npz for the report. views.npz: the report
    views' renders, targets, cameras, GT maps and ``gt_silhouette`` (1, H, W), the GT mesh's
    silhouette less what the whole-scene ``occluder`` mesh (or None) hides; the mesh error: exact
    signed distance of the predicted mesh's vertices to the GT mesh, outside positive; with
    ``cull``, which vertices lie in the region the evaluation measured."""
    import numpy as np
    import torch

    from polargs_plugin.io import atomic_path
    from polargs_plugin.mesh import read_mesh
    from polargs_plugin.metrics import mesh_silhouettes

    indices = report_view_indices(len(trainer.views))
    views = [trainer.views[i] for i in indices]
    # where the GT object itself is seen: the depth-error picture leaves a support plane out
    occluder_mesh = read_mesh(occluder) if occluder is not None else None
    silhouettes = mesh_silhouettes(read_mesh(gt_mesh), views, occluder_mesh)
    data: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for i, (index, view) in enumerate(zip(indices, views)):
            data[f"{i}/gt_silhouette"] = silhouettes[i][None]
            out = trainer.model.render_output(view, background=trainer.background, backend=trainer.config.backend)
            depth = out.median_depth if out.median_depth is not None else out.depth
            fields = {
                "color": out.color.clamp(0, 1), "normal": out.normal, "depth": depth, "alpha": out.alpha,
                "target": trainer.target(view),
                "K": view.K, "world_to_camera": view.world_to_camera,
            }
            for key, value in (("mask", view.mask), ("normal_gt", view.normal_gt), ("depth_gt", view.depth_gt)):
                if value is not None:
                    fields[key] = value
            for key, value in fields.items():
                data[f"{i}/{key}"] = value.detach().cpu().numpy()
            data[f"{i}/name"] = np.array(view.name)
    with atomic_path(tmp / "views.npz") as path:
        np.savez_compressed(path, **data)

    hooks = trainer.hooks
    if hooks is not None and hooks.config.correction.enabled and getattr(hooks, "maps", None):
        maps: dict[str, np.ndarray] = {}
        for i, view in enumerate(views):
            m = hooks.maps.get(view.name)
            if m is None:
                continue
            for key in ("aolp", "dolp", "intensity", "specular_mask", "overexposed_mask", "i_diff", "i_chro"):
                value = getattr(m, key)
                if value is not None:
                    maps[f"{i}/{key}"] = value.detach().cpu().numpy()
        if maps:
            with atomic_path(tmp / "pc_maps.npz") as path:
                np.savez_compressed(path, **maps)

    error = mesh_error(tmp / "tsdf_mesh.ply", gt_mesh, trainer.views if cull else None, occluder_mesh)
    with atomic_path(tmp / "mesh_error.npz") as path:
        np.savez_compressed(path, **error)


def mesh_error(
    mesh: Path, gt_mesh: Path, views: list | None = None, occluder: MeshLike | None = None
) -> dict[str, Any]:
    """mesh_error.npz's arrays: ``vertices`` (V, 3) float32 of the mesh file ``mesh`` and their
    ``signed_distance`` (V,) float32 to the GT mesh (exact closest point, outside positive:
    :func:`polargs_plugin.metrics.signed_distances`); with ``views``, ``evaluated`` (V,) bool: the
    vertices in the evaluation's object region (:func:`polargs_plugin.metrics.in_object_region`
    with ``EVAL_CULL_DILATION`` and the whole-scene ``occluder`` mesh or None: the predicted points
    ``polargs eval`` keeps), so that the picture does not colour the support (a floor) that the
    figures leave out."""
    import numpy as np

    from polargs_plugin.mesh import read_mesh
    from polargs_plugin.metrics import in_object_region, signed_distances

    vertices = np.asarray(read_mesh(mesh).vertices, dtype=np.float64)
    gt = read_mesh(gt_mesh)
    # open3d's BVH, a few seconds; the nearest of 400k GT samples (cKDTree) that this once was
    # took minutes for a mesh inside the GT, far from every sample (polargs_plugin.nearest)
    distance = signed_distances(vertices, gt)
    error = {"vertices": vertices.astype(np.float32), "signed_distance": distance.astype(np.float32)}
    if views is not None:
        error["evaluated"] = in_object_region(vertices, gt, views, EVAL_CULL_DILATION, occluder)
    return error
