"""Forward + backward of each CPU stand-in of an upstream CUDA rasterizer against the reference
rasterizer's, in the same run.

Scene: a bundled scene (``generate_scene``, default glossy_plane_sphere) and its cameras, 128x128;
6000 Gaussians lying flat on its ground-truth surface (area-weighted samples, the shortest axis
along the triangle's normal, 0.5-1.2 times the sample spacing wide, opacity 0.4-0.95, SH degree 3
with a random DC colour), the footprint of a model in training rather than of an initialisation.

One step: the next camera's render, a fixed random weighting of every image the rasterizer
returns (the stand-ins' extra maps included: 2024's inverse depth, GOF's 9 channels, PGSR's
all-map and plane depth, 2DGS's allmap; the reference's colour, depth, median depth, normal,
alpha and plane depth), and backward into the Gaussians (and the trainer's screen-space tensors).
Each stand-in is called the way its upstream trainer calls its CUDA rasterizer (raster settings,
``means2D`` zero tensors, SH coefficients); gsplat's through ``rasterization(packed=False)``.

Timing: after a warm-up block of each (numba compiles), ``--rounds`` rounds; in each, every
stand-in (in a rotated order) runs a block of ``--block`` steps right after a block of the
reference's. The ratio is the median over the rounds of (stand-in block) / (the reference block
just before it), so that the speed drift of a shared machine cancels out; the ratio of the mean
step times is printed beside it. The last line is one JSON object: per-stand-in ratios and
``standin_over_base``, the worst ratio.

    .venv/bin/python bench/standins.py                      # 128x128, 6000 Gaussians, 1 thread
    .venv/bin/python bench/standins.py --threads 2 --rounds 12
    .venv/bin/python bench/standins.py --size 64 --gaussians 1000 --rounds 2 --block 2   # runs?
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.dryrun.standins import (
    gof,
    graphdeco_2023,
    graphdeco_2024,
    gsplat,
    plane,
    surfel,
)
from polargs_plugin.geometry import SH_C0

STANDINS = ("graphdeco_2023", "graphdeco_2024", "gof", "plane", "surfel", "gsplat")


def surface_gaussians(vertices: np.ndarray, triangles: np.ndarray, count: int, seed: int) -> dict[str, torch.Tensor]:
    """``count`` flat Gaussians on a triangle mesh (float32 leaves; module docstring)."""
    rng = np.random.default_rng(seed)
    corners = vertices[triangles]  # (F, 3, 3)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    face = rng.choice(len(triangles), size=count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    a, b, c = corners[face, 0], corners[face, 1], corners[face, 2]
    means = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    normal = cross[face] / np.maximum(np.linalg.norm(cross[face], axis=1, keepdims=True), 1e-12)
    # the rotation taking +z to the normal: q = (1 + n_z, z x n) normalised, (w, x, y, z)
    quats = np.stack([1.0 + normal[:, 2], -normal[:, 1], normal[:, 0], np.zeros(count)], axis=1)
    flipped = quats[:, 0] < 1e-6  # normal = -z: a half turn about x
    quats[flipped] = [0.0, 1.0, 0.0, 0.0]
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    spacing = math.sqrt(area.sum() / count)
    tangent = spacing * rng.uniform(0.5, 1.2, size=(count, 2))
    scales = np.concatenate([tangent, 0.02 * tangent[:, :1]], axis=1)
    sh = 0.05 * rng.standard_normal((count, 16, 3))
    sh[:, 0] = (rng.random((count, 3)) - 0.5) / SH_C0
    params = {"means": means, "quats": quats, "scales": scales, "opacities": rng.uniform(0.4, 0.95, count), "sh": sh}
    return {k: torch.tensor(v, dtype=torch.float32) for k, v in params.items()}


class Weights:
    """A fixed random weighting of each image output (by name and shape), the same every step."""

    def __init__(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(seed)
        self.images: dict[tuple, torch.Tensor] = {}

    def loss(self, **images: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(())
        for name, image in images.items():
            key = (name, tuple(image.shape))
            if key not in self.images:
                self.images[key] = torch.rand(image.shape, generator=self.generator)
            total = total + (image * self.images[key]).sum()
        return total


def _settings_fields(view, width: int, height: int) -> dict:
    w2c = view.world_to_camera.float()
    K = view.K.float()
    return {
        "image_height": height, "image_width": width, "tanfovx": width / (2.0 * float(K[0, 0])),
        "tanfovy": height / (2.0 * float(K[1, 1])), "bg": torch.zeros(3), "scale_modifier": 1.0,
        "viewmatrix": w2c.T.contiguous(), "projmatrix": w2c.T.contiguous(), "sh_degree": 3,
        "campos": torch.linalg.inv(w2c)[:3, 3], "prefiltered": False, "debug": False,
    }


def step_functions(params: dict, views: list, width: int, height: int, seed: int) -> dict[str, Callable[[int], None]]:
    """name -> step(i): forward + backward of view i % len(views) (module docstring)."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    means, quats, scales, opac, sh = (leaves[k] for k in ("means", "quats", "scales", "opacities", "sh"))
    n = means.shape[0]
    weights = Weights(seed)

    def screen() -> torch.Tensor:
        return torch.zeros(n, 3, requires_grad=True)

    def finish(loss: torch.Tensor) -> None:
        for leaf in leaves.values():
            leaf.grad = None
        loss.backward()

    def reference(view) -> None:
        out = rasterize(means, quats, scales, opac, sh, view.K.float(), view.world_to_camera.float(), width, height)
        finish(weights.loss(color=out.color, depth=out.depth, median=out.median_depth, normal=out.normal,
                            alpha=out.alpha, plane=out.plane_depth))

    def graphdeco_2023_step(view) -> None:
        s = graphdeco_2023.GaussianRasterizationSettings(**_settings_fields(view, width, height))
        image, _ = graphdeco_2023.GaussianRasterizer(s)(means, screen(), opac[:, None], shs=sh, scales=scales,
                                                         rotations=quats)
        finish(weights.loss(color=image))

    def graphdeco_2024_step(view) -> None:
        s = graphdeco_2024.GaussianRasterizationSettings(**_settings_fields(view, width, height), antialiasing=False)
        image, _, inverse = graphdeco_2024.GaussianRasterizer(s)(means, screen(), opac[:, None], shs=sh[:, 1:],
                                                                  dc=sh[:, :1], scales=scales, rotations=quats)
        finish(weights.loss(color=image, inverse=inverse))

    def gof_step(view) -> None:
        fields = _settings_fields(view, width, height)
        s = gof.GaussianRasterizationSettings(
            height, width, fields["tanfovx"], fields["tanfovy"], 0.1, torch.zeros(height, width, 2), fields["bg"], 1.0,
            fields["viewmatrix"], fields["projmatrix"], 3, fields["campos"], False, False)
        render, _ = gof.GaussianRasterizer(s)(means, screen(), opac[:, None], shs=sh, scales=scales, rotations=quats)
        finish(weights.loss(render=render))

    def plane_step(view) -> None:
        fields = _settings_fields(view, width, height)
        s = plane.GaussianRasterizationSettings(**{k: fields[k] for k in list(fields)[:11]}, render_geo=True,
                                                debug=False)
        # PGSR's all-map: camera-frame normal, 1, plane distance (here from the rotation's axis)
        w2c = view.world_to_camera.float()
        normal = torch.nn.functional.normalize(quats[:, 1:], dim=-1) @ w2c[:3, :3].T
        cam = means @ w2c[:3, :3].T + w2c[:3, 3]
        all_map = torch.cat([normal, torch.ones(n, 1), -(normal * cam).sum(-1, keepdim=True)], dim=1)
        color, _, _, maps, depth = plane.GaussianRasterizer(s)(means, screen(), screen(), opac[:, None], shs=sh,
                                                               scales=scales, rotations=quats, all_map=all_map)
        finish(weights.loss(color=color, maps=maps, depth=depth))

    def surfel_step(view) -> None:
        s = surfel.GaussianRasterizationSettings(**_settings_fields(view, width, height))
        color, _, allmap = surfel.GaussianRasterizer(s)(means, screen(), opac[:, None], shs=sh, scales=scales[:, :2],
                                                        rotations=quats)
        finish(weights.loss(color=color, allmap=allmap))

    def gsplat_step(view) -> None:
        colors, alphas, _ = gsplat.rasterization(
            means, quats, scales, opac, sh, view.world_to_camera.float()[None], view.K.float()[None], width, height,
            sh_degree=3, packed=False)
        finish(weights.loss(color=colors, alpha=alphas))

    steps = {"reference": reference, "graphdeco_2023": graphdeco_2023_step, "graphdeco_2024": graphdeco_2024_step,
             "gof": gof_step, "plane": plane_step, "surfel": surfel_step, "gsplat": gsplat_step}
    return {name: (lambda i, f=f: f(views[i % len(views)])) for name, f in steps.items()}


def paired_ratio(blocks: list[float], reference_blocks: list[float]) -> float:
    """Median over the rounds of a block's mean step time over that of the reference block
    run just before it.

    >>> paired_ratio([1.1, 2.2, 1.21], [1.0, 2.0, 1.0])
    1.1
    """
    return statistics.median(b / r for b, r in zip(blocks, reference_blocks))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="glossy_plane_sphere")
    parser.add_argument("--size", type=int, default=128, help="image width and height")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--gaussians", type=int, default=6000)
    parser.add_argument("--block", type=int, default=6, help="steps a block")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--standins", default=",".join(STANDINS), help=f"comma-separated, of {', '.join(STANDINS)}")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    names = [s for s in args.standins.split(",") if s]
    unknown = sorted(set(names) - set(STANDINS))
    if unknown:
        parser.error(f"unknown stand-ins {', '.join(unknown)}; choose from {', '.join(STANDINS)}")
    torch.set_num_threads(args.threads)  # numba's kernels follow torch's count
    load_before = os.getloadavg()

    scene = generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)
    params = surface_gaussians(scene.mesh_vertices, scene.mesh_triangles, args.gaussians, args.seed)
    steps = step_functions(params, scene.views, args.size, args.size, args.seed)
    counter = iter(range(1 << 62))

    def block(name: str) -> float:
        start = time.perf_counter()
        for _ in range(args.block):
            steps[name](next(counter))
        return (time.perf_counter() - start) / args.block

    for name in ["reference", *names]:
        block(name)  # warm-up: compiles, caches
    times: dict[str, list[float]] = {name: [] for name in names}
    ref_times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(args.rounds):
        for name in names[r % len(names):] + names[: r % len(names)]:
            ref_times[name].append(block("reference"))
            times[name].append(block(name))

    all_ref = [t for ts in ref_times.values() for t in ts]
    ratios = {name: paired_ratio(times[name], ref_times[name]) for name in names}
    load_after = os.getloadavg()
    print(f"stand-ins bench: {args.gaussians} Gaussians, {args.size}x{args.size}, {args.scene}, {args.threads} thread(s), "
          f"{args.rounds} rounds of {args.block}-step blocks; load {load_before[0]:.2f} -> {load_after[0]:.2f}")
    print(f"{'rasterizer':<16} {'s/step':>9} {'x reference':>12} {'x ref (means)':>14}")
    print(f"{'reference':<16} {statistics.fmean(all_ref):>9.4f} {1.0:>12.2f} {1.0:>14.2f}")
    for name in names:
        mean = statistics.fmean(times[name])
        print(f"{name:<16} {mean:>9.4f} {ratios[name]:>12.2f} {mean / statistics.fmean(ref_times[name]):>14.2f}")
    worst = max(ratios, key=ratios.get)
    print(f"KEY: worst stand-in {worst} at {ratios[worst]:.2f}x the reference rasterizer's forward+backward")
    figures = {
        "bench": "standins", "scene": args.scene, "size": args.size, "gaussians": args.gaussians,
        "threads": args.threads, "rounds": args.rounds, "block": args.block,
        "load_1min_before": round(load_before[0], 2), "load_1min_after": round(load_after[0], 2),
        "reference_s": round(statistics.fmean(all_ref), 5),
        "standin_s": {name: round(statistics.fmean(times[name]), 5) for name in names},
        "ratios": {name: round(v, 3) for name, v in ratios.items()},
        "standin_over_base": round(ratios[worst], 3),
    }
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
