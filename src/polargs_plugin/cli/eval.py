"""``polargs eval``: Chamfer distance / F-score against a ground-truth mesh and normal MAE."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

_EPILOG = """examples:
  polargs eval runs/sphere --gt scenes/sphere              # GT = scenes/sphere/mesh.ply
  polargs eval runs/sphere --gt scenes/sphere --normals    # plus normal MAE vs GT normal maps
  polargs eval my_mesh.ply --gt gt.ply --max-dist 20 --fscore-threshold 1 --units mm

RUN_DIR_or_MESH: a run folder (its tsdf_mesh.ply from `polargs mesh` is evaluated; --normals and
--cull also use its model and views) or a mesh file. Chamfer: accuracy = mean distance predicted ->
GT, completeness = GT -> predicted, chamfer = their mean; distances above --max-dist are dropped
(DTU); defaults are 5 % (outlier cap) and 0.5 % (F-score) of the GT bounding-box diagonal.
Results are printed and written to metrics.json (see docs/evaluation.md).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``eval`` subcommand."""
    parser = subparsers.add_parser(
        "eval",
        help="Chamfer distance, F-score and normal MAE of a run or mesh",
        description="Evaluate a reconstructed mesh against a ground-truth mesh (DTU-style Chamfer "
        "distance and F-score on area-uniform samples) and, for a run, the rendered normals "
        "against the dataset's ground-truth normal maps (mean angular error in degrees).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("target", type=Path, metavar="RUN_DIR_or_MESH", help="run folder or mesh file")
    parser.add_argument("--gt", type=Path, help="ground-truth mesh file, or a scene folder holding mesh.ply")
    parser.add_argument("--normals", action="store_true", help="also compute normal MAE (needs a run folder and GT normals)")
    parser.add_argument("--num-samples", type=int, default=1_000_000, help="points sampled per mesh (default 1e6)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--max-dist", type=float, help="drop distances above this (default 5%% of the GT box diagonal)")
    parser.add_argument("--fscore-threshold", type=float, help="F-score distance (default 0.5%% of the GT box diagonal)")
    parser.add_argument("--units", default="scene units", help="name of the distance unit, for the report")
    parser.add_argument("--cull", action="store_true", help="drop predicted points outside the run's dilated view masks")
    parser.add_argument("--cull-dilation", type=int, default=2, help="mask dilation for --cull, pixels (default 2)")
    parser.add_argument("--out", type=Path, help="metrics file (default RUN_DIR/metrics.json or MESH.metrics.json)")
    parser.set_defaults(func=run)


def _gt_mesh(path: Path):
    from polargs_plugin.mesh import read_mesh

    if path.is_dir():
        from polargs_plugin.data.scene_format import read_gt_mesh

        return read_gt_mesh(path)
    return read_mesh(path)


def _normal_errors(model: Any, views: list) -> dict[str, float]:
    """Per-view normal MAE (degrees) of the rendered normals inside the GT masks."""
    import torch

    from polargs_plugin.metrics import normal_mae

    per_view = {}
    with torch.no_grad():
        for view in views:
            if view.normal_gt is None:
                continue
            mask = view.mask if view.mask is not None else view.normal_gt.norm(dim=0, keepdim=True) > 0
            if not bool(mask.any()):
                continue  # the object is out of this view
            normal = model.render(view).normal.cpu()
            per_view[view.name] = normal_mae([normal], [view.normal_gt.cpu()], [mask.cpu()])
    return per_view


def _json_safe(value: Any) -> Any:
    """NaN (every distance above the outlier cap) becomes null: strict JSON has no NaN."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def format_table(metrics: dict[str, Any]) -> str:
    """The metrics as an aligned two-column text table."""
    rows: list[tuple[str, str]] = []
    cd = metrics.get("chamfer")
    if cd is not None:
        unit = cd["units"]
        rows += [
            ("accuracy (pred -> GT)", f"{cd['accuracy']:.5g} {unit}"),
            ("completeness (GT -> pred)", f"{cd['completeness']:.5g} {unit}"),
            ("Chamfer (mean)", f"{cd['chamfer']:.5g} {unit}"),
            (f"F-score @ {cd['fscore_threshold']:.4g}", f"{cd['fscore']:.4f} (P {cd['precision']:.4f}, R {cd['recall']:.4f})"),
            ("outlier cap (dropped)", f"{cd['max_dist']:.4g} {unit} "
             f"(acc {100 * cd['accuracy_outliers']:.2f} %, comp {100 * cd['completeness_outliers']:.2f} %)"),
            ("samples (pred / GT)", f"{cd['num_pred_points']} / {cd['num_gt_points']}"),
        ]
    if metrics.get("normal_mae_deg") is not None:
        rows.append(("normal MAE", f"{metrics['normal_mae_deg']:.3f} deg over {len(metrics['normal_mae_per_view'])} views"))
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def run(args: argparse.Namespace) -> int:
    """Evaluate, print the table and write metrics.json atomically."""
    from polargs_plugin.cli.mesh import MESH_FILE, load_run
    from polargs_plugin.io import PolarInputError, atomic_write
    from polargs_plugin.mesh import read_mesh
    from polargs_plugin.metrics import chamfer_distance

    target: Path = args.target
    is_run = target.is_dir()
    if not is_run and not target.is_file():
        raise PolarInputError(target, "neither a run folder nor a mesh file")
    if args.gt is None and not args.normals:
        raise SystemExit("polargs eval: nothing to do; give --gt GT_MESH and/or --normals")
    if (args.normals or args.cull) and not is_run:
        raise SystemExit("polargs eval: --normals and --cull need a run folder, not a mesh file")

    model = views = None
    if is_run and (args.normals or args.cull):
        model, views = load_run(target)

    metrics: dict[str, Any] = {"target": str(target)}
    if args.gt is not None:
        mesh_path = target / MESH_FILE if is_run else target
        if is_run and not mesh_path.is_file():
            raise PolarInputError(mesh_path, "no mesh in this run; run `polargs mesh` first")
        pred = read_mesh(mesh_path)
        gt = _gt_mesh(args.gt)
        cull_views = None
        if args.cull:
            cull_views = [v for v in views if v.mask is not None]
            if not cull_views:
                raise SystemExit("polargs eval: --cull needs views with masks; this run has none")
        metrics.update(mesh=str(mesh_path), gt=str(args.gt))
        metrics["chamfer"] = chamfer_distance(
            pred, gt, num_samples=args.num_samples, seed=args.seed, max_dist=args.max_dist,
            fscore_threshold=args.fscore_threshold, cull_views=cull_views,
            cull_dilation_px=args.cull_dilation, units=args.units,
        )
        metrics["chamfer"]["culled"] = bool(args.cull)
    if args.normals:
        per_view = _normal_errors(model, views)
        if not per_view:
            raise SystemExit("polargs eval: --normals needs views with ground-truth normals inside their masks")
        metrics["normal_mae_per_view"] = per_view
        metrics["normal_mae_deg"] = sum(per_view.values()) / len(per_view)

    out = args.out or (target / "metrics.json" if is_run else target.with_name(target.stem + ".metrics.json"))
    with atomic_write(out) as handle:
        json.dump(_json_safe(metrics), handle, indent=2, allow_nan=False)
    print(format_table(metrics))
    print(f"metrics written to {out}")
    return 0
