"""PatchMatch speed: cost evaluations per second, seconds per view, peak memory.

One *cost evaluation* = the bilateral NCC of one plane hypothesis at one pixel against one
source view (36 window samples with the default radius 5, step 2).

The measured run happens in a child process so that its peak resident memory (ru_maxrss) is
the PatchMatch's own. In the same run a naive reference -- a Python loop computing the same cost
one (pixel, hypothesis, source) at a time -- is timed on a small pixel subset and extrapolated
to the full evaluation count (stated as such in the output), and the torch reference backend is
timed on a crop. Wall and CPU seconds are both printed: on a machine shared with other processes
(load average above the thread count, flagged in the output) the wall time is inflated.

Usage: .venv/bin/python bench/patchmatch.py [--size 256] [--sources 4] [--threads 2] [--backend auto]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time


def _scene(size: int, num_sources: int):
    """A textured tilted plane seen by a reference and ``num_sources`` ring cameras (exact)."""
    import torch

    def look_at(eye):
        eye = torch.tensor(eye, dtype=torch.float64)
        fwd = torch.nn.functional.normalize(-eye, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 0, 1], dtype=torch.float64)), dim=0)
        R = torch.stack([right, torch.linalg.cross(fwd, right), fwd])
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        return w2c

    focal = 1.1 * size
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    waves = [(torch.nn.functional.normalize(torch.randn(2, generator=g, dtype=torch.float64), dim=0),
              (4 + 6 * torch.rand(1, generator=g).item()) * 4.0 / focal, torch.rand(1, generator=g).item() * 6.28)
             for _ in range(8)]  # wavelengths of 4-10 pixels at the reference distance
    out = []
    for k in range(num_sources + 1):
        a = 0.0 if k == 0 else 2 * math.pi * (k - 1) / num_sources
        b = 0.0 if k == 0 else math.radians(12)
        elev = math.radians(60) + b * math.sin(a)
        azim = math.radians(-90) + b * math.cos(a)
        eye = (4 * math.cos(elev) * math.cos(azim), 4 * math.cos(elev) * math.sin(azim), 4 * math.sin(elev))
        w2c = look_at(eye)
        R, t = w2c[:3, :3], w2c[:3, 3]
        v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64) + 0.5,
                              torch.arange(size, dtype=torch.float64) + 0.5, indexing="ij")
        rays = R.T @ (torch.linalg.inv(K) @ torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1))
        cam = -R.T @ t
        s = -cam[2] / rays[2]
        pts = cam[:, None] + s * rays
        tex = 0.5 + sum(0.06 * torch.sin((d[0] * pts[0] + d[1] * pts[1]) * 2 * math.pi / lam + ph)
                        for d, lam, ph in waves)
        img = tex.reshape(1, size, size).expand(3, -1, -1).float().contiguous()
        depth = s.reshape(1, size, size).float()
        normal = (R @ torch.tensor([0.0, 0, 1], dtype=torch.float64)).float()[:, None, None].expand(3, size, size)
        out.append((img, K, w2c, depth, normal.contiguous()))
    return out


def _naive_cost(gray_ref, sources, K_ref, Ks, Rs, ts, u, v, depth, normal, radius, step, sig_s, sig_c):
    """One pixel, one hypothesis, all sources: plain Python loops (the reference)."""
    import torch

    from polargs_plugin.densify.homography import plane_homography
    from polargs_plugin.geometry import ray_plane_distance

    ray = torch.linalg.inv(K_ref) @ torch.tensor([u + 0.5, v + 0.5, 1.0], dtype=torch.float64)
    n = normal.double()
    dpl = ray_plane_distance(torch.tensor(float(depth), dtype=torch.float64), n, ray)
    h, w = len(gray_ref), len(gray_ref[0])
    costs = []
    for s in range(len(sources)):
        H = plane_homography(K_ref, Ks[s], Rs[s], ts[s], n, dpl).tolist()
        src = sources[s]
        hs, ws = len(src), len(src[0])
        W = sr = sw = swr = sww = 0.0
        rr = 0.0
        centre = gray_ref[v][u]
        for oy in range(-radius, radius + 1, step):
            for ox in range(-radius, radius + 1, step):
                y, x = min(max(v + oy, 0), h - 1), min(max(u + ox, 0), w - 1)
                r = gray_ref[y][x]
                wgt = math.exp(-(ox * ox + oy * oy) / (2 * sig_s**2) - (r - centre) ** 2 / (2 * sig_c**2))
                qx, qy = u + ox + 0.5, v + oy + 0.5
                X = H[0][0] * qx + H[0][1] * qy + H[0][2]
                Y = H[1][0] * qx + H[1][1] * qy + H[1][2]
                Z = H[2][0] * qx + H[2][1] * qy + H[2][2]
                px, py = X / Z - 0.5, Y / Z - 0.5
                x0, y0 = math.floor(px), math.floor(py)
                fx, fy = px - x0, py - y0
                val = 0.0
                for dy, wy in ((0, 1 - fy), (1, fy)):
                    for dx, wx in ((0, 1 - fx), (1, fx)):
                        if 0 <= y0 + dy < hs and 0 <= x0 + dx < ws:
                            val += wy * wx * src[y0 + dy][x0 + dx]
                W += wgt
                sr += wgt * r
                rr += wgt * r * r
                sw += wgt * val
                sww += wgt * val * val
                swr += wgt * val * r
        mr, ms = sr / W, sw / W
        var_r, var_s = rr / W - mr * mr, sww / W - ms * ms
        cov = swr / W - mr * ms
        costs.append(2.0 if var_r < 1e-5 or var_s < 1e-5 else min(max(1 - cov / math.sqrt(var_r * var_s), 0), 2))
    return costs


def child(args) -> None:
    import torch

    torch.set_num_threads(args.threads)
    try:
        import numba

        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    except ImportError:
        pass
    from polargs_plugin.config import PatchMatchConfig
    from polargs_plugin.densify.homography import relative_pose
    from polargs_plugin.densify.patchmatch import patchmatch

    scene = _scene(args.size, args.sources)
    ref, srcs = scene[0], scene[1:]
    g = torch.Generator().manual_seed(1)
    d0 = ref[3] * (1 + 0.03 * torch.randn(ref[3].shape, generator=g))
    n0 = torch.nn.functional.normalize(ref[4] + 0.2 * torch.randn(ref[4].shape, generator=g), dim=0)
    n0 = torch.where(n0[2:] > 0, -n0, n0)
    cfg = PatchMatchConfig(ncc_backend=args.backend)
    call = lambda img, d, n, c: patchmatch(
        img, ref[1], ref[2], torch.stack([s[0][:, : img.shape[1], : img.shape[2]] for s in srcs]),
        torch.stack([s[1] for s in srcs]), torch.stack([s[2] for s in srcs]), d, n, config=c)
    # warm-up on a crop: compiles / loads the numba kernels (excluded from the timing)
    call(ref[0][:, :32, :32], d0[:, :32, :32], n0[:, :32, :32], PatchMatchConfig(iterations=1, ncc_backend=args.backend))
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    res = call(ref[0], d0, n0, cfg)
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    load_after = os.getloadavg()[0]
    rel = ((res.depth - ref[3]).abs() / ref[3])[0, 8:-8, 8:-8]

    # the torch reference backend on a crop, same config, same run
    c = args.torch_crop
    t2 = time.perf_counter()
    res_t = call(ref[0][:, :c, :c], d0[:, :c, :c], n0[:, :c, :c], PatchMatchConfig(ncc_backend="torch"))
    torch_rate = res_t.evaluations / (time.perf_counter() - t2)

    # naive reference on a pixel subset, extrapolated to the same number of evaluations
    R, t = relative_pose(ref[2], torch.stack([s[2] for s in srcs]))
    gray = ref[0].mean(0).tolist()
    sources = [s[0].mean(0).tolist() for s in srcs]
    n_pix = args.naive_pixels
    t1 = time.perf_counter()
    for k in range(n_pix):
        u, v = 20 + (k * 37) % (args.size - 40), 20 + (k * 53) % (args.size - 40)
        _naive_cost(gray, sources, ref[1], [s[1] for s in srcs], R, t, u, v, float(d0[0, v, u]),
                    n0[:, v, u], cfg.window_radius, cfg.window_step, cfg.window_radius, cfg.sigma_color)
    naive_per_eval = (time.perf_counter() - t1) / (n_pix * len(srcs))
    print(json.dumps({
        "seconds": seconds, "cpu_seconds": cpu_seconds, "evaluations": res.evaluations,
        "rate": res.evaluations / seconds, "load": [load_before, load_after],
        "iterations": cfg.iterations, "initial_hypotheses": 2,
        "candidates": 4 + 3, "sources": len(srcs), "top_k": cfg.top_k_sources,
        "samples": len(range(-cfg.window_radius, cfg.window_radius + 1, cfg.window_step)) ** 2,
        "torch_rate": torch_rate,
        "naive_seconds_per_eval": naive_per_eval, "naive_evals_timed": n_pix * len(srcs),
        "naive_extrapolated_seconds": naive_per_eval * res.evaluations,
        "frac_depth_within_1pct": float((rel < 0.01).float().mean()),
        "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--sources", type=int, default=4)
    p.add_argument("--threads", type=int, default=min(2, len(os.sched_getaffinity(0))))
    p.add_argument("--backend", default="auto", choices=["auto", "torch", "numba"])
    p.add_argument("--naive-pixels", type=int, default=40)
    p.add_argument("--torch-crop", type=int, default=64, help="crop size for timing the torch backend")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args)
        return 0
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), NUMBA_NUM_THREADS=str(args.threads),
               MKL_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, __file__, "--child"] + sys.argv[1:]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        sys.stderr.write(out.stderr)
        return out.returncode
    r = json.loads(out.stdout.strip().splitlines()[-1])
    load = max(r["load"])
    print(f"PatchMatch {args.size}x{args.size}, {r['sources']} source views (top {r['top_k']}), "
          f"{args.threads} threads of {os.cpu_count()} CPUs, backend={args.backend}")
    print(f"  work: {r['initial_hypotheses']} initial hypotheses (no AoLP), then {r['iterations']} iterations x 2 "
          f"checkerboard half-steps, each pixel scoring its current plane + {r['candidates']} candidates "
          f"(4 propagated, 3 refined); {r['samples']} window samples per evaluation")
    print(f"  time per view           {r['seconds']:.2f} s wall, {r['cpu_seconds']:.2f} s CPU   (target <= 3 s)")
    print(f"  cost evaluations        {r['evaluations'] / 1e6:.2f} M  ->  {r['rate'] / 1e6:.2f} M/s wall, "
          f"{r['evaluations'] / r['cpu_seconds'] / 1e6:.2f} M per CPU-second   (target >= 4 M/s)")
    print(f"  peak memory (maxrss)    {r['maxrss_mib']:.0f} MiB   (target <= 4096 MiB; whole child process)")
    print(f"  depth within 1 %        {100 * r['frac_depth_within_1pct']:.1f} % of interior pixels")
    print(f"  torch reference backend {r['torch_rate'] / 1e6:.2f} M/s wall on a {args.torch_crop}x{args.torch_crop} "
          f"crop  ->  this backend x{r['rate'] / r['torch_rate']:.1f}")
    print(f"  naive Python reference  {r['naive_seconds_per_eval'] * 1e3:.2f} ms/eval measured on "
          f"{r['naive_evals_timed']} evaluations, EXTRAPOLATED to {r['naive_extrapolated_seconds']:.0f} s "
          f"for this view  ->  speed-up x{r['naive_extrapolated_seconds'] / r['seconds']:.0f}")
    if load > args.threads:
        print(f"  NOTE: 1-min load average {load:.1f} > {args.threads} during the run: wall times are inflated by "
              f"other processes; CPU seconds / threads ({r['cpu_seconds'] / args.threads:.2f} s) bounds an "
              f"unloaded wall time from below")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
