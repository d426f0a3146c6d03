"""Speed and memory of the reference rasterizer against a naive dense torch renderer.

Scene: a seeded surface-like cloud, Gaussians lying flat on a sphere seen from 4 radii away,
screen-space sigma 0.5-2.5 px, opacity 0.5-1 (the setting of reference §2). One "iteration" is
rasterize + a loss on every output + backward. Each configuration runs in its own subprocess
so that its peak resident memory (``resource.getrusage(...).ru_maxrss``) is its own.

The naive baseline evaluates every pixel against every Gaussian (depth-sorted) with a full
cumulative product, masked to the same compositing rule, chunked over pixels with a
per-chunk backward so it fits in memory. It is also the exactness check: the table prints the
largest colour/depth difference of each path against it.

    .venv/bin/python bench/rasterizer.py                      # 12k Gaussians, 256x256, 2 threads
    .venv/bin/python bench/rasterizer.py --gaussians 30000 --width 400 --height 300
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from polargs_plugin.backends.reference.composite_torch import ALPHA_MAX, T_MIN
from polargs_plugin.backends.reference.projection import ALPHA_MIN, project_gaussians
from polargs_plugin.backends.reference.rasterizer import rasterize

BACKENDS = ("naive", "torch", "numba")


def surface_scene(num: int, width: int, height: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Flat Gaussians tangent to a unit sphere 4 units in front of an identity camera."""
    gen = torch.Generator().manual_seed(seed)
    focal = 0.6 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    center = torch.tensor([0.0, 0.0, 4.0])
    normal = torch.nn.functional.normalize(torch.randn(num, 3, generator=gen), dim=-1)
    means = center + normal
    # Tangent frame: random in-plane direction, then (tangent, bitangent, normal) as columns.
    helper = torch.nn.functional.normalize(torch.randn(num, 3, generator=gen), dim=-1)
    tangent = torch.nn.functional.normalize(torch.cross(normal, helper, dim=-1), dim=-1)
    rot = torch.stack([tangent, torch.cross(normal, tangent, dim=-1), normal], dim=-1)
    sigma_px = 0.5 + 2.0 * torch.rand(num, 2, generator=gen)
    tangent_scales = sigma_px * means[:, 2:3] / focal
    scales = torch.cat([tangent_scales, 0.1 * tangent_scales.min(dim=-1, keepdim=True).values], dim=-1)
    return {
        "means": means,
        "quats": torch.from_numpy(np.roll(Rotation.from_matrix(rot.double().numpy()).as_quat(), 1, axis=-1)).float(),
        "scales": scales,
        "opacities": 0.5 + 0.5 * torch.rand(num, generator=gen),
        "colors": torch.rand(num, 3, generator=gen),
        "K": K,
        "world_to_camera": torch.eye(4, dtype=torch.float64),
    }


def naive_render(scene: dict, width: int, height: int, pixel_chunk: int = 512) -> dict[str, torch.Tensor]:
    """Dense baseline: every pixel x every Gaussian, full cumprod, same rule; forward+backward.

    Runs the backward of the same loss as :func:`_loss` and returns the (detached) colour,
    depth and alpha.
    """
    params = {k: scene[k] for k in ("means", "quats", "scales", "opacities", "colors")}
    proj = project_gaussians(
        params["means"], params["quats"], params["scales"], params["opacities"],
        scene["K"], scene["world_to_camera"], width, height,
    )
    colors = params["colors"]
    keep = (proj.extents > 0).all(dim=-1)
    order = torch.argsort(proj.depths.detach())
    order = order[keep[order]]
    sources = {
        "m2": proj.means2d[order],
        "con": proj.conics[order],
        "op": params["opacities"][order],
        "feat": torch.cat([colors, proj.normals], -1)[order],
        "q": proj.ray_coeffs[order],
        "b": proj.ray_offsets[order],
        "bd": proj.depth_bounds[order],
    }
    # Each pixel chunk back-propagates into detached copies at once; the sums then go through
    # the projection in one final backward, so only one chunk's graph is alive at a time.
    leaves = {k: v.detach().requires_grad_() for k, v in sources.items()}
    weights = _loss_weights(width, height)
    outs = torch.zeros(9, height * width)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px_all, py_all = xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5
    for s in range(0, height * width, pixel_chunk):
        px, py = px_all[s : s + pixel_chunk, None], py_all[s : s + pixel_chunk, None]
        dx, dy = px - leaves["m2"][:, 0], py - leaves["m2"][:, 1]
        con = leaves["con"]
        sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
        alpha = torch.clamp(leaves["op"] * torch.exp(-sigma), max=ALPHA_MAX)
        alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
        t_incl = torch.cumprod(1 - alpha, dim=-1)
        t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=-1)
        contributes = (t_incl >= T_MIN) & (alpha > 0)
        w = torch.where(contributes, alpha * t_excl, torch.zeros_like(alpha))
        q = leaves["q"]
        a = q[:, :, 0] * px[..., None] + q[:, :, 1] * py[..., None] + q[:, :, 2]
        t = (a * leaves["b"]).sum(-1) / (a * a).sum(-1)
        z = torch.minimum(torch.maximum(t, leaves["bd"][:, 0]), leaves["bd"][:, 1])
        feat = w @ leaves["feat"]
        crossing = contributes & (t_excl >= 0.5) & (t_incl < 0.5)
        chunk_out = torch.cat(
            [feat[:, :3], (w * z).sum(-1, keepdim=True), feat[:, 3:], w.sum(-1, keepdim=True),
             (crossing * z).sum(-1, keepdim=True)], dim=-1,
        ).T
        (chunk_out * weights[:, s : s + pixel_chunk]).sum().backward()
        outs[:, s : s + pixel_chunk] = chunk_out.detach()
    torch.autograd.backward(list(sources.values()), [leaves[k].grad for k in sources])
    outs = outs.reshape(9, height, width)
    return {"color": outs[0:3], "depth": outs[3:4] / outs[7:8].clamp_min(1e-6), "alpha": outs[7:8]}


def _loss_weights(width: int, height: int) -> torch.Tensor:
    return torch.rand(9, height * width, generator=torch.Generator().manual_seed(1))


def _loss(out) -> torch.Tensor:
    w = _loss_weights(out.color.shape[-1], out.color.shape[-2]).reshape(9, *out.color.shape[-2:])
    # Same weights on the raw sums as the naive path (depth sum = depth * alpha).
    stacked = torch.cat([out.color, out.depth * out.alpha, out.normal, out.alpha, out.median_depth])
    return (stacked * w).sum()


def worker(backend: str, num: int, width: int, height: int, iters: int, threads: int, out_dir: str) -> dict:
    """Time one configuration in this process; wall and CPU seconds, best of ``iters``."""
    torch.set_num_threads(threads)
    scene = surface_scene(num, width, height)
    params = ("means", "quats", "scales", "opacities", "colors")
    for k in params:
        scene[k].requires_grad_(True)
    result: dict = {"backend": backend, "rss_before_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}

    def timed(fn):
        wall, cpu = time.perf_counter(), time.process_time()
        value = fn()
        return time.perf_counter() - wall, time.process_time() - cpu, value

    if backend == "naive":
        naive_render(scene, 16, 16)  # warm-up at a tiny size; the full run is too slow to repeat
        wall, cpu, out = timed(lambda: naive_render(scene, width, height))
        result.update(fwd_s=math.nan, fwd_bwd_s=wall, fwd_bwd_cpu_s=cpu, survivors_per_px=math.nan)
        images = out
    else:
        def run(with_backward: bool):
            out = rasterize(
                *(scene[k] for k in params), scene["K"], scene["world_to_camera"], width, height, backend=backend
            )
            if with_backward:
                _loss(out).backward()
            return out

        run(True)  # warm-up: JIT compile or load the Numba cache, allocator
        fwd, full = [], []
        for _ in range(iters):
            with torch.no_grad():
                fwd.append(timed(lambda: run(False)))
            full.append(timed(lambda: run(True)))
        best_fwd, best_full = min(fwd), min(full)
        result.update(fwd_s=best_fwd[0], fwd_bwd_s=best_full[0], fwd_bwd_cpu_s=best_full[1])
        images = {"color": best_full[2].color.detach(), "depth": best_full[2].depth.detach()}
    result["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    torch.save(images, os.path.join(out_dir, f"{backend}.pt"))
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=12000)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--iters", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--backends", default=",".join(BACKENDS))
    parser.add_argument("--worker", choices=BACKENDS, help=argparse.SUPPRESS)
    parser.add_argument("--out-dir", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = worker(args.worker, args.gaussians, args.width, args.height, args.iters, args.threads, args.out_dir)
        print(json.dumps(result))
        return 0

    rows = []
    with tempfile.TemporaryDirectory() as out_dir:
        for backend in args.backends.split(","):
            cmd = [sys.executable, __file__, "--worker", backend, "--gaussians", str(args.gaussians),
                   "--width", str(args.width), "--height", str(args.height), "--iters", str(args.iters),
                   "--threads", str(args.threads), "--out-dir", out_dir]
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads)}
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if proc.returncode != 0:
                print(proc.stderr, file=sys.stderr)
                return 1
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["images"] = torch.load(os.path.join(out_dir, f"{backend}.pt"))
            rows.append(row)

    naive = next((r for r in rows if r["backend"] == "naive"), None)
    print(f"rasterizer bench: {args.gaussians} Gaussians, {args.width}x{args.height}, {args.threads} threads, "
          f"best of {args.iters} (naive: one run); cpu = process CPU seconds (less sensitive to other load)")
    print(f"{'backend':8s} {'fwd s/it':>9s} {'fwd+bwd s/it':>13s} {'cpu s/it':>9s} {'x naive':>8s} "
          f"{'peak RSS MiB':>13s} {'max|dcolor|':>12s} {'max|ddepth|':>12s}")
    for r in rows:
        speedup = naive["fwd_bwd_s"] / r["fwd_bwd_s"] if naive else math.nan
        dc = dd = math.nan
        if naive:
            dc = (r["images"]["color"] - naive["images"]["color"]).abs().max().item()
            dd = (r["images"]["depth"] - naive["images"]["depth"]).abs().max().item()
        print(f"{r['backend']:8s} {r['fwd_s']:9.3f} {r['fwd_bwd_s']:13.3f} {r['fwd_bwd_cpu_s']:9.3f} {speedup:8.1f} "
              f"{r['peak_rss_mib']:13.0f} {dc:12.2e} {dd:12.2e}")
    fast = [r for r in rows if r["backend"] != "naive"]
    if fast:
        best = min(fast, key=lambda r: r["fwd_bwd_s"])
        ratio = f"{naive['fwd_bwd_s'] / best['fwd_bwd_s']:.1f}x naive" if naive else "naive not run"
        print(f"KEY: {args.gaussians} Gaussians {args.width}x{args.height} {args.threads} threads: "
              f"best={best['backend']} fwd+bwd={best['fwd_bwd_s']:.3f} s/iter ({ratio}), "
              f"peak RSS {best['peak_rss_mib']:.0f} MiB; "
              + ", ".join(f"{r['backend']}={r['fwd_bwd_s']:.3f}" for r in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
