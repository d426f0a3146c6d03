"""What ``polargs generate`` / ``train`` / ``mesh`` / ``eval`` do, scripted with the service layer.

    python examples/service_run.py --out out/example-service --views 12 --size 64 --iters 300

Generates a bundled scene, trains Base and Full with the reference backend, meshes both runs and
prints their Chamfer distance and normal MAE against the scene's ground truth. Every call is a
function of ``polargs_plugin.service`` taking and returning plain objects (docs/api/service.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polargs_plugin import service


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="glossy_plane_sphere", help="bundled scene name")
    parser.add_argument("--views", type=int, default=12, help="number of views")
    parser.add_argument("--size", type=int, default=64, help="image width and height (pixels)")
    parser.add_argument("--iters", type=int, default=300, help="training iterations")
    parser.add_argument("--out", type=Path, default=Path("out/example-service"), help="scene and run folders go here")
    args = parser.parse_args(argv)

    scene = args.out / "scene"
    if not scene.is_dir():
        service.generate_scene_folder(service.SceneRequest(args.scene, views=args.views, width=args.size, height=args.size), scene)
    # the CPU preset with the PolarGS schedules scaled to the run's length (Dense, L_dn, L_n)
    factor = args.iters / 30_000
    results = {}
    for name, polar in (("base", None), ("full", service.polar_config("synthetic", factor))):
        out = args.out / name
        if not (out / "summary.json").is_file():
            train = service.train_config("cpu", factor, {"num_init_points": 500}, progress=False)
            service.train_run(service.TrainRequest(str(scene), out, train, polar), notify=print)
        run = service.load_run(out)
        service.mesh_run(run, service.MeshSettings(voxel=1.0 / args.size))
        metrics = service.evaluate(out, service.EvalSettings(gt=scene, normals=True, num_samples=100_000), run=run)
        results[name] = {"chamfer": metrics["chamfer"]["chamfer"], "normal_mae_deg": metrics["normal_mae_deg"]}
        print(f"{name:5s} Chamfer {results[name]['chamfer']:.4f}  normal MAE {results[name]['normal_mae_deg']:.2f} deg -> {out}")
    return results


if __name__ == "__main__":
    main()
