"""Does polar-guided photometric correction (PC) help? PC on vs off on a highlight-rich scene.

Two reference-trainer runs on the same synthetic scene, seed and settings, differing only in
``correction.enabled`` (Dense off in both, so PC's effect is isolated; L_dn and L_scale on in both).
Printed per run:

- highlight colour error: mean |rendered colour - true diffuse colour| inside the scene's
  highlight masks (the true diffuse colour is what PC's I_diff / I_chro aim at), with the same
  error of the input image itself as a reference;
- normal MAE (degrees) of the rendered normals against the ground truth, inside the object masks;
- Chamfer distance and F-score of the TSDF mesh of the rendered depths against the object-only GT
  mesh in `polargs eval`'s object region.

Runs a few minutes on 2 cores. Usage:
python bench/pc_effect.py [--scene bumpy_mixed] [--views 16] [--size 96] [--factor 0.05] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.config import PolarConfig
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.mesh import mesh_settings, tsdf_fuse
from polargs_plugin.metrics import chamfer_distance, normal_mae


def highlight_error(images: list[torch.Tensor], scene) -> float:
    """Mean absolute colour error against diffuse_gt over all highlight pixels of all views."""
    total, count = 0.0, 0
    for image, diffuse, mask in zip(images, scene.diffuse_gt, scene.highlight_masks):
        total += float(((image - diffuse).abs() * mask).sum())
        count += int(mask.sum()) * image.shape[0]
    return total / max(count, 1)


def run(scene, correction: bool, factor: float, seed: int) -> dict[str, float]:
    polar = PolarConfig.cpu_demo(factor)
    polar.densify.enabled = False
    polar.correction.enabled = correction
    trainer = Trainer(scene.views, TrainConfig.cpu(factor, progress=False, seed=seed), hooks=PolarHooks(polar))
    start = time.perf_counter()
    trainer.train()
    seconds = time.perf_counter() - start
    with torch.no_grad():
        renders = [trainer.render(view) for view in trainer.views]
    views = scene.views
    colours = [r.color.cpu() for r in renders]
    normals = [torch.nn.functional.normalize(r.normal.cpu(), dim=0) for r in renders]
    mesh = tsdf_fuse(
        [r.depth.cpu() for r in renders], colours, [v.K for v in views], [v.world_to_camera for v in views],
        masks=[v.mask for v in views], **mesh_settings("synthetic"),
    )
    # the object-only GT in `polargs eval`'s object region (glossy_plane_sphere's floor is support)
    cd = chamfer_distance(mesh, scene.object_mesh(), num_samples=200_000, cull_views=views, region="object")
    return {
        "highlight_err": highlight_error(colours, scene),
        "normal_mae": normal_mae(normals, [v.normal_gt for v in views], [v.mask for v in views]),
        "chamfer": float(cd["chamfer"]),
        "fscore": float(cd.get("fscore", float("nan"))),
        "psnr": trainer.evaluate(),
        "gaussians": trainer.model.num,
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bumpy_mixed")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--factor", type=float, default=0.05, help="schedule factor (0.05 = 1500 iterations)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    highlight = sum(int(m.sum()) for m in scene.highlight_masks) / sum(int(v.mask.sum()) for v in scene.views)
    print(f"scene {args.scene}: {args.views} views {args.size}x{args.size}, highlights {highlight:.1%} of "
          f"the object pixels; input image error in highlights "
          f"{highlight_error([v.image for v in scene.views], scene):.4f}")
    results = {name: run(scene, on, args.factor, args.seed) for name, on in (("PC off", False), ("PC on", True))}
    keys = ("highlight_err", "normal_mae", "chamfer", "fscore", "psnr", "gaussians", "seconds")
    print(f"{'':8s}" + "".join(f"{k:>15s}" for k in keys))
    for name, res in results.items():
        print(f"{name:8s}" + "".join(f"{res[k]:15.4f}" if isinstance(res[k], float) else f"{res[k]:15d}" for k in keys))
    off, on = results["PC off"], results["PC on"]
    print(f"PC on / off: highlight error x{on['highlight_err'] / off['highlight_err']:.3f}, "
          f"normal MAE x{on['normal_mae'] / off['normal_mae']:.3f}, Chamfer x{on['chamfer'] / off['chamfer']:.3f}")
    print(json.dumps({"bench": "pc_effect", "scene": args.scene, "views": args.views, "size": args.size,
                      "factor": args.factor, "seed": args.seed,
                      "runs": {name: {k: res[k] for k in keys} for name, res in results.items()},
                      "highlight_err_on_vs_off": on["highlight_err"] / off["highlight_err"],
                      "normal_mae_on_vs_off": on["normal_mae"] / off["normal_mae"],
                      "chamfer_on_vs_off": on["chamfer"] / off["chamfer"]}))


if __name__ == "__main__":
    main()
