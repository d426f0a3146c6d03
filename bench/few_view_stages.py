"""Where a surface few views see is lost: by the Gaussians, by the rendered depth, or by the fusion.

For each finished run folder (``polargs train`` or one cell of ``polargs ablate``), the
ground-truth surface is sampled and each sample classed by how the training views see it (the
evaluation's visibility classes from the views' depth maps: many, few, grazing; docs/evaluation.md).
Per class, three shares of the class's samples are "kept" at three stages of the pipeline:

- **Gaussians**: an opaque Gaussian (opacity above ``--opacity``, default 0.3) has its centre
  within ``--radius`` (default 1.5 % of the ground truth's bounding-box diagonal) of the sample;
- **render**: some view that sees the sample (the same depth-map test as the classes) renders it:
  alpha above 0.5 at its pixel and the rendered depth within ``--radius`` of the sample's depth;
- **mesh**: the run's TSDF mesh (``tsdf_mesh.ply``) passes within 2 % of the diagonal of it
  (the complement is the report's "missing" share).

A class that the Gaussians keep but the render does not is lost to the opacity the views see; one
that the render keeps but the mesh does not is lost in the fusion. Cheap: one render per training
view per run (a few seconds at 128 px on 2 cores).

Usage: python bench/few_view_stages.py RUN_DIR [RUN_DIR ...] [--samples 50000] [--radius 0.015]
       [--opacity 0.3] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from polargs_plugin.data.visibility import (
    CLASS_NAMES,
    VisibilityClasses,
    classify_counts,
    incidence_cosines,
    seen_in_depth_map,
)
from polargs_plugin.metrics import sample_surface_with_faces
from polargs_plugin.nearest import SampleIndex
from polargs_plugin.service.runs import load_run

MISSING_SHARE_OF_DIAGONAL = 0.02


def _normals_of_faces(mesh: o3d.geometry.TriangleMesh, faces: np.ndarray) -> np.ndarray:
    mesh.compute_triangle_normals()
    return np.asarray(mesh.triangle_normals)[faces]


def _distance_to_mesh(points: np.ndarray, mesh_path: Path) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.io.read_triangle_mesh(str(mesh_path))
    scene.add_triangles(mesh.vertex.positions.to(o3d.core.float32), mesh.triangle.indices.to(o3d.core.uint32))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def run_stages(run_dir: Path, samples: int, radius_share: float, opacity: float) -> dict:
    """The per-class shares of one run folder (module docstring)."""
    run = load_run(run_dir)
    gt_path = Path(json.loads((run_dir / "metrics.json").read_text())["gt"])
    gt = o3d.io.read_triangle_mesh(str(gt_path))
    points, faces = sample_surface_with_faces(gt, samples, seed=0)
    normals = _normals_of_faces(gt, faces)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(gt.vertices), axis=0)))
    radius = radius_share * diagonal
    classes = VisibilityClasses()
    well = np.zeros(len(points), dtype=np.int16)
    grazing = np.zeros(len(points), dtype=np.int16)
    rendered = np.zeros(len(points), dtype=bool)
    with torch.no_grad():
        for view in run.views:
            K = view.K.numpy().astype(np.float64)
            w2c = view.world_to_camera.numpy().astype(np.float64)
            cam = points @ w2c[:3, :3].T + w2c[:3, 3]
            seen = seen_in_depth_map(points, view)
            steep = incidence_cosines(points[seen], normals[seen], view.camera_center.numpy()) >= classes.grazing_cos
            index = np.flatnonzero(seen)
            well[index[steep]] += 1
            grazing[index[~steep]] += 1
            out = run.model.render_output(view)
            depth, alpha = out.depth[0].numpy(), out.alpha[0].numpy()
            u = np.clip((K[0, 0] * cam[seen, 0] / cam[seen, 2] + K[0, 2]).astype(np.int64), 0, depth.shape[1] - 1)
            v = np.clip((K[1, 1] * cam[seen, 1] / cam[seen, 2] + K[1, 2]).astype(np.int64), 0, depth.shape[0] - 1)
            rendered[index] |= (alpha[v, u] > 0.5) & (np.abs(depth[v, u] - cam[seen, 2]) < radius)
    codes = classify_counts(well, grazing, classes)
    means = run.model.means.detach().numpy().astype(np.float64)
    opaque = torch.sigmoid(run.model.opacity_logits.detach()).numpy() > opacity
    near_gaussian = (SampleIndex.build(means[opaque]).query(points)[0] < radius if opaque.any()
                     else np.zeros(len(points), dtype=bool))
    near_mesh = _distance_to_mesh(points, run_dir / "tsdf_mesh.ply") < MISSING_SHARE_OF_DIAGONAL * diagonal
    seen_total = int((codes >= 0).sum())
    figures = {}
    for code, name in enumerate(CLASS_NAMES):
        sel = codes == code
        count = int(sel.sum())
        figures[name] = {"share": count / max(seen_total, 1),
                         **({stage: float(keep[sel].mean()) for stage, keep in
                             (("gaussians", near_gaussian), ("render", rendered), ("mesh", near_mesh))} if count else {})}
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    parser.add_argument("--samples", type=int, default=50_000)
    parser.add_argument("--radius", type=float, default=0.015, help="share of the GT diagonal (Gaussians, render)")
    parser.add_argument("--opacity", type=float, default=0.3, help="opacity above which a Gaussian counts")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = {}
    print(f"{'run':<44}{'class':<9}{'share':>7}{'Gaussians':>11}{'render':>8}{'mesh':>7}")
    for run_dir in args.runs:
        figures = run_stages(run_dir, args.samples, args.radius, args.opacity)
        results[run_dir.name] = figures
        for name, f in figures.items():
            kept = "".join(f"{f[k]:>{w}.2f}" if k in f else f"{'-':>{w}}" for k, w in
                           (("gaussians", 11), ("render", 8), ("mesh", 7)))
            print(f"{run_dir.name:<44}{name:<9}{f['share']:>7.2f}{kept}")
    print(json.dumps({"bench": "few_view_stages", "radius": args.radius, "opacity": args.opacity, "runs": results}))


if __name__ == "__main__":
    main()
