"""``polargs ablate``: the PolarGS ablation grid (scenes x variants x seeds), gathered into a table
and a report with pictures. The machinery lives in :mod:`polargs_plugin.ablation`."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from polargs_plugin.ablation.variants import DESCRIPTIONS, PRESETS, VARIANTS

_INITS = ("hull", "sfm", "random")

_DESCRIPTION = """\
Run the PolarGS ablation: every scene x variant x seed is one training of the reference backend,
meshed (TSDF) and evaluated against the scene's ground-truth mesh. Results are gathered into
OUT/results.csv, OUT/results.json and OUT/results.md (mean and spread over seeds) and a report
OUT/report.md with pictures. See docs/ablation.md.

Variants:
""" + "\n".join(f"  {name:9s} {text}" for name, text in DESCRIPTIONS.items()) + """

Scenes (comma-separated): a bundled name (glossy_plane_sphere, shiny_torus, bumpy_mixed,
torus_knot; generated once into --scene-cache with --views/--size), or a dataset folder in any
supported format as NAME=PATH:GT_MESH, NAME=PATH or PATH (GT mesh: gt_mesh.ply or mesh.ply in
the folder).

Resumable: run folders are complete or absent; finished runs are skipped when the command runs
again. A failed run leaves OUT/logs/NAME.log, the others go on; the exit status is 1 if any failed.

Examples:
  polargs ablate --scenes glossy_plane_sphere,shiny_torus --variants all --seeds 0,1 --out runs/ablation
  polargs ablate --scenes gps=data/gps:data/gps/gt.ply --variants base,reg,full --out runs/gps --jobs 2
  polargs ablate --out runs/ablation --gather-only          # table + report from the run folders
"""


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like WIDTHxHEIGHT (e.g. 128x128), got {text!r}") from None
    if width < 8 or height < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return width, height


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def add_run_options(p: argparse.ArgumentParser, default_factor_help: str = "0.02: 600 iterations") -> None:
    """Options shared by ``polargs ablate`` and ``polargs demo``."""
    p.add_argument("--jobs", type=_positive, default=None, metavar="N",
                   help="runs in parallel (default: cores // --threads-per-run); 1 runs in this process")
    p.add_argument("--threads-per-run", type=_positive, default=1, metavar="T", help="torch threads of each run (default 1)")
    p.add_argument("--preset", choices=PRESETS, default="cpu",
                   help="cpu: every schedule x --factor (TrainConfig.cpu, PolarConfig.cpu_demo); paper: vanilla 3DGS "
                   "schedule with the paper's synthetic settings, for a GPU (default cpu)")
    p.add_argument("--factor", type=_positive_float, default=None, metavar="F", help=f"schedule factor of the cpu preset (default {default_factor_help})")
    p.add_argument("--iters", type=_positive, default=None, metavar="N", help="training iterations (default: the preset's)")
    p.add_argument("--init", default="hull", metavar="INIT",
                   help="initial points: hull (visual hull of the masks), sfm (triangulated SIFT matches with the known poses; "
                   "falls back to hull when too few, recorded), random (uniform in the look-at cube); comma-separated to run several (default hull)")
    p.add_argument("--views", type=_positive, default=24, metavar="N", help="views of a generated bundled scene (default 24)")
    p.add_argument("--size", type=_size, default=(128, 128), metavar="WxH", help="image size of a generated bundled scene (default 128x128)")
    p.add_argument("--scene-cache", type=Path, default=None, metavar="DIR", help="where bundled scenes are generated and reused (default OUT/scenes)")
    p.add_argument("--train-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a TrainConfig field, dotted for nested ones (e.g. density.max_gaussians=3000); repeatable")
    p.add_argument("--polar-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PolarConfig field of the variants with hooks (e.g. losses.alpha_normal=0.1); repeatable")
    p.add_argument("--mesh-preset", choices=("synthetic", "paper"), default="synthetic", help="TSDF settings (polargs mesh --preset; default synthetic)")
    p.add_argument("--voxel", type=_positive_float, default=None,
                   help="TSDF voxel (default: the preset's; for bundled scenes scaled to the image size, 1 / min(W, H))")
    p.add_argument("--eval-samples", type=_positive, default=1_000_000, metavar="N", help="points sampled per mesh for Chamfer (default 1e6)")
    p.add_argument("--no-cull", action="store_true", help="do not cull predicted points to the view masks before Chamfer")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (one line per finished run is still printed)")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ablate",
        help="run the ablation grid (scenes x variants x seeds) and write a report",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenes", default=None, metavar="A,B,...", help="comma-separated scenes (see above)")
    p.add_argument("--variants", default="all", metavar="V,...", help=f"comma-separated subset of {','.join(VARIANTS)}, or all (default)")
    p.add_argument("--seeds", default="0", metavar="S,...", help="comma-separated training seeds (default 0)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="the ablation folder (run folders, logs, results, report)")
    p.add_argument("--gather-only", action="store_true", help="run nothing: gather the run folders of OUT and write the report")
    p.add_argument("--no-report", action="store_true", help="write the results files but not report.md and its pictures")
    add_run_options(p)
    p.set_defaults(func=run)


# --------------------------------------------------------------------------------------- helpers
class UsageError(Exception):
    """A bad option value; printed as ``error: ...`` with exit status 2."""


def parse_assignments(items: list[str], option: str) -> dict[str, Any]:
    """``["density.max_gaussians=800", "iterations=90"]`` -> nested dict; values parsed as JSON
    when they are JSON (numbers, true/false/null, lists), else kept as strings."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"{option}: expected KEY=VALUE, got {item!r}")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UsageError(f"{option}: {key} conflicts with an earlier assignment")
        node[parts[-1]] = value
    return out


def _split(text: str, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise UsageError(f"{what}: nothing given")
    return items


def build_cells(args: argparse.Namespace, scene_texts: list[str], variants: list[str], seeds: list[int]):
    """The grid's cells from the parsed options (raises UsageError for bad values)."""
    from polargs_plugin.ablation.grid import expand
    from polargs_plugin.ablation.scenes import bundled_names, parse_scene

    out: Path = args.out
    cache = args.scene_cache or out / "scenes"
    width, height = args.size
    scenes = []
    for text in scene_texts:
        try:
            scenes.append(parse_scene(text, cache, args.views, width, height))
        except ValueError as err:
            raise UsageError(f"--scenes: {err}") from None
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise UsageError(f"--scenes: the same scene name twice ({', '.join(names)})")
    for scene in scenes:
        if scene.bundled is None and not Path(scene.path).exists():
            print(f"warning: {scene.path}: dataset not found; the runs of scene '{scene.name}' will fail", file=sys.stderr)
    inits = _split(args.init, "--init")
    bad = [i for i in inits if i not in _INITS]
    if bad:
        raise UsageError(f"--init: unknown {', '.join(bad)} (known: {', '.join(_INITS)})")
    train_overrides = parse_assignments(args.train_set, "--train-set")
    if args.iters is not None:
        train_overrides["iterations"] = args.iters
    polar_overrides = parse_assignments(args.polar_set, "--polar-set")
    cells = []
    for scene in scenes:
        mesh: dict[str, Any] = {"preset": args.mesh_preset}
        if args.voxel is not None:
            mesh["voxel"] = args.voxel
        elif scene.bundled is not None and args.mesh_preset == "synthetic" and min(scene.width, scene.height) != 128:
            mesh["voxel"] = 1.0 / min(scene.width, scene.height)  # the preset's voxel (1/128 at 128 px) per pixel size
        cells += expand([scene], variants, seeds, out, inits, preset=args.preset, factor=args.factor,
                        train_overrides=train_overrides, polar_overrides=polar_overrides, mesh=mesh,
                        eval={"num_samples": args.eval_samples, "cull": not args.no_cull},
                        threads=args.threads_per_run, device=args.device)
    for variant in dict.fromkeys(variants):  # overrides are checked before anything runs
        probe = next(c for c in cells if c.variant == variant)
        try:
            probe.configs()
        except (KeyError, TypeError, ValueError) as err:
            raise UsageError(f"--train-set / --polar-set: {err}".replace("'", "") if isinstance(err, KeyError) else f"--train-set / --polar-set: {err}") from None
    return cells


def execute(args: argparse.Namespace, cells: list, command: str) -> int:
    """Run the grid, gather, write the report, print the table; the exit status."""
    from polargs_plugin.ablation.gather import gather
    from polargs_plugin.ablation.grid import default_jobs, run_grid, write_grid_file

    out: Path = args.out
    jobs = args.jobs or default_jobs(args.threads_per_run)
    start = time.perf_counter()
    write_grid_file(cells, out)
    print(f"ablation: {len(cells)} runs in {out} ({jobs} at a time, {args.threads_per_run} thread(s) each)", file=sys.stderr, flush=True)
    result = run_grid(cells, jobs=jobs, progress=not args.quiet)
    results = gather(out)
    print(results["markdown"])
    if not getattr(args, "no_report", False):
        from polargs_plugin.ablation.report import write_report

        print(f"report: {write_report(out, results, command)}")
    print(f"results: {out / 'results.md'}, {out / 'results.csv'}, {out / 'results.json'}")
    print(f"{len(result.finished)} run(s) finished, {len(result.skipped)} skipped (already done), "
          f"{len(result.failed)} failed; {time.perf_counter() - start:.0f} s")
    if result.failed:
        print(f"error: {len(result.failed)} of {len(cells)} runs failed:", file=sys.stderr)
        for cell, log, message in result.failed:
            print(f"  {cell.name}: {message} (log: {log})", file=sys.stderr)
        return 1
    return 0


def command_line(name: str, args: argparse.Namespace, extra: list[str]) -> str:
    """The canonical command that reproduces this invocation (for the report)."""
    parts = ["polargs", name, *extra, "--out", str(args.out)]
    width, height = args.size
    for flag, value, default in (("--preset", args.preset, "cpu"), ("--factor", args.factor, None), ("--iters", args.iters, None),
                                 ("--init", args.init, "hull"), ("--views", args.views, 24), ("--size", f"{width}x{height}", "128x128"),
                                 ("--mesh-preset", args.mesh_preset, "synthetic"), ("--voxel", args.voxel, None),
                                 ("--eval-samples", args.eval_samples, 1_000_000), ("--threads-per-run", args.threads_per_run, 1)):
        if value != default:
            parts += [flag, str(value)]
    if args.scene_cache is not None:
        parts += ["--scene-cache", str(args.scene_cache)]
    for item in args.train_set:
        parts += ["--train-set", item]
    for item in args.polar_set:
        parts += ["--polar-set", item]
    if args.no_cull:
        parts.append("--no-cull")
    return shlex.join(parts)


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.ablation.variants import parse_variants

    out: Path = args.out
    if out.exists() and not out.is_dir():
        print(f"error: {out}: exists and is not a folder", file=sys.stderr)
        return 2
    if args.gather_only:
        from polargs_plugin.ablation.gather import find_runs, gather

        if not find_runs(out):
            print(f"error: {out}: no finished run folders to gather", file=sys.stderr)
            return 2
        results = gather(out)
        print(results["markdown"])
        if not args.no_report:
            from polargs_plugin.ablation.report import write_report

            print(f"report: {write_report(out, results)}")
        return 0
    try:
        if not args.scenes:
            raise UsageError("--scenes: required (or --gather-only)")
        try:
            variants = parse_variants(args.variants)
        except ValueError as err:
            raise UsageError(f"--variants: {err}") from None
        try:
            seeds = [int(s) for s in _split(args.seeds, "--seeds")]
        except ValueError:
            raise UsageError(f"--seeds: expected comma-separated integers, got {args.seeds!r}") from None
        cells = build_cells(args, _split(args.scenes, "--scenes"), variants, seeds)
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    extra = ["--scenes", args.scenes, "--variants", ",".join(variants), "--seeds", ",".join(map(str, seeds))]
    return execute(args, cells, command_line("ablate", args, extra))
