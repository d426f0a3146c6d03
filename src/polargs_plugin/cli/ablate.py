"""``polargs ablate``: the PolarGS ablation grid (scenes x variants x seeds), gathered into a table
and a report with pictures. The machinery lives in :mod:`polargs_plugin.ablation`."""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from polargs_plugin.ablation.variants import DESCRIPTIONS, PRESETS, VARIANTS
from polargs_plugin.cli.argtypes import factor_at_least_one, image_size, non_negative_int, positive_float, positive_int, unit_fraction
from polargs_plugin.cli.common import add_reader_options, command_line_of, on_stop_signals, reader_options
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.mesh import MeshSettings

if TYPE_CHECKING:
    from polargs_plugin.ablation.grid import GridOptions

CLUSTERS = ("auto", "slurm", "local", "debug")


_DESCRIPTION = """\
Run the PolarGS ablation: every scene x variant x seed is one training of the reference backend,
meshed (TSDF) and evaluated against the scene's ground-truth mesh. Results are gathered into
OUT/results.csv, OUT/results.json and OUT/results.md (mean and spread over seeds) and a report
OUT/report.md with pictures. See docs/ablation.md.

Variants:
""" + "\n".join(f"  {name:9s} {text}" for name, text in DESCRIPTIONS.items()) + """

Scenes (comma-separated): a bundled name (glossy_plane_sphere, shiny_torus, bumpy_mixed,
torus_knot; generated once into --scene-cache with --views/--size), family:K (the procedural
family's scene of seed K, with its own views and size; development seeds 0-9999 and 20000-29999,
test seeds 10000-19999 and from 30000 on, the second block with environment lighting,
docs/scene-family.md), or a dataset folder in any supported format as
NAME=PATH:GT_MESH, NAME=PATH or PATH (GT mesh: gt_mesh.ply or mesh.ply in the folder).

Resumable: run folders are complete or absent; finished runs are skipped when the command runs
again, and an interrupted run resumes from its last periodic checkpoint. A failed run leaves
OUT/logs/NAME.log, the others go on; the exit status is 1 if any failed.

Executors: --executor local (default) runs the cells in a process pool on this machine, one run per
visible GPU when CUDA is available; --executor submitit submits them as ONE Slurm job array (or
submitit's local / debug executors) and records the jobs in OUT/jobs.json: submitting again
skips done and running cells, --retry-failed resubmits only the failed ones. See docs/cluster.md.

Examples:
  polargs ablate --scenes glossy_plane_sphere,shiny_torus --variants all --seeds 0,1 --out runs/ablation
  polargs ablate --scenes gps=data/gps:data/gps/gt.ply --variants base,reg,full --out runs/gps --jobs 2
  polargs ablate --scenes family:3,family:17 --variants reg,full --out runs/family-dev
  polargs ablate --scenes shiny_torus --variants all --seeds 0,1,2 --preset paper --out runs/paper \\
                 --executor submitit --slurm-partition gpu --gpus-per-task 1 --cpus-per-task 8 --timeout-min 120
  polargs ablate --status runs/paper                        # done / running / failed / missing, with logs
  polargs ablate --out runs/ablation --gather-only          # table + report from the run folders
  polargs ablate --trainer 2dgs=~/src/2d-gaussian-splatting --scenes bumpy_mixed --out runs/plugin-2dgs
                                                            # an upstream trainer alone and with PolarGS
                                                            # (docs/adapters/plugin-ablation.md)
"""










def add_run_options(p: argparse.ArgumentParser, default_factor_help: str = "1/6: 5000 iterations") -> None:
    """Options shared by ``polargs ablate`` and ``polargs demo``."""
    p.add_argument("--jobs", type=positive_int, default=None, metavar="N",
                   help="runs in parallel (default: one per GPU when CUDA is available, see --gpus; else cores // --threads-per-run); "
                   "1 runs in this process")
    p.add_argument("--threads-per-run", type=positive_int, default=1, metavar="T", help="torch threads of each run (default 1)")
    p.add_argument("--preset", choices=PRESETS, default="cpu",
                   help="cpu: the vanilla schedule x --factor, PolarGS' x min(1, 3 --factor) (TrainConfig.cpu, PolarConfig.cpu_demo); paper: vanilla 3DGS "
                   "schedule with the paper's synthetic settings, for a GPU (default cpu)")
    p.add_argument("--factor", type=positive_float, default=None, metavar="F", help=f"schedule factor of the cpu preset (default {default_factor_help})")
    p.add_argument("--iters", type=positive_int, default=None, metavar="N", help="training iterations (default: the preset's)")
    p.add_argument("--init", default="hull", metavar="INIT",
                   help="initial points: hull (visual hull of the masks), sfm (triangulated SIFT matches with the known poses; "
                   "falls back to hull when too few, recorded), random (uniform in the look-at cube); comma-separated to run several (default hull)")
    p.add_argument("--views", type=positive_int, default=None, metavar="N",
                   help="views of a generated scene (default: 24 for a bundled scene, the seed's for family:K)")
    p.add_argument("--size", type=image_size, default=None, metavar="WxH",
                   help="image size of a generated scene (default: 128x128 for a bundled scene, the seed's for family:K)")
    p.add_argument("--scene-cache", type=Path, default=None, metavar="DIR", help="where bundled scenes are generated and reused (default OUT/scenes)")
    p.add_argument("--train-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a TrainConfig field, dotted for nested ones (e.g. density.max_gaussians=3000); repeatable")
    p.add_argument("--polar-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PolarConfig field of the variants with hooks (e.g. losses.alpha_normal=0.1); repeatable")
    p.add_argument("--mesh-preset", choices=("synthetic", "paper"), default="synthetic", help="TSDF settings (polargs mesh --preset; default synthetic)")
    p.add_argument("--voxel", type=positive_float, default=None,
                   help="TSDF voxel (default: the preset's; for bundled scenes scaled to the image size, 1 / min(W, H))")
    p.add_argument("--incidence-trunc", type=factor_at_least_one, default=MeshSettings.incidence_trunc, metavar="FACTOR",
                   help="TSDF truncation widened by 1/cos of each pixel's incidence, up to FACTOR "
                   f"(polargs mesh --incidence-trunc; default {MeshSettings.incidence_trunc:g}, 1 disables)")
    p.add_argument("--partial-alpha", type=unit_fraction, default=MeshSettings.partial_alpha, metavar="ALPHA",
                   help="TSDF fusion of the partly transparent pixels inside the masks, opacity from ALPHA to 0.5 "
                   f"(polargs mesh --partial-alpha; default {MeshSettings.partial_alpha:g}, 0.5 disables)")
    p.add_argument("--spare-pieces-in-masks", action="store_true",
                   help="TSDF: keep the small pieces inside every view's mask (polargs mesh --spare-pieces-in-masks)")
    p.add_argument("--eval-samples", type=positive_int, default=1_000_000, metavar="N", help="points sampled per mesh for Chamfer (default 1e6)")
    p.add_argument("--no-cull", action="store_true", help="do not cull predicted points to the view masks before Chamfer")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--gpus", default=None, metavar="IDS",
                   help="local executor: GPUs to spread the runs over, one run per GPU at a time (comma-separated ids, "
                   "or none; default: every visible GPU when CUDA is available)")
    p.add_argument("--checkpoint-every", type=non_negative_int, default=None, metavar="N",
                   help="iterations between the training checkpoints an interrupted run resumes from "
                   "(default: 10 per run; 0: none)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (one line per finished run is still printed)")
    add_reader_options(p)  # --format, --pattern, --no-pattern-check, --bit-depth, --sfm (dataset-folder scenes only)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ablate",
        help="run the ablation grid (scenes x variants x seeds) and write a report",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenes", default=None, metavar="A,B,...", help="comma-separated scenes (see above)")
    p.add_argument("--variants", default="all", metavar="V,...", help=f"comma-separated subset of {','.join(VARIANTS)}, or all (default); with --trainer: alone, polargs")
    p.add_argument("--seeds", default="0", metavar="S,...", help="comma-separated training seeds (default 0)")
    p.add_argument("--out", type=Path, metavar="DIR", help="the ablation folder (run folders, logs, results, report); required")
    p.add_argument("--gather-only", action="store_true", help="run nothing: gather the run folders of OUT and write the report")
    p.add_argument("--no-report", action="store_true", help="write the results files but not report.md and its pictures")
    p.add_argument("--status", type=Path, default=None, metavar="DIR",
                   help="run nothing: list the cells of DIR as done / running / failed / missing, with their logs and jobs")
    p.add_argument("--retry-failed", action="store_true",
                   help="run (or resubmit) only the cells that failed; with --executor submitit the failed cells are "
                   "otherwise left alone")
    add_run_options(p)
    g = p.add_argument_group("executors (docs/cluster.md)")
    g.add_argument("--executor", choices=("local", "submitit"), default="local",
                   help="local: a process pool on this machine (default); submitit: one job per cell, all in one Slurm "
                   "job array (needs pip install 'polargs_plugin[cluster]')")
    g.add_argument("--submitit-cluster", choices=CLUSTERS, default="auto",
                   help="submitit's executor: slurm, local (a process per cell on this machine), debug (in this process, "
                   "one after the other) or auto (slurm when srun is found, else local; default)")
    g.add_argument("--slurm-partition", default=None, metavar="NAME", help="Slurm partition")
    g.add_argument("--gpus-per-task", type=non_negative_int, default=None, metavar="N", help="GPUs per cell (default 1 on Slurm, 0 otherwise)")
    g.add_argument("--cpus-per-task", type=positive_int, default=None, metavar="N", help="CPUs per cell (default: --threads-per-run)")
    g.add_argument("--timeout-min", type=positive_int, default=240, metavar="MIN",
                   help="time limit of a job; a job that reaches it is checkpointed and requeued, up to 3 times (default 240)")
    g.add_argument("--mem-gb", type=positive_float, default=None, metavar="GB", help="memory per job (default: the partition's)")
    g.add_argument("--slurm-array-parallelism", type=positive_int, default=None, metavar="N", help="at most N cells running at once")
    g.add_argument("--slurm-additional-parameters", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                   help="more sbatch options, e.g. account=proj qos=high constraint=a100 (repeatable)")
    g.add_argument("--slurm-setup", action="append", default=[], metavar="CMD",
                   help="shell line run in the job before python, e.g. 'module load cuda' (repeatable)")
    plug = p.add_argument_group("plug-in ablation (docs/adapters/plugin-ablation.md)")
    plug.add_argument("--trainer", default=None, metavar="NAME=CHECKOUT",
                      help="instead of the reference trainer: an upstream trainer's checkout, patched (graphdeco, "
                      "graphdeco-2023, gof, pgsr, 2dgs), trained to the end of its own schedule x --factor on each scene, "
                      "alone and with PolarGS, on the CPU stand-ins of its extensions")
    wait = g.add_mutually_exclusive_group()
    wait.add_argument("--wait", dest="wait", action="store_true", default=None,
                      help="wait for the jobs, then gather and write the report (default with the local and debug clusters)")
    wait.add_argument("--no-wait", dest="wait", action="store_false",
                      help="submit and return (default on Slurm): follow with --status, then --gather-only")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------------------- helpers
def parse_assignments(items: list[str], option: str) -> dict[str, Any]:
    """``["density.max_gaussians=800", "iterations=90"]`` -> nested dict; values parsed as JSON
    when they are JSON (numbers, true/false/null, lists), else kept as strings."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise PolarInputError(option, f"expected KEY=VALUE, got {item!r}")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise PolarInputError(option, f"{key} conflicts with an earlier assignment")
        node[parts[-1]] = value
    return out


def _split(text: str, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise PolarInputError(what, "nothing given")
    return items


def grid_options(args: argparse.Namespace) -> "GridOptions":
    """The :class:`~polargs_plugin.ablation.grid.GridOptions` of parsed ``ablate`` / ``demo`` options."""
    from polargs_plugin.ablation.grid import GridOptions

    return GridOptions(
        out=args.out, scene_cache=args.scene_cache, views=args.views, size=None if args.size is None else tuple(args.size),
        inits=tuple(_split(args.init, "--init")), preset=args.preset, factor=args.factor, iters=args.iters,
        train_overrides=parse_assignments(args.train_set, "--train-set"),
        polar_overrides=parse_assignments(args.polar_set, "--polar-set"),
        mesh_preset=args.mesh_preset, voxel=args.voxel, incidence_trunc=args.incidence_trunc,
        partial_alpha=args.partial_alpha, spare_pieces_in_masks=args.spare_pieces_in_masks,
        eval_samples=args.eval_samples, cull=not args.no_cull, threads=args.threads_per_run, device=args.device,
        checkpoint_every=getattr(args, "checkpoint_every", None),
        reader=reader_options(args), command=command_line_of(args, args.command),
    )


def build_cells(args: argparse.Namespace, scene_texts: list[str], variants: list[str], seeds: list[int]):
    """The grid's cells from the parsed options (raises PolarInputError naming the option)."""
    from polargs_plugin.ablation.grid import build_cells as build

    def warn(line: str) -> None:
        print(f"warning: {line}", file=sys.stderr)

    return build(grid_options(args), scene_texts, variants, seeds, warn=warn)


def execute(args: argparse.Namespace, cells: list, command: str) -> int:
    """Run the grid, gather, write the report, print the table; the exit status."""
    from polargs_plugin.ablation.executors import ExecutorUnavailable, grid_status, visible_gpus
    from polargs_plugin.ablation.grid import default_jobs, run_grid, write_grid_file

    out: Path = args.out
    start = time.perf_counter()
    if getattr(args, "executor", "local") == "submitit":
        try:
            return _submit(args, cells, command, start)
        except ExecutorUnavailable as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    try:
        gpus = visible_gpus(getattr(args, "gpus", None), args.device)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    jobs = args.jobs or default_jobs(args.threads_per_run, gpus)
    write_grid_file(cells, out)
    todo, skipped_running = list(cells), []
    if getattr(args, "retry_failed", False) or (out / "jobs.json").is_file():
        try:
            states = {s.name: s.state for s in grid_status(out, cells)}
        except ExecutorUnavailable as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        skipped_running = [c for c in cells if states[c.name] == "running"]  # a cluster job runs it
        todo = [c for c in cells if states[c.name] != "running"]
        if getattr(args, "retry_failed", False):
            todo = [c for c in todo if states[c.name] in ("failed", "done")]  # done ones are only counted as skipped
        if skipped_running:
            print(f"ablation: {len(skipped_running)} cell(s) left to their running cluster jobs (polargs ablate --status {out})",
                  file=sys.stderr, flush=True)
    where = f"GPUs {','.join(gpus)}, " if gpus and jobs > 1 else ""
    print(f"ablation: {len(todo)} runs in {out} ({jobs} at a time, {where}{args.threads_per_run} thread(s) each)", file=sys.stderr, flush=True)
    received: list[int] = []

    def interrupt(signum: int) -> None:  # SIGTERM as Ctrl-C: the grid stops its runs and ends cleanly
        received.append(signum)
        raise KeyboardInterrupt

    try:
        with on_stop_signals(interrupt):
            result = run_grid(todo, jobs=jobs, progress=not args.quiet, gpus=gpus if jobs > 1 else ())
    except KeyboardInterrupt:
        return _interrupted(cells, out, received[0] if received else signal.SIGINT)
    return _finish(args, cells, command, result, start)


def _interrupted(cells: list, out: Path, signum: int) -> int:
    """The line an interrupted grid ends with; its exit status (128 + the signal)."""
    from polargs_plugin.ablation.cell import is_done

    done = sum(is_done(cell) for cell in cells)
    print(f"interrupted ({signal.Signals(signum).name}): {done} of {len(cells)} runs finished; runs under way keep "
          f"their last periodic checkpoint in {out / '.partial'}; the same command continues them", file=sys.stderr)
    return 128 + int(signum)


def _finish(args: argparse.Namespace, cells: list, command: str, result, start: float, skipped_note: str = "") -> int:
    """Gather, report, print the table and the counts; the exit status."""
    from polargs_plugin.ablation.gather import find_runs, gather

    out: Path = args.out
    if not find_runs(out):
        print(f"no finished run folders in {out} yet")
        return _failures(result, cells)
    results = gather(out)
    print(results["markdown"])
    if not getattr(args, "no_report", False):
        from polargs_plugin.ablation.report import write_report

        print(f"report: {write_report(out, results, command)}")
    print(f"results: {out / 'results.md'}, {out / 'results.csv'}, {out / 'results.json'}")
    print(f"{len(result.finished)} run(s) finished, {len(result.skipped)} skipped (already done), "
          f"{len(result.failed)} failed{skipped_note}; {time.perf_counter() - start:.0f} s")
    return _failures(result, cells)


def _failures(result, cells: list) -> int:
    if result.failed:
        print(f"error: {len(result.failed)} of {len(cells)} runs failed:", file=sys.stderr)
        for cell, log, message in result.failed:
            print(f"  {cell.name}: {message} (log: {log})", file=sys.stderr)
        return 1
    return 0


def _submit(args: argparse.Namespace, cells: list, command: str, start: float) -> int:
    """--executor submitit: one job array for the cells that need it; wait (local / debug) or return."""
    from polargs_plugin.ablation.executors import SubmititOptions, require_submitit, submit_grid, wait_jobs
    from polargs_plugin.ablation.grid import GridResult, write_grid_file

    require_submitit()
    out: Path = args.out
    options = SubmititOptions(
        cluster=args.submitit_cluster, partition=args.slurm_partition, gpus_per_task=args.gpus_per_task,
        cpus_per_task=args.cpus_per_task, timeout_min=args.timeout_min, mem_gb=args.mem_gb,
        array_parallelism=args.slurm_array_parallelism,
        additional_parameters=_key_values(args.slurm_additional_parameters, "--slurm-additional-parameters"),
        setup=list(args.slurm_setup),
    )
    write_grid_file(cells, out)
    if args.submitit_cluster == "auto":
        import shutil

        if shutil.which("srun") is None:
            print("ablation: no Slurm here (srun not found): submitit's local executor runs every cell at once "
                  "as a process of this machine", file=sys.stderr, flush=True)
    from polargs_plugin.ablation.grid import generate_scenes

    generate_scenes(cells, progress=not args.quiet)  # once here, not in every job
    submitted = submit_grid(cells, options, retry_failed=args.retry_failed)
    skipped = submitted.skipped
    counts = ", ".join(f"{len(names)} {state}" for state, names in sorted(skipped.items()))
    if submitted.submitted:
        kind = "job array" if submitted.cluster == "slurm" else f"submitit {submitted.cluster} jobs"
        print(f"ablation: submitted {len(submitted.submitted)} cell(s) as {kind} {submitted.array_id or ''} "
              f"({out / 'jobs.json'}); left alone: {counts or 'none'}", file=sys.stderr, flush=True)
        first = submitted.submitted[0][1]
        print(f"ablation: job logs in {first.paths.stdout.parent}/ (e.g. {first.paths.stdout.name})", file=sys.stderr, flush=True)
    else:
        hint = "" if args.retry_failed or "failed" not in skipped else " (--retry-failed resubmits the failed ones)"
        print(f"ablation: nothing to submit: {counts}{hint}", file=sys.stderr, flush=True)
    wait = args.wait if args.wait is not None else submitted.cluster != "slurm"
    if not wait:
        print(f"follow: polargs ablate --status {out}\nthen:   polargs ablate --out {out} --gather-only")
        return 0
    result = wait_jobs(submitted.submitted) if submitted.submitted else GridResult()
    result.skipped = [c for c in cells if c.name in set(skipped.get("done", []))]
    left = {state: len(skipped.get(state, [])) for state in ("running", "failed", "missing")}
    note = "".join(f", {n} {state} (left alone)" for state, n in left.items() if n)
    status = _finish(args, cells, command, result, start, note)
    if status == 0 and left["failed"]:
        print(f"error: {left['failed']} failed cell(s) left alone: polargs ablate --status {out}; "
              "resubmit them with --retry-failed", file=sys.stderr)
        return 1
    return status


def _key_values(items: list[str], option: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise PolarInputError(option, f"expected KEY=VALUE, got {item!r}")
        out[key.strip()] = value
    return out


def command_line(name: str, args: argparse.Namespace, extra: list[str]) -> str:
    """The canonical command that reproduces this invocation (for the report)."""
    parts = ["polargs", name, *extra, "--out", str(args.out)]
    size = None if args.size is None else "x".join(map(str, args.size))
    for flag, value, default in (("--preset", args.preset, "cpu"), ("--factor", args.factor, None), ("--iters", args.iters, None),
                                 ("--init", args.init, "hull"), ("--views", args.views, None), ("--size", size, None),
                                 ("--mesh-preset", args.mesh_preset, "synthetic"), ("--voxel", args.voxel, None),
                                 ("--incidence-trunc", args.incidence_trunc, MeshSettings.incidence_trunc),
                                 ("--partial-alpha", args.partial_alpha, MeshSettings.partial_alpha),
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
    if args.spare_pieces_in_masks:
        parts.append("--spare-pieces-in-masks")
    reader = reader_options(args).to_dict()
    if "fmt" in reader:
        parts += ["--format", reader["fmt"]]
    if "pattern" in reader:
        parts += ["--pattern", reader["pattern"]]
    if "bit_depth" in reader:
        parts += ["--bit-depth", str(reader["bit_depth"])]
    if reader.get("sfm"):
        parts.append("--sfm")
    if reader.get("check_pattern") is False:
        parts.append("--no-pattern-check")
    if "resolution" in reader:
        parts += ["--resolution", str(reader["resolution"])]
    return shlex.join(parts)


def _plugin_ablation(args: argparse.Namespace) -> int:
    """``--trainer NAME=CHECKOUT``: the upstream trainer alone and with PolarGS on each scene."""
    from polargs_plugin.service.plugin import PluginRequest, plugin_ablation

    name, sep, checkout = args.trainer.partition("=")
    if not sep or not name or not checkout:
        raise PolarInputError("--trainer", f"expected NAME=CHECKOUT, got {args.trainer!r}")
    for flag, value, default in (("--seeds", args.seeds, "0"),
                                 ("--executor", args.executor, "local"), ("--preset", args.preset, "cpu")):
        if value != default:
            raise PolarInputError(flag, "does not apply to --trainer (the trainer's own seed, this machine, "
                                        "the cpu preset's schedule x --factor)")
    given: dict[str, Any] = {"factor": args.factor, "views": args.views}  # None: the request's default
    if args.variants != "all":
        given["variants"] = tuple(_split(args.variants, "--variants"))
    if args.scenes is not None:
        given["scenes"] = tuple(_split(args.scenes, "--scenes"))
    if args.size is not None:
        given["width"], given["height"] = args.size
    request = PluginRequest(trainer=name, checkout=Path(checkout), out=args.out,
                            polar_overrides=parse_assignments(args.polar_set, "--polar-set"),
                            eval_samples=args.eval_samples, command=command_line_of(args, args.command),
                            **{key: value for key, value in given.items() if value is not None})
    records = plugin_ablation(request, progress=lambda message: print(message, flush=True))
    print((args.out / "results.md").read_text())
    return 1 if any("error" in r for r in records) else 0


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.ablation.variants import parse_variants

    if args.trainer is not None and args.out is not None:
        return _plugin_ablation(args)

    if args.status is not None:
        from polargs_plugin.ablation.executors import ExecutorUnavailable, format_status, grid_status

        if not args.status.is_dir():
            print(f"error: {args.status}: not a folder", file=sys.stderr)
            return 2
        try:
            print(format_status(grid_status(args.status)))
        except ExecutorUnavailable as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    if args.out is None:
        print("error: --out: required (or --status DIR)", file=sys.stderr)
        return 2
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
    if not args.scenes:
        raise PolarInputError("--scenes", "required (or --gather-only)")
    try:
        variants = parse_variants(args.variants)
    except ValueError as err:
        raise PolarInputError("--variants", str(err)) from None
    seed_texts = _split(args.seeds, "--seeds")
    try:
        seeds = [int(s) for s in seed_texts]
    except ValueError:
        raise PolarInputError("--seeds", f"expected comma-separated integers, got {args.seeds!r}") from None
    cells = build_cells(args, _split(args.scenes, "--scenes"), variants, seeds)
    _key_values(args.slurm_additional_parameters, "--slurm-additional-parameters")
    if args.executor == "submitit":
        from polargs_plugin.ablation.executors import ExecutorUnavailable, require_submitit

        try:
            require_submitit()
        except ExecutorUnavailable as err:  # names the option itself
            print(f"error: {err}", file=sys.stderr)
            return 2
    extra = ["--scenes", args.scenes, "--variants", ",".join(variants), "--seeds", ",".join(map(str, seeds))]
    return execute(args, cells, command_line("ablate", args, extra))
