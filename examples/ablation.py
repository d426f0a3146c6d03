"""The paper's plug-and-play ablation (Base / w/o Dense / w/o PC / Full) with the reference trainer.

Each variant is the same training with PolarConfig switches: Base = no hooks (plain 3DGS);
w/o Dense = ``densify.enabled = False``; w/o PC = ``correction.enabled = False`` (the PC
loss then has no masks); Full = everything. Figures: Chamfer distance of the TSDF mesh to the
ground-truth mesh and normal MAE of the rendered normals, both against the scene's ground truth.

    python examples/ablation.py --scene glossy_plane_sphere --size 96 --views 16 --factor 0.02

(``polargs ablate`` will run such grids over scenes and seeds with a report; this is the
minimal version written against the public API.)
"""

from __future__ import annotations

import argparse

import torch

from polargs_plugin import PolarConfig, PolarHooks
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.mesh import tsdf_fuse
from polargs_plugin.metrics import chamfer_distance, normal_mae

VARIANTS = ("base", "no-dense", "no-pc", "full")


def polar_config(variant: str, factor: float) -> PolarConfig | None:
    """The PolarConfig of an ablation variant (None = Base, no hooks)."""
    if variant == "base":
        return None
    config = PolarConfig.cpu_demo(factor)
    config.densify.enabled = variant != "no-dense"
    config.correction.enabled = variant != "no-pc"
    return config


@torch.no_grad()
def evaluate(trainer: Trainer, scene) -> dict[str, float]:
    renders = [trainer.render(view) for view in trainer.views]
    mesh = tsdf_fuse([r.depth for r in renders], [r.color for r in renders], [v.K for v in trainer.views],
                     [v.world_to_camera for v in trainer.views], masks=[v.mask for v in trainer.views])
    chamfer = chamfer_distance(mesh, (scene.mesh_vertices, scene.mesh_triangles), num_samples=100_000,
                               cull_views=trainer.views)
    masks = [v.mask & (r.alpha > 0.5) for v, r in zip(trainer.views, renders)]
    mae = normal_mae([r.normal for r in renders], [v.normal_gt for v in trainer.views], masks)
    return {"chamfer": float(chamfer["chamfer"]), "normal_mae_deg": mae}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="glossy_plane_sphere", help="bundled scene name")
    parser.add_argument("--views", type=int, default=16, help="number of views")
    parser.add_argument("--size", type=int, default=96, help="image width and height (pixels)")
    parser.add_argument("--factor", type=float, default=0.02, help="schedule factor (0.02 = 600 iterations)")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of " + ",".join(VARIANTS))
    args = parser.parse_args(argv)
    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    results = {}
    for variant in args.variants.split(","):
        if variant not in VARIANTS:
            parser.error(f"--variants: unknown variant '{variant}' (known: {', '.join(VARIANTS)})")
        config = polar_config(variant, args.factor)
        trainer = Trainer(scene.views, TrainConfig.cpu(args.factor, progress=False),
                          hooks=None if config is None else PolarHooks(config))
        trainer.train()
        results[variant] = evaluate(trainer, scene)
        print(f"{variant:9s} Chamfer {results[variant]['chamfer']:.4f}  normal MAE "
              f"{results[variant]['normal_mae_deg']:.2f} deg  ({trainer.model.num} Gaussians)", flush=True)
    return results


if __name__ == "__main__":
    main()
