"""The reference trainer (Base, plain 3DGS) against OpenSplat ``--cpu``, on the same scene.

OpenSplat (WebODM/OpenSplat) is the CPU 3DGS trainer people pick without a GPU: C++ on libtorch,
reading COLMAP folders. This bench trains one bundled scene with both, one after the other, with
the same views, resolution, iterations, SH degree and initial points, and the same number of
threads each; then reads OpenSplat's output PLY (:func:`polargs_plugin.kit.ply.read_gaussian_ply`),
renders both models with the reference rasterizer, fuses both with the same TSDF and evaluates
both meshes against the scene's ground truth.

What is matched: the scene (``polargs generate --export colmap``: OpenSplat reads the exported
8-bit images and sparse model; the reference trainer reads the scene folder, whose colour images
are the same s0 / 2 before quantisation), the initial points (the export's sparse points, for
both), image size (OpenSplat ``--num-downscales 0``: full resolution from the first step),
iterations, SH degree and its schedule (every ``iterations / 30`` steps, the reference trainer's
``TrainConfig.cpu`` with the factor ``iterations / 30000``), no opacity reset (the CPU preset has
none; OpenSplat ``--reset-alpha-every`` beyond the run),
threads (``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` for OpenSplat's libtorch, the thread policy for
the reference trainer), and the whole image as the colour target (``use_masks=False``). What is
not: the density control, each at its own defaults for the run's length: the reference
trainer's vanilla schedule shrunk by the CPU preset's rule (refinement every ``iterations / 300``
steps, at most 6000 Gaussians), OpenSplat's own (refinement every 100 steps from step 500, splits
until half the run, no cap, pruning below opacity 0.1). ``--opensplat-schedule shrunk`` gives
OpenSplat the shrunk schedule too; on glossy_plane_sphere at 1500 iterations that refines every 5
steps and grows the model past 200 000 Gaussians, which train badly: its own schedule is the
fair one. Nor OpenSplat's learnt background colour (the reference trainer's is black).

Figures:

- **s/it at matched Gaussian counts**: the iterations of each run are binned by their Gaussian
  count (OpenSplat's from its "new count" / "remaining" lines, timed by the arrival of its "Step"
  lines, every 10 iterations); for each count both runs went through, within +-10 %, the median
  seconds per iteration of each and their ratio (``opensplat_over_reference``);
- whole-run wall seconds (training only, the scene export and the evaluation not counted);
- PSNR of the training views, both models rendered by the reference rasterizer, each on its own
  trainer's background (OpenSplat's nerfstudio default, the reference trainer's black); inside the
  views' object masks too. The reference rasterizer's render of an OpenSplat PLY agrees with
  OpenSplat's own (``--val-render``) at about 31 dB PSNR: the two rasterizers differ in detail
  (cut-offs, tiles), not in the conventions of the parameters;
- Chamfer (capped) and the visible-surface Chamfer of each model's TSDF mesh
  (``service.mesh.fuse_model``, the synthetic preset; ``polargs eval``'s figures).

How to build OpenSplat on Debian 12 (CPU only), as this bench was run: ``apt-get install cmake
libopencv-dev nlohmann-json3-dev libnanoflann-dev libcxxopts-dev``; a CPU libtorch is the one of
the installed torch wheel (``python -c "import torch; print(torch.utils.cmake_prefix_path)"``).
OpenSplat fetches nlohmann_json, nanoflann and cxxopts at configure time; without network, point
each ``FETCHCONTENT_SOURCE_DIR_<NAME>`` at a folder whose CMakeLists.txt only declares the
INTERFACE target (``add_library(nlohmann_json INTERFACE)`` and its ``nlohmann_json::nlohmann_json``
alias; likewise ``cxxopts``, ``nanoflann``), the Debian headers serving the includes::

    cmake -DGPU_RUNTIME=CPU -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH=$TORCH_CMAKE \\
          -DFETCHCONTENT_FULLY_DISCONNECTED=ON -DFETCHCONTENT_SOURCE_DIR_NLOHMANN_JSON=$SHIMS/nlohmann_json \\
          -DFETCHCONTENT_SOURCE_DIR_CXXOPTS=$SHIMS/cxxopts -DFETCHCONTENT_SOURCE_DIR_NANOFLANN=$SHIMS/nanoflann ..
    make -j2 opensplat

(``-DGPU_RUNTIME=CPU``: where a CUDA compiler is installed, OpenSplat's default is CUDA.)

    .venv/bin/python bench/peers/opensplat.py --opensplat /path/to/OpenSplat/build/opensplat --iters 3000
    .venv/bin/python bench/peers/opensplat.py --opensplat ... --iters 300 --views 8 --size 64   # a quick check

The table's last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

STEP_LINE = re.compile(r"^Step (\d+): ([-+0-9.eE]+|nan)")
COUNT_LINE = re.compile(r"(?:new count|remaining) (\d+)")
MATCH_TOLERANCE = 0.10  # a count "matches" within +-10 %
#: OpenSplat's background colour (nerfstudio's default; its CPU path leaves it as it starts), which
#: its renders are composited on: its models are rendered on it here, the reference trainer's on black.
OPENSPLAT_BACKGROUND = (0.6130, 0.0101, 0.3984)


def _export_scene(args, folder: Path) -> Path:
    cmd = [sys.executable, "-m", "polargs_plugin.cli", "generate", "--scene", args.scene, "--out", str(folder),
           "--views", str(args.views), "--size", f"{args.size}x{args.size}", "--export", "colmap"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return folder


def _sparse_points(folder: Path):
    """The export's sparse points and colours (points3D.txt of the COLMAP model)."""
    import numpy as np

    rows = [line.split() for line in (folder / "colmap" / "sparse" / "0" / "points3D.txt").read_text().splitlines()
            if line and not line.startswith("#")]
    values = np.array([[float(v) for v in row[1:7]] for row in rows], dtype=np.float32)
    return values[:, :3], values[:, 3:6] / 255.0


def run_opensplat(args, folder: Path) -> dict:
    """Train with OpenSplat --cpu; per-iteration wall seconds (from the Step lines) and counts."""
    out = folder.parent / "opensplat"  # its own folder: OpenSplat writes a cameras.json beside its output
    out.mkdir(exist_ok=True)
    out_ply = out / "splat.ply"
    f = args.iters / 30_000  # the reference trainer's schedule factor
    cmd = [args.opensplat, str(folder / "colmap"), "--cpu", "-n", str(args.iters), "--num-downscales", "0",
           "--sh-degree", str(args.sh_degree), "--sh-degree-interval", str(max(1, round(1000 * f))),
           "--reset-alpha-every", str(10 * args.iters), "--keep-crs", "-o", str(out_ply)]
    if args.opensplat_schedule == "shrunk":
        cmd += ["--refine-every", str(max(1, round(100 * f))), "--warmup-length", str(round(500 * f)),
                "--stop-screen-size-at", str(round(4000 * f))]
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    start = time.perf_counter()
    stamps, counts, log = [], [], []  # (iteration, seconds since start), (iteration, count)
    last_step, count, reported, last_loss = 0, args.initial_count, 0, float("nan")
    # the log is written as it comes, so that a stopped run leaves what it did
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, bufsize=1) as proc, \
            open(out / "opensplat.log", "w") as log_file:
        for line in proc.stdout:
            now = time.perf_counter() - start
            log.append(line.rstrip())
            log_file.write(line)
            if (m := STEP_LINE.match(line)):
                last_step, last_loss = int(m.group(1)), float(m.group(2))
                stamps.append((last_step, now))
                counts.append((last_step, count))
                if last_step >= reported + args.iters // 10:
                    reported = last_step
                    left = now / last_step * (args.iters - last_step)
                    print(f"opensplat: iteration {last_step}/{args.iters}, {count} Gaussians, {now:.0f} s, "
                          f"~{left:.0f} s left at this pace", file=sys.stderr, flush=True)
            elif (m := COUNT_LINE.search(line)):
                count = int(m.group(1))
    wall = time.perf_counter() - start
    if proc.returncode != 0 or not out_ply.is_file():
        tail = "\n".join(log[-15:])
        raise SystemExit(f"opensplat failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")
    per_iteration = []  # (iteration, seconds per iteration over the last 10, count then)
    for (i0, t0), (i1, t1), (_, n) in zip(stamps, stamps[1:], counts[1:]):
        per_iteration.append((i1, (t1 - t0) / (i1 - i0), n))
    return {"wall": wall, "per_iteration": per_iteration, "ply": out_ply, "final_count": count, "final_loss": last_loss}


def run_reference(args, views, points, colors) -> dict:
    """Train Base with the reference trainer; per-iteration wall seconds and counts."""
    import torch

    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.threads import ThreadPolicy

    cfg = TrainConfig.cpu(factor=args.iters / 30_000, sh_degree=args.sh_degree, use_masks=False, progress=False,
                          threads=ThreadPolicy(threads=args.threads))
    cfg.density.max_gaussians = args.max_gaussians or None
    trainer = Trainer(views, cfg, init_points=(torch.from_numpy(points), torch.from_numpy(colors)))
    per_iteration = []
    start = time.perf_counter()
    for _ in range(args.iters):
        t0 = time.perf_counter()
        trainer.step()
        per_iteration.append((trainer.iteration, time.perf_counter() - t0, trainer.model.num))
        if trainer.iteration % max(1, args.iters // 10) == 0:
            print(f"reference: iteration {trainer.iteration}/{args.iters}, {trainer.model.num} Gaussians, "
                  f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    wall = time.perf_counter() - start
    return {"wall": wall, "per_iteration": per_iteration, "model": trainer.model, "final_count": trainer.model.num,
            "final_loss": float(trainer.last_logs["loss"])}


def matched_rates(ours: list, theirs: list, counts: list[int]) -> list[dict]:
    """Median s/it of each run over its iterations within +-10 % of each count both went through."""
    rows = []
    for c in counts:
        def near(rows_):
            return [dt for _, dt, n in rows_ if abs(n - c) <= MATCH_TOLERANCE * c]
        a, b = near(ours), near(theirs)
        if len(a) >= 10 and len(b) >= 2:
            rows.append({"gaussians": c, "reference_s_per_it": statistics.median(a),
                         "opensplat_s_per_it": statistics.median(b),
                         "opensplat_over_reference": statistics.median(b) / statistics.median(a),
                         "samples": [len(a), len(b)]})
    return rows


def _psnr(model, views, background) -> tuple[float, float]:
    """Mean PSNR over the views, whole image and inside the masks (rendered on ``background``)."""
    import math

    import torch

    whole, masked = [], []
    background = torch.tensor(background, dtype=torch.float32)
    with torch.no_grad():
        for view in views:
            color = model.render_output(view, background=background).color.clamp(0, 1)
            err = (color - view.image.clamp(0, 1)) ** 2
            whole.append(-10 * math.log10(float(err.mean()) + 1e-12))
            if view.mask is not None:
                m = view.mask.expand_as(err)
                masked.append(-10 * math.log10(float(err[m].mean()) + 1e-12))
    return statistics.fmean(whole), (statistics.fmean(masked) if masked else float("nan"))


def evaluate(model, views, folder: Path, name: str, background) -> dict:
    from polargs_plugin.mesh import write_mesh
    from polargs_plugin.service.evaluation import EvalSettings
    from polargs_plugin.service.evaluation import evaluate as evaluate_mesh
    from polargs_plugin.service.mesh import MeshSettings, fuse_model

    psnr, psnr_masked = _psnr(model, views, background)
    mesh = fuse_model(model, views, MeshSettings()).mesh
    path = write_mesh(folder / f"{name}_mesh.ply", mesh)
    metrics = evaluate_mesh(path, EvalSettings(gt=folder, views=str(folder)))["chamfer"]
    return {"psnr": psnr, "psnr_masks": psnr_masked, "chamfer": metrics["chamfer"],
            "chamfer_visible": metrics.get("chamfer_visible"), "gaussians": model.num}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--opensplat", required=True, help="the opensplat executable")
    parser.add_argument("--scene", default="glossy_plane_sphere")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--iters", type=int, default=2000)
    parser.add_argument("--sh-degree", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--opensplat-schedule", choices=("own", "shrunk"), default="own",
                        help="OpenSplat's refinement: its own defaults (refine every 100 from 500, split until half "
                             "the run; default) or vanilla's shrunk to the run as the reference trainer's")
    parser.add_argument("--max-gaussians", type=int, default=6000,
                        help="the reference trainer's cap (default 6000, the CPU preset's; 0: none, as OpenSplat)")
    parser.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (scene, PLY, meshes, OpenSplat's log)")
    args = parser.parse_args()
    if not Path(args.opensplat).is_file() or not os.access(args.opensplat, os.X_OK):
        parser.error(f"--opensplat: {args.opensplat} is not an executable file")
    load = os.getloadavg()

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        scene = _export_scene(args, folder / "scene")
        points, colors = _sparse_points(scene)
        args.initial_count = len(points)

        from polargs_plugin.backends.reference.model import GaussianModel
        from polargs_plugin.kit.ply import read_gaussian_ply
        from polargs_plugin.service.data import load_dataset

        views = load_dataset(str(scene)).views
        theirs = run_opensplat(args, scene)
        ours = run_reference(args, views, points, colors)
        raw = read_gaussian_ply(theirs["ply"])
        their_model = GaussianModel(dict(raw), sh_degree=raw.sh_degree, eps2d=0.3)  # OpenSplat's dilation
        their_model.active_sh_degree = raw.sh_degree
        our_model = ours["model"]
        figures = {"opensplat": evaluate(their_model, views, scene, "opensplat", OPENSPLAT_BACKGROUND),
                   "reference": evaluate(our_model, views, scene, "reference", (0.0, 0.0, 0.0))}

    lo = min(r[2] for r in ours["per_iteration"])
    hi = min(ours["final_count"], max(r[2] for r in theirs["per_iteration"]))
    counts = sorted({round(lo + (hi - lo) * k / 4, -2) for k in range(5)})
    matched = matched_rates(ours["per_iteration"], theirs["per_iteration"], [int(c) for c in counts])
    print(f"scene {args.scene}, {args.views} views {args.size}x{args.size}, {args.iters} iterations, SH {args.sh_degree}, "
          f"{args.threads} threads each, load before {load[0]:.2f}")
    print(f"{'Gaussians':>10} {'reference s/it':>15} {'OpenSplat s/it':>15} {'OpenSplat / ref':>16}")
    for r in matched:
        print(f"{r['gaussians']:>10} {r['reference_s_per_it']:>15.4f} {r['opensplat_s_per_it']:>15.4f} "
              f"{r['opensplat_over_reference']:>16.2f}")
    print(f"{'':>10} {'reference':>15} {'OpenSplat':>15}")
    rows = [("whole run (s)", ours["wall"], theirs["wall"]), ("final Gaussians", ours["final_count"], theirs["final_count"]),
            ("last step's loss", ours["final_loss"], theirs["final_loss"])]
    rows += [(label, figures["reference"][key], figures["opensplat"][key]) for label, key in (
        ("PSNR (dB)", "psnr"), ("PSNR in masks (dB)", "psnr_masks"), ("Chamfer", "chamfer"),
        ("visible Chamfer", "chamfer_visible"))]
    for label, a, b in rows:
        print(f"{label:>20} {a:>10.4g} {b:>15.4g}")
    print(json.dumps({"scene": args.scene, "views": args.views, "size": args.size, "iterations": args.iters,
                      "sh_degree": args.sh_degree, "threads": args.threads, "load_before": round(load[0], 2),
                      "matched": matched, "wall": {"reference": ours["wall"], "opensplat": theirs["wall"]},
                      "final_loss": {"reference": ours["final_loss"], "opensplat": theirs["final_loss"]},
                      "opensplat_schedule": args.opensplat_schedule,
                      "figures": figures,
                      # the least favourable matched count for the reference trainer
                      "opensplat_over_reference": min((r["opensplat_over_reference"] for r in matched), default=None)}))


if __name__ == "__main__":
    main()
