"""CUDA / CPU time ratios of the reference rasterizer (forward + backward), PatchMatch and SSIM,
measured in one process on the same inputs; prints a table, then one JSON line (scripts/gpu_check.sh).

    python bench/gpu_ratios.py [--json FILE]

Needs a CUDA device; exits with status 2 and says so otherwise. No open3d needed: the scene is
a random cloud of Gaussians and random images.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Callable

import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.config import PatchMatchConfig
from polargs_plugin.densify.patchmatch import patchmatch
from polargs_plugin.ssim import ssim_map

SIZE, GAUSSIANS, REPEATS = 128, 20000, 5


def _timed(step: Callable[[], object], device: torch.device) -> float:
    """Median seconds of ``step`` over REPEATS runs after one warm-up."""
    step()
    times = []
    for _ in range(REPEATS):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def _camera(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    f = SIZE / (2 * math.tan(0.4))
    K = torch.tensor([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1.0]], device=device)
    return K, torch.eye(4, device=device)


def rasterizer_step(device: torch.device) -> Callable[[], object]:
    g = torch.Generator().manual_seed(0)
    means = (torch.randn(GAUSSIANS, 3, generator=g) * 0.5 + torch.tensor([0, 0, 3.0])).to(device).requires_grad_()
    quats = torch.nn.functional.normalize(torch.randn(GAUSSIANS, 4, generator=g)).to(device)
    scales = (torch.rand(GAUSSIANS, 3, generator=g) * 0.02 + 0.005).to(device)
    opac = torch.rand(GAUSSIANS, generator=g).to(device)
    colors = torch.rand(GAUSSIANS, 3, generator=g).to(device)
    K, w2c = _camera(device)

    def step() -> None:
        out = rasterize(means, quats, scales, opac, colors, K, w2c, SIZE, SIZE, backend="torch")
        out.color.sum().backward()

    return step


def patchmatch_step(device: torch.device) -> Callable[[], object]:
    g = torch.Generator().manual_seed(1)
    K, w2c = _camera(device)
    sources = 4
    src_w2c = w2c.expand(sources, 4, 4).clone()
    src_w2c[:, 0, 3] = torch.linspace(-0.3, 0.3, sources, device=device)
    image = torch.rand(3, SIZE, SIZE, generator=g).to(device)
    depth = torch.full((1, SIZE, SIZE), 3.0, device=device)
    normal = torch.zeros(3, SIZE, SIZE, device=device)
    normal[2] = -1

    def step() -> None:
        patchmatch(image, K, w2c, image.expand(sources, -1, -1, -1), K.expand(sources, 3, 3), src_w2c, depth, normal,
                   config=PatchMatchConfig(), generator=torch.Generator(device=device).manual_seed(0))

    return step


def ssim_step(device: torch.device) -> Callable[[], object]:
    g = torch.Generator().manual_seed(2)
    a = torch.rand(3, 4 * SIZE, 4 * SIZE, generator=g).to(device).requires_grad_()
    b = torch.rand(3, 4 * SIZE, 4 * SIZE, generator=g).to(device)
    return lambda: ssim_map(a, b).mean().backward()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", help="also write the JSON line to this file")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print("gpu_ratios: no CUDA device (torch.cuda.is_available() is False)", file=sys.stderr)
        return 2
    result = {"device": torch.cuda.get_device_name(0), "size": SIZE, "gaussians": GAUSSIANS}
    for name, make in (("rasterizer", rasterizer_step), ("patchmatch", patchmatch_step), ("ssim", ssim_step)):
        cpu = _timed(make(torch.device("cpu")), torch.device("cpu"))
        cuda = _timed(make(torch.device("cuda")), torch.device("cuda"))
        result[name] = {"cpu_s": round(cpu, 5), "cuda_s": round(cuda, 5), "speedup": round(cpu / cuda, 2)}
    print(f"{'step':<12}{'CPU s':>10}{'CUDA s':>10}{'CPU / CUDA':>12}")
    for name in ("rasterizer", "patchmatch", "ssim"):
        row = result[name]
        print(f"{name:<12}{row['cpu_s']:>10.4f}{row['cuda_s']:>10.4f}{row['speedup']:>12.2f}")
    line = json.dumps(result)
    print(line)
    if args.json:
        with open(args.json, "w") as handle:
            handle.write(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
