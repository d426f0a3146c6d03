"""Does polar-enhanced PatchMatch densification (Dense) help? Dense on vs off on a textureless scene.

Two reference-trainer runs on the same synthetic scene, seed, iterations and PolarHooks settings,
differing only in ``densify.enabled`` (PC, L_dn and L_scale identical in both; L_n exists only
with Dense, since its target N_opt is Dense's output). A third run, "seeds only", is Dense on with
L_n off, separating Dense's two outputs: the seeded Gaussians and the N_opt targets of L_n. Default scene ``glossy_plane_sphere``: its
sphere is textureless (uniform glossy red, shading and highlights only), the case PatchMatch
densification is meant for; its masks mark the sphere (the floor is background since generator
version 2), so PatchMatch works on the textureless sphere alone.
PatchMatch and the polarimetric filter use the synthetic data's azimuth model
(``data.synthetic.AZIMUTH_MODEL``, the physical one for an on-sensor polarizer grid), which is
the synthetic preset's (``PolarConfig.synthetic``, checked here). L_n covers every target pixel
until ``losses.normal_until_after_dense`` iterations after the Dense window, then the pixels whose
render agrees with the target within ``losses.normal_hold_deg`` (the preset's values).

Printed per run: Chamfer distance (accuracy, completeness, mean; scene units) of the TSDF mesh of
the rendered depths (``mesh.tsdf_fuse``, synthetic preset) against the object-only GT mesh in
``polargs eval``'s object region; normal MAE
(degrees) of the rendered normals against the GT normal maps inside the masks; training PSNR;
final Gaussians; Gaussians appended by Dense; pixels with an N_opt target (sum over views, end of
training) and the densifier's per-call counts; training seconds. Also the load average
(``uptime``): the machine is shared, wall times are inflated by contention.

Usage (a few minutes on 2 cores):
python bench/dense_effect.py [--scene glossy_plane_sphere] [--views 12] [--size 64] [--factor 0.02] [--threads 2]
    [--ln-after-dense preset|none|N] [--hold-deg preset|none|DEG]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time

import torch

from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.config import PolarConfig
from polargs_plugin.data.synthetic import AZIMUTH_MODEL, generate_scene
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.mesh import mesh_settings, tsdf_fuse
from polargs_plugin.metrics import chamfer_distance, normal_mae


def load() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average %.2f, %.2f, %.2f" % os.getloadavg()


def set_normal_loss_span(polar: PolarConfig, ln_after_dense: str, hold_deg: str) -> None:
    """The command line's L_n options ("preset", "none" or a number) on ``polar.losses``."""
    if ln_after_dense != "preset":
        polar.losses.normal_until_after_dense = None if ln_after_dense == "none" else int(ln_after_dense)
    if hold_deg != "preset":
        polar.losses.normal_hold_deg = None if hold_deg == "none" else float(hold_deg)


def run(scene, dense: bool, factor: float, seed: int, normal_loss: bool = True,
        ln_after_dense: str = "preset", hold_deg: str = "preset") -> dict[str, float]:
    polar = PolarConfig.cpu_demo(factor)
    set_normal_loss_span(polar, ln_after_dense, hold_deg)
    polar.densify.enabled = dense
    polar.losses.use_normal = normal_loss
    if {polar.densify.patchmatch.azimuth_model, polar.densify.filters.azimuth_model} != {AZIMUTH_MODEL}:
        raise SystemExit(f"the preset's azimuth model is not the synthetic data's ({AZIMUTH_MODEL})")
    hooks = PolarHooks(polar)
    trainer = Trainer(scene.views, TrainConfig.cpu(factor, progress=False, seed=seed), hooks=hooks)
    appended, l_n = 0, []
    start = time.perf_counter()
    while trainer.iteration < trainer.config.iterations:
        logs = trainer.step()
        appended += int(logs.get("appended", 0))
        if "l_n" in logs:
            l_n.append(logs["l_n"])
    seconds = time.perf_counter() - start
    with torch.no_grad():
        renders = [trainer.render(view) for view in trainer.views]
    views = scene.views
    normals = [torch.nn.functional.normalize(r.normal.cpu(), dim=0) for r in renders]
    mesh = tsdf_fuse(
        [r.depth.cpu() for r in renders], [r.color.cpu() for r in renders], [v.K for v in views],
        [v.world_to_camera for v in views], masks=[v.mask for v in views], **mesh_settings("synthetic"),
    )
    # the object-only GT in `polargs eval`'s object region (glossy_plane_sphere's floor is support)
    cd = chamfer_distance(mesh, scene.object_mesh(), num_samples=200_000, cull_views=views, region="object")
    targets = [hooks.normal_target(v.name) for v in views]
    densifier = hooks._densifier
    return {
        "accuracy": float(cd["accuracy"]),
        "completeness": float(cd["completeness"]),
        "chamfer": float(cd["chamfer"]),
        "normal_mae": normal_mae(normals, [v.normal_gt for v in views], [v.mask for v in views]),
        "psnr": trainer.evaluate(),
        "gaussians": trainer.model.num,
        "dense_added": appended,
        "nopt_pixels": sum(int(t[1].sum()) for t in targets if t is not None),
        "l_n_nonzero": sum(v > 0 for v in l_n),
        "seconds": seconds,
        "stats": dict(densifier.stats) if densifier is not None else {},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="glossy_plane_sphere")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--factor", type=float, default=0.02, help="schedule factor (0.02 = 600 iterations)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--ln-after-dense", default="preset",
                        help="losses.normal_until_after_dense: 'preset', 'none' (L_n to the end) or iterations")
    parser.add_argument("--hold-deg", default="preset",
                        help="losses.normal_hold_deg: 'preset', 'none' (L_n stops after the window) or degrees")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    demo = PolarConfig.cpu_demo(args.factor)
    set_normal_loss_span(demo, args.ln_after_dense, args.hold_deg)
    d, until, hold = demo.densify, demo.losses.normal_until_after_dense, demo.losses.normal_hold_deg
    print(f"{load()}\nscene {args.scene}: {args.views} views {args.size}x{args.size}, "
          f"{round(30_000 * args.factor)} iterations, Dense every {d.interval} from {d.start_iter} "
          f"to {d.end_iter}, L_n until {'the end' if until is None else d.end_iter + until}"
          f"{'' if until is None or hold is None else f', then held within {hold:g} deg'}, "
          f"azimuth model {AZIMUTH_MODEL}, seed {args.seed}, {args.threads} threads")
    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    runs = (("Dense off", False, True), ("Dense on", True, True), ("seeds only", True, False))
    results = {name: run(scene, on, args.factor, args.seed, l_n, args.ln_after_dense, args.hold_deg) for name, on, l_n in runs}
    keys = ("accuracy", "completeness", "chamfer", "normal_mae", "psnr", "gaussians", "dense_added",
            "nopt_pixels", "l_n_nonzero", "seconds")
    print(f"{'':11s}" + "".join(f"{k:>13s}" for k in keys))
    for name, res in results.items():
        print(f"{name:11s}" + "".join(f"{res[k]:13.4f}" if isinstance(res[k], float) else f"{res[k]:13d}" for k in keys))
    off, on = results["Dense off"], results["Dense on"]
    seeds = results["seeds only"]
    print(f"densifier totals over all calls (pixels; added = Gaussians): {on['stats']}")
    print(f"Dense on / off: Chamfer x{on['chamfer'] / off['chamfer']:.3f} (accuracy x{on['accuracy'] / off['accuracy']:.3f}, "
          f"completeness x{on['completeness'] / off['completeness']:.3f}), normal MAE x{on['normal_mae'] / off['normal_mae']:.3f}, "
          f"time x{on['seconds'] / off['seconds']:.2f}")
    print(f"seeds only / off: Chamfer x{seeds['chamfer'] / off['chamfer']:.3f}, "
          f"normal MAE x{seeds['normal_mae'] / off['normal_mae']:.3f}")
    print(load())
    print(json.dumps({"bench": "dense_effect", "scene": args.scene, "views": args.views, "size": args.size,
                      "factor": args.factor, "seed": args.seed,
                      "runs": {name: {k: res[k] for k in keys} for name, res in results.items()},
                      "chamfer_on_vs_off": on["chamfer"] / off["chamfer"],
                      "normal_mae_on_vs_off": on["normal_mae"] / off["normal_mae"],
                      "time_on_vs_off": on["seconds"] / off["seconds"],
                      "chamfer_seeds_only_vs_off": seeds["chamfer"] / off["chamfer"]}))


if __name__ == "__main__":
    main()
