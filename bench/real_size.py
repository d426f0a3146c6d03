"""Training at real capture sizes: memory per input pixel, step and Dense time, the whole run.

Scenes (generated once into ``--cache``, reused after): ``bumpy_mixed``, 36 views of 612x512
(NeISF's size; RMVP3D's training size), 61 views of 1224x1024 (RMVP3D's full size: 76 million
input pixels), the same 36 views at 128x128 and at 64x54 (the references), and 36 raw 2448x2048
IMX250MYR frames of glossy_plane_sphere on a speckled floor (``polargs generate --mosaic rgb
--floor-texture speckle``: bumpy_mixed's smooth surfaces give SfM too few corners; the generator's
cameras are kept aside in ``true_sparse/0`` and SfM builds its own). Figures, each
from ``polargs`` commands in child processes (their own peak memory and CPU time, from
``os.wait4``) or from one in-process measurement:

- ``bytes_per_pixel``: (peak RSS of ``polargs train`` on 36 x 612x512 - the same command's on
  36 x 64x54) / (the difference in input pixels), for Base and Full at the CPU preset (target:
  at most 40);
- ``step_ratio``: a Base step at 612x512 over the 128x128 step times the pixel ratio (19.1),
  both on the initial model of 36 views, taking turns in blocks (wall and CPU seconds);
- ``dense_seconds``: one Dense call at 612x512 (and at 128x128), after a warm-up call;
- ``maps_bytes_per_pixel``: the Full run's maps cache on disk over its input pixels;
- ``run_minutes``: the whole ``polargs train`` + ``mesh`` + ``eval`` of 36 x 612x512 at the CPU
  preset, Base and Full (targets on 2 cores: 30 and 40 minutes), with the CPU minutes beside;
- ``large_peak_gb``: ``polargs train`` of 61 x 1224x1024, Full, at ``--large-factor`` (default
  0.02: the CPU preset's 61 Dense calls within 600 iterations, so Dense visits the views as in a
  whole run) (target: at most 6 GB), and its bytes per input pixel against the same training of
  36 x 64x54;
- ``raw``: ``polargs train RAW --sfm --pattern auto --resolution 2`` on the raw frames (at
  ``--raw-iters`` iterations of the CPU preset, or ``--raw-factor``), then ``polargs mesh``: peak
  memory, SfM's time apart from the training's, the views SfM registered; then the mesh, brought
  into the generator's frame by the similarity that maps SfM's camera centres onto the true ones
  (``cameras.similarity_transform``), through ``polargs eval`` against the ground truth.

Before the sections that report peak memory (runs, large, raw), a Full training, mesh and
evaluation of the 64x54 scene at ``--factor 0.02`` fill numba's cache of compiled kernels (kept
beside the installed package): a process that compiles them peaks about 0.35 GB higher, and that
must not count as the training's memory.

The table gives each figure with its target; the last line is one JSON object. Runs take hours on
a shared 2-core machine: start it under ``nice`` and read the load beside the figures (printed
at the start and the end). ``--only`` picks sections (step, dense, runs, large, raw; the scenes they
read are generated first).

    .venv/bin/python bench/real_size.py --cache ~/.cache/polargs-bench          # everything
    .venv/bin/python bench/real_size.py --only step,dense                       # minutes
    .venv/bin/python bench/real_size.py --quick --cache out/rs-quick            # a check that it runs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

SECTIONS = ("step", "dense", "runs", "large", "raw")
SCENE = "bumpy_mixed"
RAW_SCENE = ("glossy_plane_sphere", "--floor-texture", "speckle")
TARGETS = {"bytes_per_pixel": 40.0, "base_minutes": 30.0, "full_minutes": 40.0, "large_peak_gb": 6.0}


@dataclass
class Sizes:
    """The scenes of one bench run: (views, width, height) each."""

    real: tuple[int, int, int] = (36, 612, 512)
    large: tuple[int, int, int] = (61, 1224, 1024)
    step_reference: tuple[int, int, int] = (36, 128, 128)
    base: tuple[int, int, int] = (36, 64, 54)
    raw: tuple[int, int, int] = (36, 2448, 2048)

    @classmethod
    def quick(cls) -> "Sizes":
        return cls(real=(6, 96, 80), large=(5, 128, 96), step_reference=(6, 32, 32), base=(6, 32, 28),
                   raw=(4, 192, 160))


@dataclass
class Child:
    """A finished child process: wall and CPU seconds, peak RSS in bytes, exit status."""

    wall: float
    cpu: float
    peak: int
    status: int
    output: str = ""

    def add(self, other: "Child") -> "Child":
        return Child(self.wall + other.wall, self.cpu + other.cpu, max(self.peak, other.peak),
                     self.status or other.status, self.output + other.output)


@dataclass
class Bench:
    """Where the bench works and what it found."""

    cache: Path
    sizes: Sizes
    threads: int
    env: dict[str, str] = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    rows: list = field(default_factory=list)


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def _wait(args: list[str], env: dict[str, str], out) -> tuple[int, float, int]:
    """Run ``args``: (exit status, CPU seconds, peak RSS bytes) of that child alone (os.wait4)."""
    process = subprocess.Popen(args, env=env, stdout=out, stderr=subprocess.STDOUT)
    _, status, usage = os.wait4(process.pid, 0)
    return os.waitstatus_to_exitcode(status), usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024


def run_child(args: list[str], env: dict[str, str], log: Path) -> Child:
    """Run ``args`` to the end: its wall and CPU time and peak RSS.

    Linux gives a child the peak RSS of the process it was started from (the copy exec replaces),
    so the command is started from a small launcher (this file with ``--launch``), not from the
    bench, whose own memory would otherwise be every child's peak."""
    start = time.perf_counter()
    report = log.with_suffix(".usage.json")
    with open(log, "w") as out:
        code, _, _ = _wait([sys.executable, __file__, "--launch", str(report), "--", *args], env, out)
    wall = time.perf_counter() - start
    output = log.read_text()
    usage = json.loads(report.read_text()) if report.is_file() else {"status": code}
    if usage["status"] != 0 or code != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({usage['status']}); see {log}:\n{output[-2000:]}")
    return Child(wall, usage["cpu"], usage["peak"], 0, output)


def launch(report: Path, args: list[str]) -> int:
    """``--launch REPORT -- COMMAND``: run COMMAND, write its status, CPU time and peak RSS to REPORT."""
    status, cpu, peak = _wait(args, dict(os.environ), sys.stdout)
    report.write_text(json.dumps({"status": status, "cpu": cpu, "peak": peak}))
    return status


def polargs(bench: Bench, *args: str, log: str) -> Child:
    return run_child([sys.executable, "-m", "polargs_plugin.cli", *args], bench.env, bench.cache / "logs" / log)


# ------------------------------------------------------------------------------------- scenes
def scene_folder(bench: Bench, size: tuple[int, int, int], mosaic: bool = False) -> Path:
    views, width, height = size
    name = f"{RAW_SCENE[0]}-speckle" if mosaic else SCENE
    return bench.cache / (f"{name}-{views}v-{width}x{height}" + ("-raw" if mosaic else ""))


def make_scenes(bench: Bench, sections: list[str]) -> None:
    """Generate the scenes the ``sections`` read (those missing from the cache)."""
    sizes = bench.sizes
    needed = {"step": [sizes.real, sizes.step_reference], "dense": [sizes.real, sizes.step_reference],
              "runs": [sizes.real, sizes.base], "large": [sizes.large, sizes.base], "raw": [sizes.base]}
    for size in dict.fromkeys(size for name in sections for size in needed.get(name, [])):
        folder = scene_folder(bench, size)
        if not folder.is_dir():
            polargs(bench, "generate", "--scene", SCENE, "--views", str(size[0]), "--size", f"{size[1]}x{size[2]}",
                    "--out", str(folder), log=f"generate-{folder.name}.log")
    raw = scene_folder(bench, sizes.raw, mosaic=True)
    if "raw" in sections and not raw.is_dir():
        polargs(bench, "generate", "--scene", *RAW_SCENE, "--views", str(sizes.raw[0]), "--size",
                f"{sizes.raw[1]}x{sizes.raw[2]}", "--mosaic", "rgb", "--bits", "16", "--out", str(raw),
                log=f"generate-{raw.name}.log")
        (raw / "sparse").rename(raw / "true_sparse")  # the truth, for the evaluation


def _pixels(size: tuple[int, int, int]) -> int:
    views, width, height = size
    return views * width * height


# --------------------------------------------------------------------------------- step, dense
def _trainers(bench: Bench, polar: bool):
    """Trainers on the real-size and the 128x128 scene, Base (or Full), initial model."""
    from polargs_plugin.service import build_trainer, load_dataset, polar_config, train_config

    made = []
    for size in (bench.sizes.real, bench.sizes.step_reference):
        config = polar_config("synthetic", 1 / 6) if polar else None
        if config is not None:
            config.cache_dir = str(bench.cache / "maps" / f"{size[1]}x{size[2]}")
        views = load_dataset(str(scene_folder(bench, size))).views
        made.append(build_trainer(views, train_config("cpu", progress=False), config))
    return made


def measure_steps(bench: Bench, block: int = 5, rounds: int = 4) -> None:
    """Base steps at the real size and at 128x128, taking turns in blocks (wall and CPU s)."""
    import torch

    torch.set_num_threads(bench.threads)
    real, small = _trainers(bench, polar=False)
    for trainer in (real, small):
        trainer.step()  # compiles and warms
    times = {"real": [0.0, 0.0], "small": [0.0, 0.0]}
    for _ in range(rounds):
        for name, trainer in (("real", real), ("small", small)):
            wall, cpu = time.perf_counter(), time.process_time()
            for _ in range(block):
                trainer.step()
            times[name][0] += time.perf_counter() - wall
            times[name][1] += time.process_time() - cpu
    count = block * rounds
    scale = (bench.sizes.real[1] * bench.sizes.real[2]) / (bench.sizes.step_reference[1] * bench.sizes.step_reference[2])
    real_wall, real_cpu = (t / count for t in times["real"])
    small_wall, small_cpu = (t / count for t in times["small"])
    bench.figures["step"] = {"real_seconds": real_wall, "real_cpu_seconds": real_cpu, "small_seconds": small_wall,
                             "small_cpu_seconds": small_cpu, "pixel_ratio": scale,
                             "step_ratio": real_wall / (small_wall * scale), "step_ratio_cpu": real_cpu / (small_cpu * scale)}


def measure_dense(bench: Bench) -> None:
    """One Dense call at the real size and at 128x128 on the initial model, after a warm-up call."""
    import torch

    torch.set_num_threads(bench.threads)
    result = {}
    for name, trainer in zip(("real", "small"), _trainers(bench, polar=True)):
        trainer._prepare()
        hooks, iteration = trainer.hooks, trainer.hooks.config.densify.start_iter
        walls, cpus = [], []
        for view in trainer.views[:3]:
            wall, cpu = time.perf_counter(), time.process_time()
            with torch.no_grad():
                hooks.densify(iteration, view, trainer.render, trainer.model.state())
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
        result[f"{name}_seconds"] = sum(walls[1:]) / len(walls[1:])
        result[f"{name}_cpu_seconds"] = sum(cpus[1:]) / len(cpus[1:])
    bench.figures["dense"] = result


# -------------------------------------------------------------------------------------- runs
def whole_run(bench: Bench, folder: Path, name: str, variant: str, extra: tuple[str, ...] = (),
              mesh: bool = True, evaluate: bool = True) -> dict:
    """``polargs train`` (+ ``mesh`` + ``eval``) of ``folder``: times, peak memory, the summary."""
    out = bench.cache / "runs" / name
    shutil.rmtree(out, ignore_errors=True)
    flags = ("--no-polar",) if variant == "base" else ()
    train = polargs(bench, "train", str(folder), "--out", str(out), "--quiet", *flags, *extra, log=f"{name}-train.log")
    summary = json.loads((out / "summary.json").read_text())
    steps = {"train": train}
    if mesh:
        steps["mesh"] = polargs(bench, "mesh", str(out), log=f"{name}-mesh.log")
    if evaluate:
        steps["eval"] = polargs(bench, "eval", str(out), "--gt", str(folder), log=f"{name}-eval.log")
    total = Child(0.0, 0.0, 0, 0)
    for child in steps.values():
        total = total.add(child)
    maps = out / "maps"
    maps_bytes = sum(p.stat().st_size for p in maps.glob("*.pt")) if maps.is_dir() else 0
    return {"wall_seconds": total.wall, "cpu_seconds": total.cpu, "train_peak_bytes": train.peak,
            "train_wall_seconds": train.wall, "train_cpu_seconds": train.cpu,
            "steps": {k: {"wall": v.wall, "cpu": v.cpu, "peak": v.peak} for k, v in steps.items()},
            "maps_bytes": maps_bytes, "psnr": summary.get("psnr"), "num_gaussians": summary.get("num_gaussians"),
            "estimate": summary.get("estimate"), "sfm_seconds": summary.get("sfm_seconds"),
            "metrics": _metrics(out) if evaluate else None}


def _metrics(run: Path) -> dict | None:
    path = run / "metrics.json"
    if not path.is_file():
        return None
    metrics = json.loads(path.read_text())
    return {k: metrics[k] for k in ("chamfer", "normal_mae_deg") if k in metrics}


def warm_kernel_cache(bench: Bench) -> None:
    """Train (Full, with Dense calls), mesh and evaluate the 64x54 scene once, untimed, so that no
    measured command compiles numba's kernels (their cache outlives the process)."""
    whole_run(bench, scene_folder(bench, bench.sizes.base), "warm-up", "full", ("--factor", "0.02"))


def measure_runs(bench: Bench, factor: str | None) -> None:
    extra = ("--factor", factor) if factor else ()
    for variant in ("base", "full"):
        real = whole_run(bench, scene_folder(bench, bench.sizes.real), f"real-{variant}", variant, extra)
        _add_bytes_per_pixel(bench, real, bench.sizes.real, f"small-{variant}", variant, extra)
        real["maps_bytes_per_pixel"] = real["maps_bytes"] / _pixels(bench.sizes.real)
        bench.figures[f"run_{variant}"] = real


def measure_large(bench: Bench, factor: str) -> None:
    """The 61 x 1224x1024 Full training, and its bytes per input pixel against the same training
    of the 64x54 reference."""
    large = whole_run(bench, scene_folder(bench, bench.sizes.large), "large-full", "full", ("--factor", factor),
                      evaluate=False)
    _add_bytes_per_pixel(bench, large, bench.sizes.large, "small-large-full", "full", ("--factor", factor))
    bench.figures["large"] = large


def _add_bytes_per_pixel(bench: Bench, figures: dict, size: tuple[int, int, int], name: str, variant: str,
                         extra: tuple[str, ...]) -> None:
    """Train the 64x54 reference as ``figures``' run was trained; add its peak (``base_peak_bytes``)
    and the run's peak beyond it over the difference in input pixels (``bytes_per_pixel``)."""
    small = whole_run(bench, scene_folder(bench, bench.sizes.base), name, variant, extra, mesh=False, evaluate=False)
    figures["base_peak_bytes"] = small["train_peak_bytes"]
    pixels = _pixels(size) - _pixels(bench.sizes.base)
    figures["bytes_per_pixel"] = (figures["train_peak_bytes"] - small["train_peak_bytes"]) / pixels


def measure_raw(bench: Bench, schedule: tuple[str, ...], sfm: bool) -> None:
    """The raw frames through ``polargs train --sfm --pattern auto --resolution 2`` and ``mesh``
    (``sfm`` False: with the generator's cameras, for a quick check), then the mesh evaluated in
    the generator's frame."""
    folder = scene_folder(bench, bench.sizes.raw, mosaic=True)
    shutil.rmtree(folder / "sparse", ignore_errors=True)
    if not sfm:
        shutil.copytree(folder / "true_sparse", folder / "sparse")
    flags = ("--sfm",) if sfm else ()
    figures = whole_run(bench, folder, "raw-full", "full", (*flags, "--pattern", "auto", "--resolution", "2", *schedule),
                        evaluate=False)
    figures.update(_evaluate_in_true_frame(bench, folder, bench.cache / "runs" / "raw-full"))
    bench.figures["raw"] = figures


def _evaluate_in_true_frame(bench: Bench, folder: Path, run: Path) -> dict:
    """The run's mesh mapped into the generator's frame by the similarity of SfM's camera centres
    to the true ones, evaluated there (``polargs eval`` with the true cameras in ``sparse/0``)."""
    import numpy as np
    import open3d as o3d

    from polargs_plugin.data.cameras import camera_centers, similarity_transform
    from polargs_plugin.data.colmap import read_colmap_model

    found = read_colmap_model(folder / "sparse" / "0")
    true = read_colmap_model(folder / "true_sparse" / "0")
    names = sorted(set(found) & set(true))
    centres = camera_centers(np.stack([found[n].world_to_camera for n in names]))
    true_centres = camera_centers(np.stack([true[n].world_to_camera for n in names]))
    scale, rotation, shift = similarity_transform(centres, true_centres)

    def to_true_frame(points: np.ndarray) -> np.ndarray:
        return scale * points @ rotation.T + shift

    residual = np.linalg.norm(to_true_frame(centres) - true_centres, axis=1)
    mesh = o3d.io.read_triangle_mesh(str(run / "tsdf_mesh.ply"))
    mesh.vertices = o3d.utility.Vector3dVector(to_true_frame(np.asarray(mesh.vertices)))
    aligned = run / "tsdf_mesh_true_frame.ply"
    o3d.io.write_triangle_mesh(str(aligned), mesh)
    shutil.rmtree(folder / "sparse")
    shutil.copytree(folder / "true_sparse", folder / "sparse")  # the evaluation's cameras: the true ones
    polargs(bench, "eval", str(aligned), "--gt", str(folder), "--views", str(folder), "--out",
            str(run / "metrics_true_frame.json"), log="raw-full-eval.log")
    metrics = json.loads((run / "metrics_true_frame.json").read_text())
    return {"registered": len(names), "views": len(true), "alignment_residual_max": float(residual.max()),
            "metrics": {k: metrics[k] for k in ("chamfer",) if k in metrics}}


# ------------------------------------------------------------------------------------- report
def _row(rows: list, figure: str, value: str, target: str = "") -> None:
    rows.append((figure, value, target))


def _label(size: tuple[int, int, int]) -> str:
    return f"{size[0]} x {size[1]}x{size[2]}"


def report(bench: Bench, load_start: str) -> None:
    f, rows, sizes = bench.figures, [], bench.sizes
    for variant in ("base", "full"):
        run = f.get(f"run_{variant}")
        if run:
            target = TARGETS[f"{variant}_minutes"]
            _row(rows, f"bytes per input pixel, {variant} ({_label(sizes.real)})", f"{run['bytes_per_pixel']:.1f}",
                 f"<= {TARGETS['bytes_per_pixel']:.0f}")
            _row(rows, f"train + mesh + eval, {variant}: wall (CPU) min", f"{run['wall_seconds'] / 60:.1f} "
                 f"({run['cpu_seconds'] / 60:.1f})", f"<= {target:.0f}")
            _row(rows, f"  peak RSS {variant}; {_label(sizes.base)} reference", f"{run['train_peak_bytes'] / 2**30:.2f} GB; "
                 f"{run['base_peak_bytes'] / 2**30:.2f} GB")
    if f.get("run_full"):
        _row(rows, "maps cache bytes per input pixel", f"{f['run_full']['maps_bytes_per_pixel']:.1f}")
    if f.get("step"):
        s = f["step"]
        _row(rows, "Base step real / (step 128 px x pixel ratio)", f"{s['step_ratio']:.3f} (CPU {s['step_ratio_cpu']:.3f})")
        _row(rows, "  Base step real; 128 px: s (CPU s)", f"{s['real_seconds']:.3f} ({s['real_cpu_seconds']:.3f}); "
             f"{s['small_seconds']:.4f} ({s['small_cpu_seconds']:.4f})")
    if f.get("dense"):
        d = f["dense"]
        _row(rows, "Dense call real; 128 px: s (CPU s)", f"{d['real_seconds']:.2f} ({d['real_cpu_seconds']:.2f}); "
             f"{d['small_seconds']:.2f} ({d['small_cpu_seconds']:.2f})")
    if f.get("large"):
        large = f["large"]
        _row(rows, f"{_label(sizes.large)} Full: peak RSS", f"{large['train_peak_bytes'] / 2**30:.2f} GB",
             f"<= {TARGETS['large_peak_gb']:.0f} GB")
        _row(rows, f"  its bytes per input pixel ({_label(sizes.base)} reference {large['base_peak_bytes'] / 2**30:.2f} GB)",
             f"{large['bytes_per_pixel']:.1f}", f"<= {TARGETS['bytes_per_pixel']:.0f}")
        _row(rows, "  its train wall (CPU) min", f"{large['train_wall_seconds'] / 60:.1f} ({large['train_cpu_seconds'] / 60:.1f})")
    if f.get("raw"):
        raw = f["raw"]
        _row(rows, f"raw {_label(sizes.raw)} -r 2: peak RSS", f"{raw['train_peak_bytes'] / 2**30:.2f} GB",
             f"<= {TARGETS['large_peak_gb']:.0f} GB")
        sfm = raw["sfm_seconds"] or 0.0
        _row(rows, "  SfM; train without SfM; mesh: min", f"{sfm / 60:.1f}; {(raw['train_wall_seconds'] - sfm) / 60:.1f}; "
             f"{raw['steps']['mesh']['wall'] / 60:.1f}")
        chamfer = (raw["metrics"] or {}).get("chamfer", {})
        _row(rows, "  views registered; camera centres after the similarity: max error",
             f"{raw['registered']} of {raw['views']}; {raw['alignment_residual_max']:.4f}")
        if chamfer:
            _row(rows, "  Chamfer in the true frame; median signed distance",
                 f"{chamfer['chamfer']:.4f}; {chamfer['signed_distance_median']:.4f}")
    width = max([len(r[0]) for r in rows] + [6])
    print(f"\nload average at the start {load_start}, at the end {_load()} ({os.cpu_count()} CPUs, {bench.threads} threads)")
    print(f"| {'figure':<{width}} | value | target |")
    print(f"|{'-' * (width + 2)}|---|---|")
    for figure, value, target in rows:
        print(f"| {figure:<{width}} | {value} | {target} |")
    print(json.dumps({"bench": "real_size", "sizes": vars(bench.sizes), "threads": bench.threads,
                      "load_start": load_start, "load_end": _load(), **f}))


def _raw_schedule(args: argparse.Namespace) -> tuple[str, ...]:
    if args.quick:
        return ("--factor", "0.002")
    return ("--factor", args.raw_factor) if args.raw_factor else ("--iters", args.raw_iters)


def main() -> None:
    if len(sys.argv) > 3 and sys.argv[1] == "--launch" and sys.argv[3] == "--":
        sys.exit(launch(Path(sys.argv[2]), sys.argv[4:]))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=Path("out/bench-real-size"), help="scenes, runs and logs")
    parser.add_argument("--only", default=",".join(SECTIONS), help=f"sections, comma-separated ({', '.join(SECTIONS)})")
    parser.add_argument("--threads", type=int, default=2, help="threads of every training (default 2)")
    parser.add_argument("--factor", default=None, help="--factor of the whole runs (default: the CPU preset)")
    parser.add_argument("--large-factor", default="0.02", help="--factor of the 61 x 1224x1024 run (default 0.02)")
    parser.add_argument("--raw-iters", default="800",
                        help="--iters of the raw-frame run at the CPU preset (default 800: seven Dense calls)")
    parser.add_argument("--raw-factor", default=None, help="--factor of the raw-frame run instead of --raw-iters")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and schedules: a check that it runs")
    args = parser.parse_args()
    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown sections {unknown} (known: {', '.join(SECTIONS)})")
    sizes = Sizes.quick() if args.quick else Sizes()
    factor = "0.002" if args.quick else args.factor
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads)}
    bench = Bench(args.cache, sizes, args.threads, env)
    (bench.cache / "logs").mkdir(parents=True, exist_ok=True)
    load_start = _load()
    make_scenes(bench, sections)
    if {"runs", "large", "raw"} & set(sections):
        warm_kernel_cache(bench)
    measures = {
        "step": lambda: measure_steps(bench),
        "dense": lambda: measure_dense(bench),
        "large": lambda: measure_large(bench, "0.002" if args.quick else args.large_factor),
        "raw": lambda: measure_raw(bench, _raw_schedule(args), sfm=not args.quick),
        "runs": lambda: measure_runs(bench, factor),
    }
    for name, measure in measures.items():  # the quick sections first, the whole runs last
        if name in sections:
            measure()
            # kept if a later section fails (named by the sections, so that two benches can share a cache)
            (bench.cache / f"figures-{'-'.join(sections)}.json").write_text(json.dumps(bench.figures, indent=1))
    report(bench, load_start)


if __name__ == "__main__":
    main()
