"""Preprocessing speed on a full 2448x2048 colour-polarization raw frame.

Times, in one run and on the same synthetic mosaic:

- reference: polanalyser.demosaicing(COLOR_PolarRGB) + polanalyser.calcLinearStokes;
- ours: optics.demosaic_polar + optics.stokes_from_intensities (target: >= 2x the reference);
- the whole PC pipeline: demosaic, Stokes, AoLP/DoLP, masks, PRI, CRMs (target: <= 1.5 s on 2 cores).

The frame is a smooth colour field with polarized white highlights and clipped blobs, so that the
masks and the I_chro propagation see realistic workloads (a few percent reflective pixels).

Usage: python bench/preprocess.py [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.optics.mosaic import demosaic_polar, mosaic_from_intensities
from polargs_plugin.optics.stokes import stokes_from_intensities

HEIGHT, WIDTH = 2048, 2448


def synthetic_raw(seed: int = 0) -> np.ndarray:
    """(2048, 2448) uint8 IMX250MYR-style raw frame of a highlight-rich scene."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    diffuse = np.stack(
        [0.35 + 0.15 * np.sin(x / 300 + c) * np.cos(y / 250 - c) for c in (0.0, 1.3, 2.6)]
    )  # (3, H, W)
    specular = np.zeros((HEIGHT, WIDTH), np.float32)
    aolp = np.zeros((HEIGHT, WIDTH), np.float32)
    for _ in range(40):
        cy, cx, r = rng.uniform(0, HEIGHT), rng.uniform(0, WIDTH), rng.uniform(15, 60)
        blob = np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / (2 * r * r))
        specular += rng.uniform(0.5, 2.0) * blob
        aolp = np.where(blob > 0.1, rng.uniform(0, math.pi), aolp)
    dolp_s = np.clip(0.3 + 0.5 * specular / (1 + specular), 0, 0.9)
    beta = np.deg2rad([0, 45, 90, 135]).astype(np.float32)[:, None, None, None]
    modulation = 1 - dolp_s[None, None] * np.cos(2 * beta - 2 * aolp[None, None])  # specular part
    angles = diffuse[None] * 0.5 + 0.5 * specular[None, None] * modulation
    for _ in range(12):  # strong unpolarized light: every angle clips (overexposed)
        cy, cx, r = rng.uniform(0, HEIGHT), rng.uniform(0, WIDTH), rng.uniform(20, 50)
        angles += 1.5 * np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / (2 * r * r))[None, None]
    angles = np.clip(angles + rng.normal(0, 0.003, angles.shape).astype(np.float32), 0, 1)
    raw = mosaic_from_intensities(torch.from_numpy(angles), "rgb").numpy()
    return np.round(raw * 255).astype(np.uint8)


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import cv2
    import polanalyser as pa

    cv2.setNumThreads(args.threads)
    raw = synthetic_raw()
    angles_rad = np.deg2rad([0, 45, 90, 135])

    def reference():
        images = pa.demosaicing(raw, pa.COLOR_PolarRGB)
        return pa.calcLinearStokes([image.astype(np.float32) / 255 for image in images], angles_rad)

    def ours():
        return stokes_from_intensities(demosaic_polar(raw, "rgb"))

    config = CorrectionConfig()

    def pipeline():
        intensities = demosaic_polar(raw, "rgb")
        return compute_polar_maps(stokes_from_intensities(intensities), None, config, intensities)

    maps = pipeline()
    t_ref = best_time(reference, args.repeats)
    t_ours = best_time(ours, args.repeats)
    t_pipe = best_time(pipeline, args.repeats)
    pixels = HEIGHT * WIDTH
    print(f"frame {WIDTH}x{HEIGHT} rgb, torch threads {torch.get_num_threads()}, best of {args.repeats}")
    print(f"specular {int(maps.specular_mask.sum()) / pixels:.2%}, overexposed {int(maps.overexposed_mask.sum())} px, "
          f"I_chro found for {int(maps.extras['i_chro_valid'].sum())} px")
    print(f"polanalyser demosaic + Stokes      {t_ref:7.3f} s")
    print(f"ours demosaic + Stokes             {t_ours:7.3f} s   speed-up x{t_ref / t_ours:.2f}  (target >= 2)")
    print(f"ours full PC preprocessing         {t_pipe:7.3f} s   (target <= 1.5 s; "
          f"{t_pipe / t_ref:.2f}x polanalyser demosaic + Stokes)")


if __name__ == "__main__":
    main()
