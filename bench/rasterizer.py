"""Speed and memory of the reference rasterizer against a naive dense torch renderer.

Scene: a seeded surface-like cloud, Gaussians lying flat on a sphere seen from 4 radii away,
screen-space sigma 0.5-2.5 px, opacity 0.5-1 (the setting of reference §2). One "iteration" is
rasterize + a loss on every output + backward. Each configuration runs in its own subprocess
so that its peak resident memory (``resource.getrusage(...).ru_maxrss``) is its own.

Configurations (``--configs``, ``N:WxH[:shD]``): 12k Gaussians at 256x256 with RGB colours, and
6000 Gaussians at 128x128 with SH degree 3 (the size of the CPU training preset). Backends:
``naive``; ``torch`` (torch projection and compositing); ``numba`` (compiled projection and
compositing, what ``backend="auto"`` runs on CPU); ``numba_tproj`` (numba compositing with the
torch projection and SH evaluation, ``projection="torch"``: the projection path before the
compiled one, kept for this comparison); with ``--ref-src DIR``, ``numba_ref``: ``backend="numba"``
of another copy of the package (``DIR`` is put first on its PYTHONPATH), e.g. the last commit's,
so that old and new are timed in the same run. The "proj" column is the projection + SH colour
forward+backward alone as a share of the whole forward+backward.

The naive baseline evaluates every pixel against every Gaussian (depth-sorted) with a full
cumulative product, masked to the same compositing rule, chunked over pixels with a
per-chunk backward so it fits in memory. It is also the exactness check: the table prints the
largest colour/depth difference of each path against it.

    .venv/bin/python bench/rasterizer.py                      # both configurations, 2 threads
    .venv/bin/python bench/rasterizer.py --configs 30000:400x300 --backends torch,numba
    .venv/bin/python bench/rasterizer.py --configs 40000:1024x1024 --backends numba --orders center:16,ray:4,ray:1
    mkdir -p out/ref && git archive HEAD src | tar -x -C out/ref && .venv/bin/python bench/rasterizer.py --ref-src out/ref/src

``--orders ORDER:TILE,...`` times every backend in each compositing order and tile size
(``rasterize(order=, tile_size=)``; default vanilla's center:16); the "x first" column is each
row's fwd+bwd time over its backend's first order, and the naive baseline stays in mean-depth
order (its differences to a ray-ordered row are the order's, not errors).

The last line printed is one JSON object with the figures of every configuration.
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
from polargs_plugin.backends.reference.rasterizer import parse_order_and_tile, rasterize
from polargs_plugin.geometry import eval_sh

BACKENDS = ("naive", "torch", "numba", "numba_tproj", "numba_ref")
DEFAULT_CONFIGS = "12000:256x256,6000:128x128:sh3"


def surface_scene(num: int, width: int, height: int, seed: int = 0, sh_degree: int = -1) -> dict[str, torch.Tensor]:
    """Flat Gaussians tangent to a unit sphere 4 units in front of an identity camera; RGB
    colours (``sh_degree`` -1) or SH coefficients of that degree (DC from the same colours)."""
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
        "colors": _colors(torch.rand(num, 3, generator=gen), sh_degree, gen),
        "K": K,
        "world_to_camera": torch.eye(4, dtype=torch.float64),
    }


def _colors(rgb: torch.Tensor, sh_degree: int, gen: torch.Generator) -> torch.Tensor:
    if sh_degree < 0:
        return rgb
    rest = 0.1 * torch.randn(rgb.shape[0], (sh_degree + 1) ** 2 - 1, 3, generator=gen)
    return torch.cat([((rgb - 0.5) / 0.28209479177387814)[:, None], rest], dim=1)


def _view_colors(scene: dict, colors: torch.Tensor) -> torch.Tensor:
    """Per-view RGB of ``colors`` (SH evaluated as the rasterizer does)."""
    if colors.dim() == 2:
        return colors
    w2c = scene["world_to_camera"].to(scene["means"])
    return eval_sh(colors, scene["means"] + w2c[:3, :3].T @ w2c[:3, 3])


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
    colors = _view_colors(scene, params["colors"])
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


def _loss(out, weights: torch.Tensor | None = None) -> torch.Tensor:
    shape = out.color.shape[-2:]
    w = (_loss_weights(shape[1], shape[0]) if weights is None else weights).reshape(9, *shape)
    # Same weights on the raw sums as the naive path (depth sum = depth * alpha).
    stacked = torch.cat([out.color, out.depth * out.alpha, out.normal, out.alpha, out.median_depth])
    return (stacked * w).sum()


def _projection_step(backend: str, scene: dict, params: tuple, width: int, height: int):
    """The projection + SH colour forward+backward alone, as ``rasterize`` runs it for ``backend``."""
    tensors = [scene[k] for k in params]
    if backend == "numba":
        from polargs_plugin.backends.reference.projection_numba import project_numba

        proj, colors = project_numba(*tensors, scene["K"], scene["world_to_camera"], width, height)
    else:
        means, quats, scales, opacities, colors = tensors
        proj = project_gaussians(means, quats, scales, opacities, scene["K"], scene["world_to_camera"], width, height)
        colors = _view_colors(scene, colors)
    outs = [x for x in (*proj[:7], colors)]
    return outs


def worker(
    backend: str, num: int, width: int, height: int, sh_degree: int, iters: int, threads: int, out_dir: str,
    order: str, tile_size: int,
) -> dict:
    """Time one configuration in this process; wall and CPU seconds, best of ``iters``."""
    torch.set_num_threads(threads)
    scene = surface_scene(num, width, height, sh_degree=sh_degree)
    params = ("means", "quats", "scales", "opacities", "colors")
    for k in params:
        scene[k].requires_grad_(True)
    import polargs_plugin

    result: dict = {
        "backend": backend,
        "order": f"{order}:{tile_size}",
        "package": os.path.dirname(polargs_plugin.__file__),
        "rss_before_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }

    def timed(fn):
        wall, cpu = time.perf_counter(), time.process_time()
        value = fn()
        return time.perf_counter() - wall, time.process_time() - cpu, value

    if backend == "naive":
        naive_render(scene, 16, 16)  # warm-up at a tiny size; the full run is too slow to repeat
        wall, cpu, out = timed(lambda: naive_render(scene, width, height))
        result.update(fwd_s=math.nan, fwd_bwd_s=wall, fwd_bwd_cpu_s=cpu, proj_s=math.nan)
        images = out
    else:
        raster_backend, projection = {"numba_tproj": ("numba", "torch"), "numba_ref": ("numba", None)}.get(
            backend, (backend, "auto")
        )
        weights = _loss_weights(width, height)
        kwargs = {"backend": raster_backend, "order": order, "tile_size": tile_size}
        kwargs |= {} if projection is None else {"projection": projection}

        def run(with_backward: bool):
            out = rasterize(*(scene[k] for k in params), scene["K"], scene["world_to_camera"], width, height, **kwargs)
            if with_backward:
                _loss(out, weights).backward()
            return out

        proj_path = "numba" if backend == "numba" else "torch"
        proj_grads = [torch.rand_like(x) for x in _projection_step(proj_path, scene, params, width, height)]

        def run_projection():
            outs = _projection_step(proj_path, scene, params, width, height)
            torch.autograd.backward(outs, proj_grads)

        run(True)  # warm-up: JIT compile or load the Numba cache, allocator
        run_projection()
        fwd, full, proj = [], [], []
        for _ in range(iters):
            with torch.no_grad():
                fwd.append(timed(lambda: run(False)))
            full.append(timed(lambda: run(True)))
            proj.append(timed(run_projection))
        best_fwd, best_full, best_proj = min(fwd), min(full), min(proj)
        result.update(fwd_s=best_fwd[0], fwd_bwd_s=best_full[0], fwd_bwd_cpu_s=best_full[1], proj_s=best_proj[0])
        images = {"color": best_full[2].color.detach(), "depth": best_full[2].depth.detach()}
    result["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    torch.save(images, os.path.join(out_dir, f"{backend}_{order}_{tile_size}.pt"))
    return result


def _parse_config(text: str) -> tuple[int, int, int, int]:
    """"N:WxH[:shD]" -> (N, W, H, SH degree or -1 for RGB)."""
    parts = text.split(":")
    width, height = (int(v) for v in parts[1].lower().split("x"))
    sh = int(parts[2].lower().removeprefix("sh")) if len(parts) > 2 else -1
    return int(parts[0]), width, height, sh


def _parse_orders(text: str) -> list[tuple[str, int]]:
    """"center:16,ray:1" -> [("center", 16), ("ray", 1)]; argparse error otherwise."""
    try:
        return [parse_order_and_tile(item, "--orders") for item in text.split(",")]
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _thread_env(threads: int) -> dict[str, str]:
    """The thread policy's environment for the workers (:class:`polargs_plugin.threads.ThreadPolicy`:
    passive OpenMP waiting, numba's workqueue layer), variables already set in the shell kept.
    Without it torch's and numba's OpenMP workers spin against each other on 2 cores: at 6000
    Gaussians / 128x128 a worker then took 0.136 s/iter instead of 0.021 s (tiny torch ops of
    8 ms each)."""
    try:
        from polargs_plugin.threads import ThreadPolicy
    except ImportError:  # a package without the policy
        return {}
    return {k: v for k, v in ThreadPolicy(threads=threads).environment().items() if k not in os.environ}


def run_config(num: int, width: int, height: int, sh: int, args) -> dict | None:
    """Run every backend of one configuration, print its table; returns its figures."""
    rows = []
    with tempfile.TemporaryDirectory() as out_dir:
        backends = args.backends.split(",")
        if args.ref_src and "numba_ref" not in backends:
            backends.append("numba_ref")
        runs = [(b, o) for b in backends for o in (args.orders[:1] if b == "naive" else args.orders)]
        for backend, (order, tile) in runs:
            if backend == "numba_ref" and not args.ref_src:
                continue
            cmd = [sys.executable, __file__, "--worker", backend, "--gaussians", str(num),
                   "--width", str(width), "--height", str(height), "--sh-degree", str(sh),
                   "--iters", str(args.iters), "--threads", str(args.threads), "--out-dir", out_dir,
                   "--order", order, "--tile-size", str(tile)]
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads)}
            env.update(_thread_env(args.threads))
            if backend == "numba_ref":
                env["PYTHONPATH"] = os.pathsep.join([os.path.abspath(args.ref_src), env.get("PYTHONPATH", "")])
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if proc.returncode != 0:
                print(proc.stderr, file=sys.stderr)
                return None
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["images"] = torch.load(os.path.join(out_dir, f"{backend}_{order}_{tile}.pt"))
            row["name"] = backend if len(args.orders) == 1 else f"{backend} {order}:{tile}"
            rows.append(row)

    naive = next((r for r in rows if r["backend"] == "naive"), None)
    colours = "RGB" if sh < 0 else f"SH degree {sh}"
    print(f"rasterizer bench: {num} Gaussians, {width}x{height}, {colours}, {args.threads} threads, "
          f"best of {args.iters} (naive: one run); cpu = process CPU seconds (less sensitive to other load); "
          f"proj = projection + SH fwd+bwd alone / fwd+bwd")
    print(f"{'backend':20s} {'fwd s/it':>9s} {'fwd+bwd s/it':>13s} {'cpu s/it':>9s} {'proj':>6s} {'x naive':>8s} "
          f"{'x first':>8s} {'peak RSS MiB':>13s} {'max|dcolor|':>12s} {'max|ddepth|':>12s}")
    first = {}
    for r in rows:
        first.setdefault(r["backend"], r)
    figures: dict = {"gaussians": num, "width": width, "height": height, "sh_degree": sh, "backends": {}}
    for r in rows:
        speedup = naive["fwd_bwd_s"] / r["fwd_bwd_s"] if naive else math.nan
        dc = dd = math.nan
        if naive:
            dc = (r["images"]["color"] - naive["images"]["color"]).abs().max().item()
            dd = (r["images"]["depth"] - naive["images"]["depth"]).abs().max().item()
        share = r["proj_s"] / r["fwd_bwd_s"]
        over_first = r["fwd_bwd_s"] / first[r["backend"]]["fwd_bwd_s"]
        print(f"{r['name']:20s} {r['fwd_s']:9.4f} {r['fwd_bwd_s']:13.4f} {r['fwd_bwd_cpu_s']:9.4f} {share:6.1%} "
              f"{speedup:8.1f} {over_first:8.2f} {r['peak_rss_mib']:13.0f} {dc:12.2e} {dd:12.2e}")
        figures["backends"][r["name"]] = {
            "order": r["order"], "x_first_order": _num(over_first),
            "fwd_s": _num(r["fwd_s"]), "fwd_bwd_s": _num(r["fwd_bwd_s"]), "fwd_bwd_cpu_s": _num(r["fwd_bwd_cpu_s"]),
            "proj_s": _num(r["proj_s"]), "proj_share": _num(share), "x_naive": _num(speedup),
            "peak_rss_mib": round(r["peak_rss_mib"], 1), "max_dcolor": _num(dc), "max_ddepth": _num(dd),
            "package": r["package"],
        }
    fast = [r for r in rows if r["backend"] != "naive"]
    by_name = first  # each backend's row in the first order
    for other in ("numba_tproj", "numba_ref"):
        if "numba" in by_name and other in by_name:
            figures[f"{other.removeprefix('numba_')}_over_numba"] = round(
                by_name[other]["fwd_bwd_s"] / by_name["numba"]["fwd_bwd_s"], 3
            )
    if fast:
        best = min(fast, key=lambda r: r["fwd_bwd_s"])
        figures["best"] = best["name"]
        ratio = f"{naive['fwd_bwd_s'] / best['fwd_bwd_s']:.1f}x naive" if naive else "naive not run"
        print(f"KEY: {num} Gaussians {width}x{height} {colours} {args.threads} threads: "
              f"best={best['name']} fwd+bwd={best['fwd_bwd_s']:.4f} s/iter ({ratio}), "
              f"peak RSS {best['peak_rss_mib']:.0f} MiB; "
              + ", ".join(f"{r['name']}={r['fwd_bwd_s']:.4f}" for r in rows))
    print()
    return figures


def _num(x: float) -> float | None:
    return None if x is None or math.isnan(x) else round(float(x), 6)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", default=DEFAULT_CONFIGS, help="comma-separated N:WxH[:shD]")
    parser.add_argument("--iters", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--backends", default=",".join(BACKENDS[:4]))
    parser.add_argument("--ref-src", help="another copy of the package's src/ to time as numba_ref")
    parser.add_argument("--orders", default="center:16", type=_parse_orders,
                        help="comma-separated ORDER:TILE compositing orders and tile sizes (default center:16)")
    parser.add_argument("--order", help=argparse.SUPPRESS)  # the worker's: main passes one of --orders
    parser.add_argument("--tile-size", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--worker", choices=BACKENDS, help=argparse.SUPPRESS)
    parser.add_argument("--gaussians", type=int, default=12000, help=argparse.SUPPRESS)
    parser.add_argument("--width", type=int, default=256, help=argparse.SUPPRESS)
    parser.add_argument("--height", type=int, default=256, help=argparse.SUPPRESS)
    parser.add_argument("--sh-degree", type=int, default=-1, help=argparse.SUPPRESS)
    parser.add_argument("--out-dir", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = worker(args.worker, args.gaussians, args.width, args.height, args.sh_degree, args.iters,
                        args.threads, args.out_dir, args.order, args.tile_size)
        print(json.dumps(result))
        return 0

    load_before = os.getloadavg()[0]
    configs = []
    for text in args.configs.split(","):
        figures = run_config(*_parse_config(text), args)
        if figures is None:
            return 1
        configs.append(figures)
    summary = {
        "bench": "rasterizer",
        "threads": args.threads,
        "iters": args.iters,
        "load_1min_before": round(load_before, 2),
        "load_1min_after": round(os.getloadavg()[0], 2),
        "worker_env": {"OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads)}
        | {k: os.environ[k] for k in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER") if k in os.environ}
        | _thread_env(args.threads),
        "configs": configs,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
