"""Which surface does each compositing order render best? The rendering side of the inward bias.

Flat, opaque splats are laid on the ground-truth surface of a generated scene (tangent, one
footprint apart, each coloured with the true diffuse colour of its surface point, read from the
view that sees that point most squarely), moved k pixel footprints along the outward normal
(negative = inside the object), and rendered, untrained, into every view twice: in mean-depth
order ("center", vanilla 3DGS, 16-px tiles) and in ray order ("ray", one-pixel tiles: exact per
pixel). The error is the mean absolute difference to the true diffuse images over the pixels at
least 6 px from the mask's edge and 3 px from a depth jump, so neither silhouettes nor
occlusion edges enter it.

A renderer that draws the surface where it lies has its smallest error at k = 0. Mean-depth
order composites, of two overlapping splats, the one whose centre is nearer the camera on top,
which on a curved surface shows each colour displaced towards the far side of its splat; a model
recessed into the surface puts the colours back, and photometric training finds that model.

Usage (about 1.5 minutes a scene with the default offsets on 2 cores):
python bench/composite_order.py [--scenes family:253,torus_knot] [--splats 40000]
    [--offsets -1.5,-1,-0.5,0,0.5] [--eps2d 0.1] [--threads 2]

``--splats`` sets the splats' size (each as wide as their spacing): fewer, larger splats are
closer to a trained CPU-preset model's. ``--eps2d`` is the screen dilation of every render
(default: the CPU preset's, which trained models use).
"""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np
import open3d as o3d
import torch
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from scipy.ndimage import distance_transform_edt

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.backends.reference.trainer import CPU_EPS2D
from polargs_plugin.data.family import generate_family_scene, parse_family
from polargs_plugin.data.synthetic import SyntheticScene, generate_scene
from polargs_plugin.densify.seeding import frames_from_normals
from polargs_plugin.geometry import rgb_to_sh
from polargs_plugin.metrics import depth_jumps

ORDERS = (("center", 16), ("ray", 1))


def load() -> str:
    return "load average %.2f, %.2f, %.2f" % os.getloadavg()


def make_scene(name: str) -> SyntheticScene:
    seed = parse_family(name)
    return generate_family_scene(seed) if seed is not None else generate_scene(name)


def splats_on_surface(scene: SyntheticScene, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """(points (N, 3), outward normals (N, 3), spacing): uniform samples of the object's surface."""
    vertices, triangles = scene.object_mesh()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(seed)
    cloud = mesh.sample_points_uniformly(count, use_triangle_normal=True)
    return np.asarray(cloud.points), np.asarray(cloud.normals), math.sqrt(mesh.get_surface_area() / count)


def true_colours(scene: SyntheticScene, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) diffuse colour of each surface point, from the view that sees it most squarely
    (nearest pixel; visible = its camera z within 1 % of that view's GT depth)."""
    colours, best = np.zeros((len(points), 3)), np.full(len(points), -1.0)
    for view, diffuse in zip(scene.views, scene.diffuse_gt):
        w2c, K = view.world_to_camera.double().numpy(), view.K.double().numpy()
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        u = np.floor(K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]).astype(int)
        v = np.floor(K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]).astype(int)
        inside = (u >= 0) & (v >= 0) & (u < view.width) & (v < view.height) & (cam[:, 2] > 0)
        u, v = np.clip(u, 0, view.width - 1), np.clip(v, 0, view.height - 1)
        depth = view.depth_gt[0].numpy()[v, u]
        seen = inside & (np.abs(depth - cam[:, 2]) < 0.01 * cam[:, 2])
        facing = ((normals @ w2c[:3, :3].T) * -cam / np.linalg.norm(cam, axis=1, keepdims=True)).sum(1)
        better = seen & (facing > best)
        colours[better] = diffuse.numpy()[:, v[better], u[better]].T
        best[better] = facing[better]
    return colours


def scored_pixels(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: inside the object, >= 6 px from the mask's edge and >= 3 px from a depth jump (> 5 %)."""
    return (distance_transform_edt(depth > 0) > 6) & (distance_transform_edt(~depth_jumps(depth)) > 3)


def footprint(scene: SyntheticScene) -> float:
    """Median over the views of the median GT depth / focal on the object (scene units a pixel)."""
    return float(np.median([float(v.depth_gt[v.depth_gt > 0].median()) / float(v.K[0, 0]) for v in scene.views]))


def tangent_quaternions(normals: np.ndarray) -> torch.Tensor:
    """(N, 4) wxyz rotations whose local z (the splat's shortest axis) is ``normals``, as Dense
    orients its seeds."""
    frames = frames_from_normals(torch.tensor(normals, dtype=torch.float32))
    return rotation_matrix_to_quaternion(frames.contiguous())


def errors(scene: SyntheticScene, count: int, offsets: list[float], eps2d: float) -> dict[str, dict[float, float]]:
    points, normals, spacing = splats_on_surface(scene, count)
    colours = true_colours(scene, points, normals)
    step = footprint(scene)
    quats = tangent_quaternions(normals)
    scales = torch.tensor([spacing, spacing, 1e-4 * spacing], dtype=torch.float32).expand(count, 3).contiguous()
    sh = rgb_to_sh(torch.tensor(colours, dtype=torch.float32))[:, None, :]
    opacities = torch.full((count,), 0.99)
    scored = [scored_pixels(v.depth_gt[0].numpy()) for v in scene.views]
    out: dict[str, dict[float, float]] = {order: {} for order, _ in ORDERS}
    for k in offsets:
        means = torch.tensor(points + k * step * normals, dtype=torch.float32)
        for order, tile in ORDERS:
            diffs = []
            for view, diffuse, keep in zip(scene.views, scene.diffuse_gt, scored):
                render = rasterize(means, quats, scales, opacities, sh, view.K.float(), view.world_to_camera.float(),
                                   view.width, view.height, background=torch.zeros(3), order=order, tile_size=tile,
                                   eps2d=eps2d, with_plane_depth=False)
                diffs.append((render.color.clamp(0, 1) - diffuse).abs().mean(0).numpy()[keep])
            out[order][k] = float(np.concatenate(diffs).mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="family:253,torus_knot")
    parser.add_argument("--splats", type=int, default=40_000)
    parser.add_argument("--offsets", default="-1.5,-1,-0.5,0,0.5")
    parser.add_argument("--eps2d", type=float, default=CPU_EPS2D, help="screen dilation, pixels^2 (default %(default)s)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if args.splats < 1 or args.eps2d < 0:
        parser.error(f"--splats must be >= 1 and --eps2d >= 0, got {args.splats} and {args.eps2d}")
    torch.set_num_threads(args.threads)
    offsets = [float(x) for x in args.offsets.split(",")]
    print(f"# {load()}; {args.splats} splats, eps2d {args.eps2d:g}; error = mean |render - true diffuse| away from edges")
    print(f"{'scene':22s} {'order':7s} " + " ".join(f"{k:+8.1f}" for k in offsets) + "   best offset (footprints)")
    figures = {}
    for name in args.scenes.split(","):
        result = errors(make_scene(name), args.splats, offsets, args.eps2d)
        figures[name] = {}
        for order, by_offset in result.items():
            best = min(by_offset, key=by_offset.get)
            print(f"{name:22s} {order:7s} " + " ".join(f"{by_offset[k]:8.5f}" for k in offsets) + f"   {best:+.1f}")
            figures[name][order] = {"errors": {str(k): round(v, 6) for k, v in by_offset.items()}, "best_offset": best}
    print(f"# {load()}")
    print(json.dumps({"bench": "composite_order", "splats": args.splats, "eps2d": args.eps2d, "scenes": figures}))


if __name__ == "__main__":
    main()
