"""Where do a trained model's normals go wrong? Normal error by distance to the contours.

For each run folder (`polargs train`, or a cell of `polargs ablate`) the model's normals are
rendered, in the compositing order and tile size it was trained with, into every training view
that has ground-truth normals and depth, and compared with the ground truth: the normal MAE
computed as `polargs eval` does (per view, then over the views) and the
angular error pooled over the pixels in bands of distance to the nearest contour, a silhouette or
an occlusion edge of the ground-truth depth (0-2, 2-4, 4-8 and beyond 8 px;
`polargs_plugin.metrics.normal_errors_by_contour_distance`).

`--render ORDER:TILE` adds a row per run rendered with another compositing order and tile size
(the model is unchanged): `--render ray:1` composites a ray-ordered model exactly per pixel, as
`polargs mesh`, `polargs eval` and the ablation's pictures do, which shows what its training
tiles cost.

Usage (a few seconds a run on 2 cores at 128-160 px):
python bench/normal_bands.py RUN [RUN ...] [--render ray:1] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

from polargs_plugin.backends.reference.rasterizer import parse_order_and_tile
from polargs_plugin.io import PolarInputError
from polargs_plugin.metrics import CONTOUR_BANDS_PX, normal_errors_by_contour_distance, normal_mae
from polargs_plugin.service.evaluation import normal_mask
from polargs_plugin.service.runs import load_run


def load() -> str:
    return "load average %.2f, %.2f, %.2f" % os.getloadavg()


def parse_render(spec: str) -> tuple[str, int]:
    """'ORDER:TILE' -> (order, tile size); argparse error otherwise."""
    try:
        return parse_order_and_tile(spec, "--render")
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def band_figures(model, views) -> dict:
    """Normal MAE and the contour bands of ``model`` over ``views`` (those with GT normals and depth)."""
    pred, gt, masks, depths = [], [], [], []
    with torch.no_grad():
        for view in views:
            mask = normal_mask(view)
            if not bool(mask.any()):
                continue
            pred.append(model.render(view).normal.cpu())
            gt.append(view.normal_gt.cpu())
            masks.append(mask.cpu())
            depths.append(view.depth_gt.cpu())
    return {
        "normal_mae_deg": normal_mae(pred, gt, masks),
        "bands": normal_errors_by_contour_distance(pred, gt, masks, depths),
    }


def band_label(band: dict) -> str:
    return f"> {band['low']:g} px" if band["high"] == float("inf") else f"{band['low']:g}-{band['high']:g} px"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with summary.json and checkpoint.pt)")
    parser.add_argument("--render", action="append", type=parse_render, default=[], metavar="ORDER:TILE",
                        help="also render each run with this compositing order and tile size (repeatable)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    for folder in args.runs:
        try:
            run = load_run(folder)
        except PolarInputError as err:
            raise SystemExit(f"normal_bands.py: {err}") from None
        views = [v for v in run.dataset.views if v.normal_gt is not None and v.depth_gt is not None]
        if not views:
            raise SystemExit(f"{folder}: no view with ground-truth normals and depth; nothing to compare")
        trained = (run.model.order, run.model.tile_size)
        for order, tile in [trained, *[r for r in args.render if r != trained]]:
            run.model.order, run.model.tile_size = order, tile
            figures = band_figures(run.model, views)
            rows.append({"run": str(folder), "order": order, "tile_size": tile,
                         "trained_as": f"{trained[0]}:{trained[1]}", **figures})
        run.model.order, run.model.tile_size = trained

    labels = [band_label(b) for b in rows[0]["bands"]]
    print(f"Normal error (deg) by distance to the nearest contour; {load()}")
    print("| run | rendered as (trained as) | normal MAE | " + " | ".join(labels) + " |")
    print("|---|---|---|" + "---|" * len(labels))
    for r in rows:
        cells = " | ".join(f"{b['mae_deg']:.2f} ({b['share']:.0%})" for b in r["bands"])
        print(f"| {Path(r['run']).name} | {r['order']}:{r['tile_size']} ({r['trained_as']}) | {r['normal_mae_deg']:.2f} | {cells} |")
    print("(each band: mean error over its pixels, pooled over the views, and its share of them; "
          f"band edges {CONTOUR_BANDS_PX} px)")
    print(json.dumps({"bench": "normal_bands", "rows": rows}, default=float))


if __name__ == "__main__":
    main()
