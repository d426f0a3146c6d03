"""Fused SSIM (``polargs_plugin.ssim.ssim_map``, Numba forward and hand-written backward) against
kornia's ``metrics.ssim`` (conv2d forward, autograd backward) on the CPU.

For each image size (3 x 128 x 128 and 3 x 256 x 256 by default) both are timed in the same
process, interleaved call by call (so load changes hit both alike), as the colour loss uses them:
``ssim(pred, target, 11).mean()`` forward, then backward to ``pred`` only. Printed: median
milliseconds per call of forward alone and forward + backward, the kornia / fused ratios, and
the largest differences of the map and of the gradient to kornia's; then, as the last line, one
JSON object with these figures (``speedup_<size>`` = fwd+bwd ratio).

The machine's load average is printed: timings on a shared machine are noisy, compare ratios.

Usage: python bench/ssim.py [--sizes 128 256] [--channels 3] [--threads 2] [--repeats 30]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import kornia
import torch

from polargs_plugin.ssim import ssim_map


def _kornia(pred, target):
    return kornia.metrics.ssim(pred[None], target[None], 11)[0]


def _fused(pred, target):
    return ssim_map(pred, target, 11)


def _once(fn, pred, target, backward: bool) -> float:
    start = time.perf_counter()
    if backward:
        pred.grad = None
        fn(pred, target).mean().backward()
    else:
        with torch.no_grad():
            fn(pred, target)
    return time.perf_counter() - start


def _measure(channels: int, size: int, repeats: int) -> dict[str, float]:
    gen = torch.Generator().manual_seed(size)
    pred = torch.rand(channels, size, size, generator=gen).requires_grad_()
    target = torch.rand(channels, size, size, generator=gen)
    # Agreement (and warm-up, compilation included).
    maps, grads = [], []
    for fn in (_kornia, _fused):
        pred.grad = None
        value = fn(pred, target)
        value.mean().backward()
        maps.append(value.detach())
        grads.append(pred.grad.clone())
    times: dict[str, list[float]] = {key: [] for key in ("kornia_fwd", "fused_fwd", "kornia_fb", "fused_fb")}
    for _ in range(3):
        for fn in (_kornia, _fused):
            _once(fn, pred, target, True)
    for _ in range(repeats):
        times["kornia_fwd"].append(_once(_kornia, pred, target, False))
        times["fused_fwd"].append(_once(_fused, pred, target, False))
        times["kornia_fb"].append(_once(_kornia, pred, target, True))
        times["fused_fb"].append(_once(_fused, pred, target, True))
    out = {key: 1e3 * statistics.median(values) for key, values in times.items()}
    out["max_abs_diff"] = float((maps[0] - maps[1]).abs().max())
    out["max_abs_grad_diff"] = float((grads[0] - grads[1]).abs().max())
    out["grad_scale"] = float(grads[0].abs().max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--channels", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()
    print(f"torch {torch.__version__}, kornia {kornia.__version__}, threads {torch.get_num_threads()}, "
          f"load average {' '.join(f'{x:.2f}' for x in load)} ({os.cpu_count()} CPUs)")
    header = (
        f"{'image':>14} | {'kornia fwd':>10} {'fused fwd':>10} {'ratio':>6} | {'kornia f+b':>10} {'fused f+b':>10}"
        f" {'ratio':>6} | {'max |map diff|':>14} {'max |grad diff|':>15}"
    )
    print(header)
    print("-" * len(header))
    summary: dict[str, float] = {"threads": args.threads}
    worst_map = worst_grad = 0.0
    for size in args.sizes:
        r = _measure(args.channels, size, args.repeats)
        fwd_ratio = r["kornia_fwd"] / r["fused_fwd"]
        fb_ratio = r["kornia_fb"] / r["fused_fb"]
        image = f"{args.channels}x{size}x{size}"
        print(f"{image:>14} | {r['kornia_fwd']:8.2f}ms {r['fused_fwd']:8.2f}ms {fwd_ratio:5.1f}x"
              f" | {r['kornia_fb']:8.2f}ms {r['fused_fb']:8.2f}ms {fb_ratio:5.1f}x"
              f" | {r['max_abs_diff']:14.2e} {r['max_abs_grad_diff']:15.2e}")
        summary[f"speedup_{size}"] = round(fb_ratio, 3)
        summary[f"speedup_fwd_{size}"] = round(fwd_ratio, 3)
        summary[f"kornia_fwd_bwd_ms_{size}"] = round(r["kornia_fb"], 4)
        summary[f"fused_fwd_bwd_ms_{size}"] = round(r["fused_fb"], 4)
        worst_map = max(worst_map, r["max_abs_diff"])
        worst_grad = max(worst_grad, r["max_abs_grad_diff"])
    summary["max_abs_diff"] = worst_map
    summary["max_abs_grad_diff"] = worst_grad
    summary["load_start"] = round(load[0], 2)
    summary["load_end"] = round(os.getloadavg()[0], 2)
    print("(medians over interleaved calls; map/grad diffs are fused vs kornia, gradient of the mean SSIM)")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
