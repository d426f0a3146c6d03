"""Preprocessing speed on a full 2448x2048 colour-polarization raw frame.

Times, in one run, on the same synthetic uint8 mosaic, best of N consecutive calls of each:

- reference: polanalyser.demosaicing(raw, COLOR_PolarRGB) + polanalyser.calcLinearStokes, the
  faster of its two natural uses (on the uint8 images, or on float32 images / 255);
- ours: optics.mosaic.stokes_from_raw, the fused demosaic + Stokes (target: >= 2x the reference);
  the unfused optics.demosaic_polar + optics.stokes_from_intensities is printed for comparison;
- the whole PC pipeline: demosaic, Stokes, AoLP/DoLP, masks, PRI, CRMs (target: <= 1.5 s on 2 cores).
  It demosaics to the four angle images (PRI and the clipping test need the measured angles,
  which Stokes alone cannot give back) and takes Stokes from stokes_from_raw.

OpenCV, numba and torch are all limited to ``--threads``.

The frame is a smooth colour field with polarized white highlights and clipped blobs, so that the
masks and the I_chro propagation see realistic workloads (a few percent reflective pixels).

Usage: python bench/preprocess.py [--threads 2] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import torch

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.optics.mosaic import demosaic_polar, mosaic_from_intensities, stokes_from_raw
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


def load_average() -> str:
    """System load (as `uptime` prints it): timings on a shared machine are only comparable in one run."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def best_times(functions: dict, repeats: int) -> dict:
    """Best wall time of each function over ``repeats`` consecutive calls, after one untimed call.

    One function at a time: the thread pools of OpenCV, OpenBLAS, torch and numba spin for a
    while after their parallel regions, so interleaving the contenders would bill one's idle
    spinning to the next (seen here: polanalyser's calcLinearStokes up to 10x slower right after
    a torch or numba call). The untimed call absorbs the hand-over.
    """
    best = {}
    for name, fn in functions.items():
        fn()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        best[name] = min(times)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    import cv2
    import numba
    import polanalyser as pa

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    raw = synthetic_raw()
    angles_rad = np.deg2rad([0, 45, 90, 135])
    config = CorrectionConfig()

    def pipeline():
        # The fused Stokes (equal to 1e-6, tests/test_optics_fused.py) beat the einsum over the
        # angle images, which are still needed for the PRI and the clipping test.
        intensities = demosaic_polar(raw, "rgb")
        return compute_polar_maps(stokes_from_raw(raw, "rgb"), None, config, intensities)

    contenders = {
        "polanalyser, float32 / 255": lambda: pa.calcLinearStokes(
            [image.astype(np.float32) / 255 for image in pa.demosaicing(raw, pa.COLOR_PolarRGB)], angles_rad
        ),
        "polanalyser, uint8": lambda: pa.calcLinearStokes(pa.demosaicing(raw, pa.COLOR_PolarRGB), angles_rad),
        "fused": lambda: stokes_from_raw(raw, "rgb"),
        "unfused": lambda: stokes_from_intensities(demosaic_polar(raw, "rgb")),
        "pipeline": pipeline,
    }
    # Also the first calls: numba compilation (or cache load), OpenCV.
    reference_stokes = np.moveaxis(contenders["polanalyser, float32 / 255"](), -1, 0)[:, :, :, ::-1]  # (3, H, W, RGB)
    ours = stokes_from_raw(raw, "rgb").numpy()
    error = float(np.abs(ours - reference_stokes.transpose(0, 3, 1, 2)).max())
    maps = pipeline()
    load_before = load_average()
    best = best_times(contenders, args.repeats)

    t_ref_name = min(("polanalyser, float32 / 255", "polanalyser, uint8"), key=best.get)
    t_ref, t_ours, t_pipe = best[t_ref_name], best["fused"], best["pipeline"]
    pixels = HEIGHT * WIDTH
    print(f"frame {WIDTH}x{HEIGHT} rgb uint8, threads {args.threads} (torch {torch.get_num_threads()}, "
          f"numba {numba.get_num_threads()}, cv2 {cv2.getNumThreads()}), best of {args.repeats}, "
          f"{os.cpu_count()} CPUs, load average (1/5/15 min) before {load_before}, after {load_average()}")
    print(f"specular {int(maps.specular_mask.sum()) / pixels:.2%}, overexposed {int(maps.overexposed_mask.sum())} px, "
          f"I_chro found for {int(maps.extras['i_chro_valid'].sum())} px; "
          f"fused Stokes vs polanalyser max |diff| {error:.1e}")
    for name in ("polanalyser, float32 / 255", "polanalyser, uint8"):
        mark = "   <- reference (the faster)" if name == t_ref_name else ""
        print(f"{name + ' demosaic + Stokes':<45}{best[name]:7.3f} s{mark}")
    print(f"{'ours unfused demosaic_polar + Stokes':<45}{best['unfused']:7.3f} s   x{t_ref / best['unfused']:.2f}")
    print(f"{'ours fused stokes_from_raw':<45}{t_ours:7.3f} s   speed-up x{t_ref / t_ours:.2f}  (target >= 2)")
    print(f"{'ours full PC preprocessing':<45}{t_pipe:7.3f} s   (target <= 1.5 s; "
          f"{t_pipe / t_ref:.2f}x polanalyser demosaic + Stokes)")
    print(json.dumps({"bench": "preprocess", "frame": [WIDTH, HEIGHT], "threads": args.threads,
                      "repeats": args.repeats, "seconds": best, "reference": t_ref_name,
                      "fused_speedup": t_ref / t_ours, "pipeline_seconds": t_pipe,
                      "pipeline_vs_reference": t_pipe / t_ref, "stokes_max_abs_diff": error}))


if __name__ == "__main__":
    main()
