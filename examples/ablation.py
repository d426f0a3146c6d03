"""The paper's plug-and-play ablation (base / reg / no-dense / no-pc / full) on one bundled scene.

The variants are defined once, in :mod:`polargs_plugin.ablation.variants` (docs/ablation.md);
each grid cell is plain data and :func:`polargs_plugin.ablation.cell.run_cell` trains, meshes
(TSDF), evaluates against the ground truth (Chamfer, normal MAE) and writes its run folder.

    python examples/ablation.py --scene glossy_plane_sphere --size 96 --views 16 --factor 0.02

``polargs ablate`` runs such grids over scenes and seeds, in parallel, resumable, with a report;
this is the minimal loop written against the same API.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polargs_plugin.ablation.cell import CellFailed, run_cell
from polargs_plugin.ablation.grid import expand
from polargs_plugin.ablation.scenes import parse_scene
from polargs_plugin.ablation.variants import VARIANTS, parse_variants, polar_config  # noqa: F401 (polar_config: the per-variant PolarConfig)


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="glossy_plane_sphere", help="bundled scene name")
    parser.add_argument("--views", type=int, default=16, help="number of views")
    parser.add_argument("--size", type=int, default=96, help="image width and height (pixels)")
    parser.add_argument("--factor", type=float, default=0.02, help="schedule factor (0.02 = 600 iterations)")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of " + ",".join(VARIANTS))
    parser.add_argument("--seed", type=int, default=0, help="training seed")
    parser.add_argument("--out", type=Path, default=Path("out/example-ablation"), help="run folders go here")
    args = parser.parse_args(argv)
    try:
        variants = parse_variants(args.variants)
    except ValueError as err:
        parser.error(f"--variants: {err}")
    scene = parse_scene(args.scene, args.out / "scenes", args.views, args.size, args.size)
    cells = expand([scene], variants, [args.seed], args.out, factor=args.factor,
                   mesh={"voxel": 1.0 / args.size},  # the synthetic TSDF voxel (1/128 at 128 px) per pixel size
                   eval={"num_samples": 100_000})
    results = {}
    for cell in cells:
        try:
            summary = run_cell(cell)  # skipped (read back) when its run folder exists
        except CellFailed as failure:
            print(f"{cell.variant:9s} failed: {failure}", flush=True)
            continue
        figures = summary["figures"]
        results[cell.variant] = {"chamfer": figures["chamfer"], "normal_mae_deg": figures["normal_mae_deg"]}
        print(f"{cell.variant:9s} Chamfer {figures['chamfer']:.4f}  normal MAE {figures['normal_mae_deg']:.2f} deg  "
              f"({figures['num_gaussians']} Gaussians) -> {cell.run_dir}", flush=True)
    return results


if __name__ == "__main__":
    main()
