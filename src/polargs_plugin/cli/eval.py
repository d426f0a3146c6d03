"""``polargs eval``: Chamfer distance / F-score against a ground-truth mesh and normal MAE."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from polargs_plugin.io import PolarInputError
from polargs_plugin.service.evaluation import EvalSettings, evaluate, metrics_path, write_metrics

_EPILOG = """examples:
  polargs eval runs/sphere --gt scenes/sphere              # GT = scenes/sphere/gt_mesh.ply (object only)
  polargs eval runs/sphere --gt scenes/sphere --normals    # plus normal MAE vs GT normal maps
  polargs eval my_mesh.ply --gt gt.ply --max-dist 20 --fscore-threshold 1 --units mm
  polargs eval my_mesh.ply --gt scenes/sphere --views scenes/sphere   # object region from the scene's cameras
  polargs eval runs/sphere --gt /new/place/sphere --data /new/place/sphere   # the run's dataset moved since

RUN_DIR_or_MESH: a run folder (its tsdf_mesh.ply from `polargs mesh` is evaluated; --normals and the
object region also use its model and views) or a mesh file. Region (default: object when cameras are
known): predicted points are culled to the dilated silhouettes of the GT mesh and GT points no view
sees are left out, and the normal MAE counts only the pixels where the GT object itself is seen.
Distances are in the GT mesh's units; the defaults of --max-dist and --fscore-threshold are 5 % and
0.5 % of the GT bounding-box diagonal (docs/evaluation.md).

figures, one row each (their keys in metrics.json in brackets):
  region                       object, masks or all, and the shares of the predicted and GT samples
                               it kept [region, pred_kept_fraction, gt_kept_fraction]
  accuracy (pred -> GT)        mean distance from the predicted samples to the GT, distances above
                               --max-dist dropped (DTU); uncapped: over all [accuracy, accuracy_uncapped]
  completeness (GT -> pred)    the same from the GT samples to the prediction
                               [completeness, completeness_uncapped]
  Chamfer (mean)               (accuracy + completeness) / 2 [chamfer, chamfer_uncapped]
  F-score @ T                  harmonic mean of precision (predicted samples within T of the GT) and
                               recall (GT samples within T of the prediction), T = --fscore-threshold
                               [fscore, precision, recall, fscore_threshold]
  outlier cap (dropped)        --max-dist and the shares of predicted / GT samples beyond it
                               [max_dist, accuracy_outliers, completeness_outliers]
  signed distance (outside +)  median and mean signed distance of the predicted samples to the GT
                               surface (negative: the mesh sits inside), share inside
                               [signed_distance_median, signed_distance_mean, inside_fraction]
  visible surface              where cameras are known: the uncapped Chamfer over the GT surface some
                               view sees in its GT depth map (ray-cast from the GT mesh where the
                               dataset has none), its completeness, and the share of GT seen
                               [chamfer_visible, completeness_visible, visible_fraction]
  completeness by view         uncapped completeness of the GT seen well (incidence below 70 deg) by
                               4 views or more (many), by 1-3 (few), or only at grazing angles
                               (grazing), with each class's share of the seen GT and the share of
                               the class's GT samples farther than 2 % of the GT box diagonal from
                               the prediction (missing) [completeness_by_visibility,
                               visibility_shares, missing_by_visibility, missing_dist]
  samples (pred / GT)          samples compared [num_pred_points, num_gt_points]
  normal MAE                   with --normals: mean angle in degrees between rendered and GT normals,
                               per view then averaged; GT normals ray-cast from the --gt mesh where the
                               dataset has none [normal_mae_deg, normal_mae_per_view, normal_region,
                               normal_source]
Results are printed and written to metrics.json.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``eval`` subcommand."""
    from polargs_plugin.metrics import REGIONS

    parser = subparsers.add_parser(
        "eval",
        help="Chamfer distance, F-score and normal MAE of a run or mesh",
        description="Evaluate a reconstructed mesh against a ground-truth mesh (DTU-style Chamfer "
        "distance and F-score on area-uniform samples, signed distance) and, for a run, the rendered "
        "normals against the dataset's ground-truth normal maps (mean angular error in degrees).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("target", type=Path, metavar="RUN_DIR_or_MESH", help="run folder or mesh file")
    parser.add_argument("--gt", type=Path, help="ground-truth mesh file, or a folder holding gt_mesh.ply or mesh.ply")
    parser.add_argument("--normals", action="store_true",
                        help="also compute normal MAE (needs a run folder, and GT normals or --gt)")
    parser.add_argument("--region", choices=REGIONS, default=None,
                        help="object: predicted points inside the GT's dilated silhouettes, GT points some view sees "
                        "(default when cameras are known); masks: predicted points inside the views' dilated masks; "
                        "all: whole meshes (default for a mesh file without --views)")
    parser.add_argument("--cull", action="store_true", help="same as --region object (kept for old scripts)")
    parser.add_argument("--views", metavar="DATASET", help="dataset whose cameras (and masks) define the region for a mesh file")
    parser.add_argument("--data", metavar="NEW_PATH", default=None,
                        help="a run's dataset, moved since training (checked against the run's fingerprint.json)")
    parser.add_argument("--num-samples", type=int, default=1_000_000, help="points sampled per mesh (default 1e6)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--max-dist", type=float, help="drop distances above this (default 5%% of the GT box diagonal)")
    parser.add_argument("--fscore-threshold", type=float, help="F-score distance (default 0.5%% of the GT box diagonal)")
    parser.add_argument("--units", default="scene units", help="name of the distance unit, for the report")
    parser.add_argument("--cull-dilation", type=int, default=2, help="mask / silhouette dilation, pixels (default 2)")
    parser.add_argument("--out", type=Path, help="metrics file (default RUN_DIR/metrics.json or MESH.metrics.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def _figure(value: float | None) -> str:
    """A figure as printed; a class without samples has none (NaN, or null once in metrics.json)."""
    return "none" if value is None or math.isnan(value) else f"{value:.4g}"


def format_table(metrics: dict[str, Any]) -> str:
    """The metrics as an aligned two-column text table."""
    rows: list[tuple[str, str]] = []
    cd = metrics.get("chamfer")
    if cd is not None:
        unit = cd["units"]
        rows += [
            ("region", f"{cd.get('region', 'all')} (pred kept {100 * cd.get('pred_kept_fraction', 1):.1f} %, "
             f"GT kept {100 * cd.get('gt_kept_fraction', 1):.1f} %)"),
            ("accuracy (pred -> GT)", f"{cd['accuracy']:.5g} {unit} (uncapped {cd.get('accuracy_uncapped', math.nan):.5g})"),
            ("completeness (GT -> pred)", f"{cd['completeness']:.5g} {unit} (uncapped {cd.get('completeness_uncapped', math.nan):.5g})"),
            ("Chamfer (mean)", f"{cd['chamfer']:.5g} {unit} (uncapped {cd.get('chamfer_uncapped', math.nan):.5g})"),
            (f"F-score @ {cd['fscore_threshold']:.4g}", f"{cd['fscore']:.4f} (P {cd['precision']:.4f}, R {cd['recall']:.4f})"),
            ("outlier cap (dropped)", f"{cd['max_dist']:.4g} {unit} "
             f"(acc {100 * cd['accuracy_outliers']:.2f} %, comp {100 * cd['completeness_outliers']:.2f} %)"),
        ]
        if "signed_distance_median" in cd:
            rows.append(("signed distance (outside +)", f"median {cd['signed_distance_median']:+.4g} {unit}, "
                         f"mean {cd['signed_distance_mean']:+.4g}, {100 * cd['inside_fraction']:.1f} % inside"))
        if "chamfer_visible" in cd:
            rows.append(("visible surface", f"Chamfer {cd['chamfer_visible']:.5g} {unit} uncapped, completeness "
                         f"{cd['completeness_visible']:.5g} over the {100 * cd['visible_fraction']:.1f} % of GT some view sees"
                         f" ({cd.get('visibility_classes', {}).get('source', 'ground-truth depth maps')})"))
            missing = {name: value for name, value in (cd.get("missing_by_visibility") or {}).items()
                       if value is not None and not math.isnan(value)}
            rows.append(("completeness by view", ", ".join(
                f"{name} {_figure(cd['completeness_by_visibility'][name])} ({100 * share:.0f} %"
                + (f", {100 * missing[name]:.1f} % missing" if name in missing else "") + ")"
                for name, share in cd["visibility_shares"].items())))
        rows.append(("samples (pred / GT)", f"{cd['num_pred_points']} / {cd['num_gt_points']}"))
    if metrics.get("normal_mae_deg") is not None:
        region = metrics.get("normal_region", "masks")
        rows.append(("normal MAE", f"{metrics['normal_mae_deg']:.3f} deg over {len(metrics['normal_mae_per_view'])} views "
                     f"(region {region}, {metrics.get('normal_source', 'ground-truth normal maps')})"))
    if not rows:
        return ""
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def settings_from_args(args: argparse.Namespace) -> EvalSettings:
    """The :class:`EvalSettings` of parsed ``polargs eval`` options."""
    return EvalSettings(
        gt=args.gt, normals=args.normals, region=args.region, cull=args.cull, views=args.views, data=args.data,
        num_samples=args.num_samples, seed=args.seed, max_dist=args.max_dist, fscore_threshold=args.fscore_threshold,
        units=args.units, cull_dilation=args.cull_dilation,
    )


def run(args: argparse.Namespace) -> int:
    """Evaluate, print the table and write metrics.json atomically."""
    try:
        metrics = evaluate(args.target, settings_from_args(args), progress=not args.quiet)
    except PolarInputError:  # already names its file
        raise
    except ValueError as err:  # the metrics' own checks (empty masks, everything culled, ...)
        raise PolarInputError(args.target, str(err)) from None
    out = write_metrics(metrics, args.out or metrics_path(args.target))
    print(format_table(metrics))
    print(f"metrics written to {out}")
    return 0
