"""``polargs eval``: Chamfer distance / F-score against a ground-truth mesh and normal MAE."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

# Mesh files looked up, in order, when ``--gt`` is a folder (the same as `polargs ablate`'s): the
# object-only evaluation GT that the bundled scenes ship, then the whole-scene mesh.
from polargs_plugin.ablation.scenes import GT_MESH_NAMES

_EPILOG = """examples:
  polargs eval runs/sphere --gt scenes/sphere              # GT = scenes/sphere/gt_mesh.ply (object only)
  polargs eval runs/sphere --gt scenes/sphere --normals    # plus normal MAE vs GT normal maps
  polargs eval my_mesh.ply --gt gt.ply --max-dist 20 --fscore-threshold 1 --units mm
  polargs eval my_mesh.ply --gt scenes/sphere --views scenes/sphere   # object region from the scene's cameras

RUN_DIR_or_MESH: a run folder (its tsdf_mesh.ply from `polargs mesh` is evaluated; --normals and the
object region also use its model and views) or a mesh file. Region (default: object when cameras are
known): predicted points are culled to the dilated silhouettes of the GT mesh and GT points no view
sees are left out, and the normal MAE counts only the pixels where the GT object itself is seen
(docs/evaluation.md). Chamfer: accuracy = mean distance predicted -> GT,
completeness = GT -> predicted, chamfer = their mean; distances above --max-dist are dropped (DTU) and
the uncapped means are reported next to them; defaults are 5 % (outlier cap) and 0.5 % (F-score) of
the GT bounding-box diagonal. The signed distance (outside positive) tells whether the mesh sits
inside or outside the true surface. Results are printed and written to metrics.json.
"""


from polargs_plugin.cli.mesh import CommandError, fail  # noqa: E402  (one-line errors, exit status 2)

EvalError = CommandError


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
    parser.add_argument("--normals", action="store_true", help="also compute normal MAE (needs a run folder and GT normals)")
    parser.add_argument("--region", choices=REGIONS, default=None,
                        help="object: predicted points inside the GT's dilated silhouettes, GT points some view sees "
                        "(default when cameras are known); masks: predicted points inside the views' dilated masks; "
                        "all: whole meshes (default for a mesh file without --views)")
    parser.add_argument("--cull", action="store_true", help="same as --region object (kept for old scripts)")
    parser.add_argument("--views", metavar="DATASET", help="dataset whose cameras (and masks) define the region for a mesh file")
    parser.add_argument("--num-samples", type=int, default=1_000_000, help="points sampled per mesh (default 1e6)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--max-dist", type=float, help="drop distances above this (default 5%% of the GT box diagonal)")
    parser.add_argument("--fscore-threshold", type=float, help="F-score distance (default 0.5%% of the GT box diagonal)")
    parser.add_argument("--units", default="scene units", help="name of the distance unit, for the report")
    parser.add_argument("--cull-dilation", type=int, default=2, help="mask / silhouette dilation, pixels (default 2)")
    parser.add_argument("--out", type=Path, help="metrics file (default RUN_DIR/metrics.json or MESH.metrics.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def gt_meshes(path: Path) -> tuple[Path, Path | None]:
    """(evaluation GT mesh, whole-scene mesh that may hide it or None) for ``--gt PATH``."""
    from polargs_plugin.io import PolarInputError

    if not path.exists():
        raise PolarInputError(path, "ground-truth mesh or folder not found")
    if not path.is_dir():
        return path, None
    found = [path / name for name in GT_MESH_NAMES if (path / name).is_file()]
    if not found:
        raise PolarInputError(path, f"no ground-truth mesh in this folder (looked for {', '.join(GT_MESH_NAMES)})")
    occluder = path / "mesh.ply" if found[0].name == "gt_mesh.ply" and (path / "mesh.ply").is_file() else None
    return found[0], occluder


def _normal_errors(model: Any, views: list, progress: bool = False, object_pixels: list | None = None) -> dict[str, float]:
    """Per-view normal MAE (degrees) of the rendered normals inside the GT masks and, when given,
    ``object_pixels`` (one (H, W) bool per view: where the GT object itself is seen)."""
    import torch
    from tqdm import tqdm

    from polargs_plugin.metrics import normal_mae

    per_view = {}
    with torch.no_grad():
        for index, view in enumerate(tqdm(views, desc="normal MAE", unit="view", disable=not progress)):
            if view.normal_gt is None:
                continue
            valid = view.normal_gt.norm(dim=0, keepdim=True) > 0
            mask = valid if view.mask is None else view.mask.bool() & valid
            if object_pixels is not None:
                mask = mask & torch.from_numpy(object_pixels[index])[None]
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
        rows.append(("samples (pred / GT)", f"{cd['num_pred_points']} / {cd['num_gt_points']}"))
    if metrics.get("normal_mae_deg") is not None:
        region = metrics.get("normal_region", "masks")
        rows.append(("normal MAE", f"{metrics['normal_mae_deg']:.3f} deg over {len(metrics['normal_mae_per_view'])} views "
                     f"(region {region})"))
    if not rows:
        return ""
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def run(args: argparse.Namespace) -> int:
    """Evaluate, print the table and write metrics.json atomically.

    Ordinary errors (missing files, a run without mesh, no GT normals) are printed as one
    ``error: FILE: problem`` line and raise :class:`EvalError` (exit status 2).
    """
    from polargs_plugin.io import PolarInputError

    try:
        return _run(args)
    except PolarInputError as err:
        raise fail(str(err)) from None
    except ValueError as err:  # the metrics' own checks (empty masks, everything culled, ...)
        raise fail(f"{args.target}: {err}") from None


def _region(args: argparse.Namespace, have_views: bool) -> str:
    region = getattr(args, "region", None)
    if region is None:
        region = "object" if (getattr(args, "cull", False) or have_views) else "all"
    return region


def _run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from polargs_plugin.cli.mesh import MESH_FILE, load_run
    from polargs_plugin.io import PolarInputError, atomic_write
    from polargs_plugin.mesh import read_mesh
    from polargs_plugin.metrics import chamfer_distance, mesh_silhouettes

    target: Path = args.target
    progress = not getattr(args, "quiet", False)
    is_run = target.is_dir()
    if not is_run and not target.is_file():
        raise PolarInputError(target, "neither a run folder nor a mesh file")
    if args.gt is None and not args.normals:
        raise PolarInputError(target, "nothing to do; give --gt GT_MESH and/or --normals")
    views_spec = getattr(args, "views", None)
    if args.normals and not is_run:
        raise PolarInputError(target, "--normals needs a run folder (a model to render), not a mesh file")
    region = _region(args, is_run or views_spec is not None)
    if region != "all" and not is_run and views_spec is None:
        raise PolarInputError(target, f"--region {region} needs cameras: a run folder, or --views DATASET for a mesh file")

    model = views = None
    if is_run and (args.normals or (args.gt is not None and region != "all")):
        mesh_path = target / MESH_FILE
        if args.gt is not None and not mesh_path.is_file():  # say this before loading a whole dataset
            raise PolarInputError(mesh_path, "no mesh in this run; run `polargs mesh` first")
        model, views = load_run(target)
    if views_spec is not None:
        from polargs_plugin.cli.train import load_dataset

        views = load_dataset(str(views_spec))

    metrics: dict[str, Any] = {"target": str(target)}
    if args.gt is not None:
        mesh_path = target / MESH_FILE if is_run else target
        if is_run and not mesh_path.is_file():
            raise PolarInputError(mesh_path, "no mesh in this run; run `polargs mesh` first")
        gt_path, occluder_path = gt_meshes(Path(args.gt))
        pred, gt = read_mesh(mesh_path), read_mesh(gt_path)
        occluder = read_mesh(occluder_path) if occluder_path is not None and region == "object" else None
        cull_views = None
        if region != "all":
            cull_views = list(views)
            if region == "masks":
                cull_views = [v for v in cull_views if v.mask is not None]
                if not cull_views:
                    raise PolarInputError(target, "--region masks needs views with masks; these have none")
        steps = {"all": 3, "masks": 4, "object": 5}[region]
        with tqdm(total=steps, desc="Chamfer", unit="step", disable=not progress) as bar:
            def step(name: str) -> None:
                if bar.n or name != "sampling":
                    bar.update(1)
                bar.set_postfix_str(name)

            metrics["chamfer"] = chamfer_distance(
                pred, gt, num_samples=args.num_samples, seed=args.seed, max_dist=args.max_dist,
                fscore_threshold=args.fscore_threshold, cull_views=cull_views,
                cull_dilation_px=args.cull_dilation, units=args.units, region=region,
                occluder=occluder, progress=step,
            )
            bar.update(bar.total - bar.n)
        metrics.update(mesh=str(mesh_path), gt=str(gt_path))
        if occluder is not None:
            metrics["occluder"] = str(occluder_path)
    if args.normals:
        with_gt = [v for v in views if v.normal_gt is not None]
        if not with_gt:
            source = getattr(views[0], "source", "") or str(target) if views else str(target)
            raise PolarInputError(source, "--normals: the dataset has no ground-truth normal maps "
                                  "(docs/readers.md lists which readers load them)")
        object_pixels = None
        if args.gt is not None and region == "object":
            # the same object as Chamfer's: a support plane in the masks (and GT normal maps) is left out
            object_pixels = mesh_silhouettes(gt, with_gt, occluder)
        per_view = _normal_errors(model, with_gt, progress, object_pixels)
        if not per_view:
            raise PolarInputError(target, "--normals: no view has ground-truth normals inside its mask")
        metrics["normal_mae_per_view"] = per_view
        metrics["normal_mae_deg"] = sum(per_view.values()) / len(per_view)
        metrics["normal_region"] = "masks" if object_pixels is None else "object"

    out = args.out or (target / "metrics.json" if is_run else target.with_name(target.stem + ".metrics.json"))
    try:
        with atomic_write(out) as handle:
            json.dump(_json_safe(metrics), handle, indent=2, allow_nan=False)
    except OSError as err:
        raise PolarInputError(out, f"cannot write the metrics ({err.strerror or err})") from None
    print(format_table(metrics))
    print(f"metrics written to {out}")
    return 0
