"""The reference backend's whole training step on CPU, against its parts and a git revision.

Scene: a bundled scene (``generate_scene``, default glossy_plane_sphere), 24 views 128x128; the
Gaussians come from a short warm-up training (``TrainConfig.cpu`` schedule, capped at 6000) so
that opacities and sizes look like a model in training, not like an initialisation. Measured in
ONE run, in worker subprocesses started with the thread policy's environment (so that
``OMP_WAIT_POLICY`` reaches torch's OpenMP runtime, which reads it at ``import torch``). Each
group of parts below runs in a process of its own, as a training does (a process holding several
trainers runs each of them slower: their data evict each other's from the caches), and the groups
take turns, ``--rounds`` times, so that load changes on a shared machine hit all of them alike:

- raster + base (SH 1; again with SH 3): the rasterizer's forward + backward alone (render of
  the view the next Base step uses, a fixed random weighting of its colour, backward through the
  activations) and the whole Base step (render, colour loss with SSIM, backward, Adam, density
  statistics and control: paper schedule at iterations 7001-7000+S, so one refinement in 100
  steps), taking turns in blocks of ``--block`` steps from the same Gaussians;
- base + hooks (SH 1): the Base step again, taking turns with the step with PolarHooks (PC, L_dn,
  L_scale on, Dense off; PolarConfig.synthetic()) from the same Gaussians, the pair of
  ``hooks_over_base`` (both pay alike for sharing the process);
- turns (with ``--reference-rev REV`` or ``--reference-src DIR``), first in every round: the Base
  step of the package at an older git revision and this package's (SH 1), each in a worker
  process of its own, taking turns block by block, only one running at a time (the other sleeps
  in ``read``): the ``speedup_vs_reference`` figure, a median over the block pairs like the
  ratios within a group. The reference is a git revision, not a copy kept in this file: the
  revision is frozen by definition and needs no upkeep when the package's internals move.
  ``--reference-rev bfaaf45`` is the package before the fused training step (kornia's SSIM, the
  torch projection with its autograd graph, a float() of every figure and an MSE every step,
  boolean-indexed density statistics). Without a reference the figure is ``null``;
- dense: one Dense call (all PatchMatch rounds, filters, seeding) on this scene, after a warm-up
  call; its share of a whole run with the paper's window (61 calls: 1k-7k every 100, or the CPU
  preset's 500-3500 every 50): ``61 t_dense / (iterations t_hooks + 61 t_dense)`` for
  ``--iterations`` (default: the CPU preset's 5000);
- contention: a Base step loop alone, then two of them side by side (two processes); per-step
  median time side by side over alone;
- peak RSS: of a single Base training process (the contention loop), and the largest of all workers.

The table's figures are wall seconds (mean over the measured steps and rounds; CPU seconds in
brackets, less sensitive to other processes). The ratios of two parts of one group
(``step_over_raster``, ``hooks_over_base``) are medians over adjacent block pairs
(:func:`paired_ratio`): the machine's speed drifts by 15-40 % over seconds on a shared VM, and a
pair of blocks run back to back sees the same speed; the ratios of the means are printed too (and
in the JSON's ``ratios_of_means``). The last line is one JSON object.

    .venv/bin/python bench/train_step.py --reference-rev bfaaf45   # all figures, 2 threads
    .venv/bin/python bench/train_step.py --only-contention --numba-layer omp   # contention loops only
    .venv/bin/python bench/train_step.py --numba-layer omp --wait-policy none   # the older thread policy

A check that it runs, in under a minute (tiny sizes; the figures mean nothing):

    .venv/bin/python bench/train_step.py --views 6 --size 64 --gaussians 1000 --warmup-iterations 20
        --steps 4 --block 2 --rounds 1 --dense-calls 1 --no-contention    (one command line)
"""

from __future__ import annotations

import argparse
import io
import json
import os
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

# Nothing imports torch or numba at module level before a worker has its environment: the
# orchestrator passes the policy's environment to every worker subprocess.

DENSE_CALLS = 61  # the paper's window, 1000..7000 every 100 (the CPU preset's 500..3500 every 50)
START_ITER = 7000  # measured steps: L_dn on (from 7000), refinement every 100 (until 15000)


# ------------------------------------------------------------------------------ helpers
def _policy(args):
    from polargs_plugin.threads import ThreadPolicy

    wait = None if args.wait_policy == "none" else args.wait_policy
    return ThreadPolicy(threads=args.threads, numba_layer=args.numba_layer, wait_policy=wait)


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _scene(args):
    from polargs_plugin.data.synthetic import generate_scene

    return generate_scene(args.scene, num_views=args.views, width=args.size, height=args.size)


def _warm_params(args, views, path: Path) -> dict:
    """Raw parameters of a briefly trained model (SH degree 3 rows), cached in ``path``."""
    import torch

    if path.exists():
        return torch.load(path, weights_only=True)
    from polargs_plugin.backends.reference.strategy import DensityConfig
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer

    cfg = TrainConfig.cpu(
        iterations=args.warmup_iterations, sh_degree=3, progress=False, num_init_points=args.gaussians // 3,
        density=DensityConfig(max_gaussians=args.gaussians, opacity_reset=False), threads=_policy(args),
    )
    trainer = Trainer(views, cfg)
    trainer.train()
    params = {k: v.detach().clone() for k, v in trainer.model._params().items()}
    params["extent"] = torch.tensor(trainer.extent)
    torch.save(params, path)
    return params


def _trainer(args, views, params: dict, sh_degree: int, hooks=None, policy: bool = True):
    """A trainer at iteration START_ITER on the warm Gaussians (paper schedule, density on).

    ``policy=False`` for a package older than the thread policy (its environment still applies)."""
    from polargs_plugin.backends.reference.model import PARAM_NAMES, GaussianModel
    from polargs_plugin.backends.reference.strategy import DensityConfig, DensityControl
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer

    cfg = TrainConfig.paper(
        sh_degree=sh_degree, progress=False, density=DensityConfig(max_gaussians=args.gaussians),
        **({"threads": _policy(args)} if policy else {}),
    )
    raw = {k: params[k] for k in PARAM_NAMES}
    raw["sh_rest"] = raw["sh_rest"][:, : (sh_degree + 1) ** 2 - 1]
    colors = (raw["sh_dc"][:, 0] * 0.28209479177387814 + 0.5).clamp(0, 1)
    trainer = Trainer(views, cfg, hooks=hooks, init_points=(raw["means"], colors))
    extent = float(params["extent"])
    trainer.model = GaussianModel(raw, sh_degree=sh_degree, extent=extent, lrs=trainer.model.lrs)
    trainer.model.active_sh_degree = sh_degree
    trainer.density = DensityControl(cfg.density.scaled(cfg.schedule_scale), trainer.extent)
    trainer.iteration = START_ITER
    return trainer


# --------------------------------------------------------------------------------- workers
def _peek_view(trainer) -> int:
    import torch

    if not trainer._order:
        trainer._order = torch.randperm(len(trainer.views), generator=trainer._sampler).tolist()
    return trainer._order[-1]


def _raster(trainer, weights) -> None:
    """Forward + backward of the rasterizer alone on the view the next step of ``trainer`` uses."""
    index = _peek_view(trainer)
    out = trainer.render(trainer.views[index])
    (out.color * weights).sum().backward()
    trainer.model.optimizer.zero_grad(set_to_none=True)


#: The measured parts, in groups that share one worker process and take turns in blocks of
#: --block steps: the parts compared with each other (the rasterizer alone, the Base step and the
#: step with hooks) see the same load changes. Each group, like the reference revision, runs
#: in a process of its own: a process holding more trainers runs each of them slower (their data
#: evict each other's from the caches), which a training never sees.
#: The Base step in the hooks' process (``base1h``) is the reference of ``hooks_over_base`` only:
#: ``base1``, the reference of the other ratios, runs as a training does, one trainer a process.
GROUPS: tuple[tuple[str, ...], ...] = (
    ("raster1", "base1"), ("base1h", "hooks1"), ("raster3", "base3"),
)


def _runner(args, views, params, name: str, hooks=None):
    """The trainer a part steps (``raster1`` renders with ``base1``'s)."""
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.hooks import PolarHooks

    if name != "hooks1":  # base1, base1h, base3
        return _trainer(args, views, params, int(name[4]))
    if hooks is None:
        polar = PolarConfig.synthetic()
        polar.cache_dir = str(Path(args.tmp) / "maps")
        polar.densify.enabled = False
        hooks = PolarHooks(polar)
    return _trainer(args, views, params, 1, hooks=hooks)


def worker_measure(args) -> dict:
    """The parts of group ``--group`` (an index into GROUPS), interleaved in blocks of ``--block``
    steps; or one Dense call (``--group dense``)."""
    import torch

    applied = _policy(args).apply()
    views = _scene(args).views
    params = _warm_params(args, views, Path(args.tmp) / "warm.pt")
    result = {"threads": {"torch": torch.get_num_threads(), "numba": applied.numba_threads, "layer": applied.layer(),
                          "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"), "notes": applied.notes}}
    if args.group == "dense":
        result["dense"] = _measure_dense(args, views, params)
        result["peak_rss_mib"] = _rss_mib()
        return result
    parts = GROUPS[int(args.group)]
    trainers = [name for name in parts if not name.startswith("raster")]
    gen = torch.Generator().manual_seed(7)
    weights = torch.rand(3, args.size, args.size, generator=gen)
    runners = {name: _runner(args, views, params, name) for name in trainers}
    for t in runners.values():  # warm-up outside the measured window: JIT, preprocess, allocator
        t._prepare()
        _raster(t, weights)
        t.step()
    # Back to START_ITER on fresh trainers, prepared here: a trainer's first step would otherwise
    # run hooks.preprocess again (maps from the cache, L_ref's constants) inside the measured window.
    runners = {name: _runner(args, views, params, name, hooks=t.hooks) for name, t in runners.items()}
    for t in runners.values():
        t._prepare()
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in parts}

    def timed(name, fn):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        times[name].append((time.perf_counter() - wall, time.process_time() - cpu))

    steps = {name: (lambda t=runners["base" + name[-1]]: _raster(t, weights)) if name.startswith("raster")
             else runners[name].step for name in parts}
    # In blocks of --block consecutive steps: the parts of a group take turns (load changes hit both
    # alike) and each runs as in a training (its data warm in the caches after a block's first step).
    for _ in range(max(1, args.steps // args.block)):
        for name in parts:
            for _ in range(args.block):
                timed(name, steps[name])
    for name, v in times.items():
        walls = [w for w, _ in v]
        result[name] = {"wall": statistics.fmean(walls), "cpu": statistics.fmean(c for _, c in v),
                        "median": statistics.median(walls),
                        "blocks": [statistics.fmean(walls[i:i + args.block]) for i in range(0, len(walls), args.block)]}
    result["num_gaussians"] = {k: t.model.num for k, t in runners.items()}
    result["peak_rss_mib"] = _rss_mib()
    return result


def _measure_dense(args, views, params) -> dict:
    """One Dense call (PatchMatch rounds, filters, seeding) in the paper's window, after a warm-up."""
    import torch

    from polargs_plugin.config import PolarConfig
    from polargs_plugin.hooks import PolarHooks

    dense_cfg = PolarConfig.synthetic()
    dense_cfg.cache_dir = str(Path(args.tmp) / "maps")
    dense_hooks = PolarHooks(dense_cfg)
    trainer = _trainer(args, views, params, 1, hooks=dense_hooks)
    trainer._prepare()
    dense = []
    for k in range(args.dense_calls + 1):
        view = trainer.views[k % len(trainer.views)]
        with torch.no_grad():
            render = trainer.render(view)
            wall, cpu = time.perf_counter(), time.process_time()
            new = dense_hooks.densify(1000, view, trainer.render, trainer.model.state(), render=render)
            dense.append((time.perf_counter() - wall, time.process_time() - cpu, 0 if new is None else len(new)))
    dense = dense[1:]  # the first call compiles / loads the numba cache
    return {"wall": statistics.fmean(d[0] for d in dense), "cpu": statistics.fmean(d[1] for d in dense),
            "appended": statistics.fmean(d[2] for d in dense)}


def worker_turns(args) -> dict:
    """The Base step (SH 1) in blocks of ``--block`` steps, one block for each line read from
    stdin (one JSON line of the block's wall and CPU seconds written back), until stdin closes.
    Two of these take turns (:func:`_take_turns`): this package's and the reference revision's
    (``--reference-rev`` / ``--reference-src``: the package's source at that revision, its own
    training step exactly). Same warm Gaussians, same environment (thread counts, wait policy);
    the one waiting sleeps in ``read``."""
    import polargs_plugin

    old = bool(args.reference_src)
    if old and not str(Path(polargs_plugin.__file__)).startswith(str(Path(args.reference_src).resolve())):
        raise SystemExit(f"reference worker imported {polargs_plugin.__file__}, not {args.reference_src}")
    if not old:
        _policy(args).apply()
    views = _scene(args).views
    params = _warm_params(args, views, Path(args.tmp) / "warm.pt")
    trainer = _trainer(args, views, params, 1, policy=not old)
    for _ in range(3):  # JIT and allocator warm-up
        trainer.step()
    trainer = _trainer(args, views, params, 1, policy=not old)
    print(json.dumps({"ready": True}), flush=True)
    walls, cpus = [], []
    for _ in sys.stdin:
        block_walls, block_cpus = [], []
        for _ in range(args.block):
            wall, cpu = time.perf_counter(), time.process_time()
            trainer.step()
            block_walls.append(time.perf_counter() - wall)
            block_cpus.append(time.process_time() - cpu)
        walls += block_walls
        cpus += block_cpus
        print(json.dumps({"wall": statistics.fmean(block_walls), "cpu": statistics.fmean(block_cpus)}), flush=True)
    return {"wall": statistics.fmean(walls), "cpu": statistics.fmean(cpus), "median": statistics.median(walls),
            "package": str(Path(polargs_plugin.__file__).parent), "peak_rss_mib": _rss_mib()}


def worker_loop(args) -> dict:
    """Base steps (SH 1) for ``--seconds`` after a warm-up; per-step wall times."""
    _policy(args).apply()
    views = _scene(args).views
    params = _warm_params(args, views, Path(args.tmp) / "warm.pt")
    trainer = _trainer(args, views, params, 1)
    for _ in range(3):
        trainer.step()
    if args.start_at:
        while time.time() < args.start_at:
            time.sleep(0.01)
    steps, cpus = [], []
    end = time.perf_counter() + args.seconds
    while time.perf_counter() < end:
        wall, cpu = time.perf_counter(), time.process_time()
        trainer.step()
        steps.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return {"median": statistics.median(steps), "mean": statistics.fmean(steps), "steps": len(steps),
            "cpu_median": statistics.median(cpus), "peak_rss_mib": _rss_mib()}


# ---------------------------------------------------------------------------- orchestrator
def _worker_cmd(args, mode: str, extra: list[str] | None = None) -> list[str]:
    cmd = [sys.executable, __file__, "--worker", mode, "--tmp", args.tmp]
    for key in ("scene", "views", "size", "gaussians", "threads", "steps", "block", "numba_layer", "wait_policy",
                "warmup_iterations", "dense_calls", "seconds"):
        cmd += [f"--{key.replace('_', '-')}", str(getattr(args, key))]
    return cmd + (extra or [])


def _worker_env(args) -> dict:
    env = dict(os.environ)
    for key in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER"):
        env.pop(key, None)
    env.update(_policy(args).environment())
    env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(args.threads)
    return env


def _run_workers(args, mode: str, count: int, options: list[str] | None = None) -> list[dict]:
    start_at = time.time() + (45 if count > 1 else 0)  # side by side: both start measuring together
    env = _worker_env(args)
    extra = (["--start-at", str(start_at)] if count > 1 else []) + (options or [])
    procs = [subprocess.Popen(_worker_cmd(args, mode, extra),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(count)]
    results = []
    for p in procs:
        out, err = p.communicate()
        if p.returncode != 0:
            sys.stderr.write(err)
            raise SystemExit(f"worker {mode} failed ({p.returncode})")
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def _take_turns(args) -> dict:
    """This package's Base step and the reference revision's (``--reference-src``), each in a
    worker process of its own (:func:`worker_turns`), taking turns block by block, the reference
    first in each pair: only one of them runs at any time, and a pair of blocks sees the same
    machine speed. Returns each worker's blocks (mean wall seconds) and summary."""
    source = Path(args.reference_src).resolve()
    env_new = _worker_env(args)
    # The old package first on the path; this file's helpers still import from it.
    env_old = dict(env_new, PYTHONPATH=os.pathsep.join([str(source), env_new.get("PYTHONPATH", "")]))
    commands = {"reference": (_worker_cmd(args, "turns", ["--reference-src", str(source / "polargs_plugin")]), env_old),
                "base": (_worker_cmd(args, "turns"), env_new)}
    with tempfile.TemporaryFile("w+") as err_reference, tempfile.TemporaryFile("w+") as err_base:
        errors = {"reference": err_reference, "base": err_base}
        procs = {name: subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors[name],
                                        text=True, env=env)
                 for name, (cmd, env) in commands.items()}

        def answer(name: str) -> dict:
            line = procs[name].stdout.readline()
            if not line:
                procs[name].wait()
                errors[name].seek(0)
                sys.stderr.write(errors[name].read())
                raise SystemExit(f"worker turns ({name}) failed ({procs[name].returncode})")
            return json.loads(line)

        try:
            for name in procs:
                answer(name)  # ready: warmed up
            blocks: dict[str, list[float]] = {name: [] for name in procs}
            for _ in range(max(1, args.steps // args.block)):
                for name, proc in procs.items():
                    proc.stdin.write("block\n")
                    proc.stdin.flush()
                    blocks[name].append(answer(name)["wall"])
            summaries = {}
            for name, proc in procs.items():
                proc.stdin.close()
                summaries[name] = answer(name)
                proc.wait()
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
    return {"blocks": blocks, "summaries": summaries}


def paired_ratio(blocks: list[float], reference_blocks: list[float]) -> float:
    """Median over the block pairs of a group of (mean step time of a part's block) / (that of the
    reference part's block just before it). Each pair ran within a second or two of each other,
    so a change of the machine's speed between blocks (15-40 % on a shared VM) cancels out,
    which the ratio of the means over the whole run does not do.

    >>> paired_ratio([1.1, 2.2, 1.21], [1.0, 2.0, 1.0])
    1.1
    """
    if len(blocks) != len(reference_blocks) or not blocks:
        raise ValueError(f"paired_ratio: {len(blocks)} blocks against {len(reference_blocks)} reference blocks")
    return statistics.median(b / r for b, r in zip(blocks, reference_blocks))


def _measure_groups(args) -> tuple[list[dict], dict]:
    """Every group of GROUPS in a worker of its own, ``--rounds`` times in turn (with the reference
    revision and this package taking turns first in each round, :func:`_take_turns`), then one
    Dense worker. Returns the rounds of turns and, per part, the mean wall / CPU time and the
    median over the rounds, plus the workers' details."""
    turns, runs, num_gaussians, rss = [], {}, {}, []
    threads = None
    for _ in range(args.rounds):
        if args.reference_src:
            turns.append(_take_turns(args))
            rss += [summary["peak_rss_mib"] for summary in turns[-1]["summaries"].values()]
        for index, group in enumerate(GROUPS):
            out = _run_workers(args, "measure", 1, ["--group", str(index)])[0]
            for name in group:
                runs.setdefault(name, []).append(out[name])
            num_gaussians.update(out["num_gaussians"])
            rss.append(out["peak_rss_mib"])
            threads = out["threads"]
    dense = _run_workers(args, "measure", 1, ["--group", "dense"])[0]
    m = {name: {key: statistics.fmean(r[key] for r in rs) for key in ("wall", "cpu", "median")}
         for name, rs in runs.items()}
    for name, rs in runs.items():
        m[name]["blocks"] = [block for r in rs for block in r["blocks"]]  # in order, round after round
    m.update(dense=dense["dense"], threads=threads, num_gaussians=num_gaussians,
             peak_rss_mib=max(rss + [dense["peak_rss_mib"]]))
    return turns, m


def _extract_revision(revision: str, into: Path) -> Path:
    """The ``src`` folder of this repository at git revision ``revision``, extracted under
    ``into``; the reference package of :func:`_take_turns`."""
    repo = Path(__file__).resolve().parent.parent
    archive = subprocess.run(["git", "-C", str(repo), "archive", revision, "src"], check=False,
                             capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"error: --reference-rev {revision}: {archive.stderr.decode().strip()}")
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(into, filter="data")
    return into / "src"


def _prepare_warm(args) -> None:
    """Train the warm model once (in a worker, with the policy's environment)."""
    subprocess.run(_worker_cmd(args, "prepare"), check=True, env=_worker_env(args), capture_output=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="glossy_plane_sphere")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--gaussians", type=int, default=6000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=100, help="measured steps per configuration (interleaved)")
    parser.add_argument("--block", type=int, default=10,
                        help="consecutive steps of one part before the next part of its group (1: step by step)")
    parser.add_argument("--rounds", type=int, default=2, help="times every group's worker runs, in turn")
    parser.add_argument("--group", help=argparse.SUPPRESS)
    parser.add_argument("--iterations", type=int, default=None,
                        help="run length for the Dense share (default: the CPU preset's, TrainConfig.cpu().iterations)")
    parser.add_argument("--numba-layer", default="workqueue", choices=("workqueue", "omp", "tbb", "default"))
    parser.add_argument("--wait-policy", default="passive", choices=("passive", "active", "none"))
    parser.add_argument("--warmup-iterations", type=int, default=150)
    parser.add_argument("--dense-calls", type=int, default=2, help="timed Dense calls (after one warm-up)")
    parser.add_argument("--seconds", type=float, default=20.0, help="contention: measured seconds per loop")
    parser.add_argument("--no-contention", action="store_true")
    parser.add_argument("--only-contention", action="store_true", help="only the contention loops (quick policy comparisons)")
    reference = parser.add_mutually_exclusive_group()
    reference.add_argument("--reference-rev", metavar="REV",
                           help="the reference for speedup_vs_reference: this repository's package at git revision "
                           "REV (e.g. bfaaf45, the package before the fused training step); its Base step and this "
                           "package's take turns block by block in two worker processes")
    reference.add_argument("--reference-src", metavar="DIR",
                           help="as --reference-rev, from a folder already extracted (DIR/polargs_plugin, e.g. "
                           "`git archive REV src | tar -x -C PARENT`, DIR = PARENT/src)")
    parser.add_argument("--worker", choices=("prepare", "measure", "loop", "turns"), help=argparse.SUPPRESS)
    parser.add_argument("--tmp", help=argparse.SUPPRESS)
    parser.add_argument("--start-at", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.iterations is None and args.worker is None:
        # Not at module level: the reference worker imports this file with the old package first.
        from polargs_plugin.config import CPU_FACTOR  # plain dataclasses: loads neither torch nor numba

        args.iterations = round(30_000 * CPU_FACTOR)

    if args.worker:
        if args.worker == "prepare":
            _policy(args).apply()
            _warm_params(args, _scene(args).views, Path(args.tmp) / "warm.pt")
            print(json.dumps({"ok": True}))
        else:
            work = {"measure": worker_measure, "loop": worker_loop, "turns": worker_turns}[args.worker]
            print(json.dumps(work(args)))
        return 0

    started = time.perf_counter()
    load_before = _load()
    with tempfile.TemporaryDirectory() as tmp:
        args.tmp = tmp
        if args.reference_rev:
            args.reference_src = str(_extract_revision(args.reference_rev, Path(tmp) / "reference"))
        _prepare_warm(args)
        if args.only_contention:
            alone = _run_workers(args, "loop", 1)[0]
            pair = _run_workers(args, "loop", 2)
            slowdown = statistics.fmean(p["median"] for p in pair) / alone["median"]
            cpu = statistics.fmean(p["cpu_median"] for p in pair) / alone["cpu_median"]
            print(f"contention ({args.numba_layer}, OMP_WAIT_POLICY {args.wait_policy}): alone {alone['median']:.4f} s "
                  f"(cpu {alone['cpu_median']:.4f}), side by side " + ", ".join(
                      f"{p['median']:.4f} (cpu {p['cpu_median']:.4f})" for p in pair) + f"; load {_load()}")
            print(json.dumps({"contention_slowdown": slowdown, "contention_cpu_slowdown": cpu, "alone": alone,
                              "pair": pair, "load_before": load_before, "load_after": _load()}))
            return 0
        turns, m = _measure_groups(args)
        contention = None
        if not args.no_contention:
            alone = _run_workers(args, "loop", 1)[0]
            pair = _run_workers(args, "loop", 2)
            contention = {"alone": alone, "pair": pair,
                          "slowdown": statistics.fmean(p["median"] for p in pair) / alone["median"],
                          "cpu_slowdown": statistics.fmean(p["cpu_median"] for p in pair) / alone["cpu_median"]}
    wall = lambda k: m[k]["wall"]  # noqa: E731
    t_dense = m["dense"]["wall"]
    share = DENSE_CALLS * t_dense / (args.iterations * wall("hooks1") + DENSE_CALLS * t_dense)
    rss = max([m["peak_rss_mib"]] + ([contention["alone"]["peak_rss_mib"]] + [p["peak_rss_mib"] for p in contention["pair"]]
                                     if contention else []))
    single_rss = contention["alone"]["peak_rss_mib"] if contention else m["peak_rss_mib"]
    paired = lambda part, reference: paired_ratio(m[part]["blocks"], m[reference]["blocks"])  # noqa: E731
    # The reference revision's and this package's Base step taking turns, block by block.
    turn_blocks = {name: [b for t in turns for b in t["blocks"][name]] for name in ("reference", "base")}
    turn_means = {name: statistics.fmean(turn_blocks[name]) for name in turn_blocks} if turns else {}
    figures = {
        "step_over_raster": paired("base1", "raster1"),
        "step_over_raster_sh3": paired("base3", "raster3"),
        "speedup_vs_reference": paired_ratio(turn_blocks["reference"], turn_blocks["base"]) if turns else None,
        "hooks_over_base": paired("hooks1", "base1h"),
        "ratios_of_means": {"step_over_raster": wall("base1") / wall("raster1"),
                            "step_over_raster_sh3": wall("base3") / wall("raster3"),
                            "hooks_over_base": wall("hooks1") / wall("base1h"),
                            "speedup_vs_reference": (turn_means["reference"] / turn_means["base"] if turns
                                                     else None)},
        "dense_share": share,
        "contention_slowdown": contention["slowdown"] if contention else None,
        "contention_cpu_slowdown": contention["cpu_slowdown"] if contention else None,
        "peak_rss_mib": single_rss,
        "peak_rss_mib_all_workers": rss,
        "seconds": {k: round(wall(k), 5) for k in ("raster1", "base1", "base1h", "hooks1", "raster3", "base3")},
        "dense_call_s": round(t_dense, 3),
        "iterations_for_dense_share": args.iterations,
        "threads": m["threads"],
        "num_gaussians": m["num_gaussians"]["base1"],
        "reference_revision": args.reference_rev,
        "reference_package": turns[0]["summaries"]["reference"]["package"] if turns else None,
        "turns_seconds": {name: round(value, 5) for name, value in turn_means.items()},
        "load_before": load_before,
        "block": args.block,
        "load_after": _load(),
    }
    print(f"train-step bench: {args.scene}, {args.views} views {args.size}x{args.size}, ~{figures['num_gaussians']} "
          f"Gaussians, {args.threads} threads (torch {m['threads']['torch']}, numba {m['threads']['numba']} "
          f"'{m['threads']['layer']}', OMP_WAIT_POLICY={m['threads']['OMP_WAIT_POLICY']}), {args.steps} steps per part and round, in blocks of {args.block}, each group in its own process, {args.rounds} round(s) "
          f"steps from iteration {START_ITER + 1}; load average {load_before} -> {figures['load_after']} "
          f"({os.cpu_count()} CPUs)")
    for note in m["threads"]["notes"]:
        print(f"  note: {note}")
    print(f"{'part':44s} {'s/step':>8s} {'(cpu s)':>9s} {'median':>8s}")
    rows = [("raster1", "rasterizer fwd+bwd alone, SH 1"), ("base1", "Base step, SH 1"),
            ("base1h", "Base step beside the hooks step, SH 1"),
            ("hooks1", "step with PolarHooks (PC, L_dn, L_scale), SH 1"),
            ("raster3", "rasterizer fwd+bwd alone, SH 3"), ("base3", "Base step, SH 3")]
    for key, label in rows:
        print(f"{label:44s} {m[key]['wall']:8.4f} {m[key]['cpu']:9.4f} {m[key]['median']:8.4f}")
    for name, label in (("reference", "reference revision, Base step, SH 1 [2]"),
                        ("base", "Base step taking turns with it, SH 1 [2]")):
        if turns:
            summaries = [t["summaries"][name] for t in turns]
            print(f"{label:44s} {turn_means[name]:8.4f} {statistics.fmean(x['cpu'] for x in summaries):9.4f} "
                  f"{statistics.fmean(x['median'] for x in summaries):8.4f}")
    print(f"{'one Dense call (PatchMatch, filters, seeding)':44s} {t_dense:8.3f} {m['dense']['cpu']:9.3f} "
          f"({m['dense']['appended']:.0f} Gaussians appended)")
    if contention:
        print(f"contention: Base step median alone {contention['alone']['median']:.4f} s "
              f"(cpu {contention['alone']['cpu_median']:.4f}), side by side "
              + ", ".join(f"{p['median']:.4f} (cpu {p['cpu_median']:.4f})" for p in contention["pair"]) + " s; "
              f"CPU seconds per step x{contention['cpu_slowdown']:.2f} (spinning workers inflate it)")
    targets = [
        ("step / raster fwd+bwd (SH 1) [1]", figures["step_over_raster"], "<= 1.5"),
        ("step / raster fwd+bwd (SH 3) [1]", figures["step_over_raster_sh3"], "<= 1.5"),
        ("reference revision's step / Base step [2]", figures["speedup_vs_reference"], ">= 4 vs bfaaf45"),
        ("hooks step / Base step [1]", figures["hooks_over_base"], "<= 1.10"),
        (f"Dense share of a {args.iterations}-iteration run", figures["dense_share"], "<= 0.25"),
        ("contention slowdown (2 trainings / alone)", figures["contention_slowdown"], "<= 2.5"),
        ("peak RSS of one training, MiB", figures["peak_rss_mib"], "<= 2048"),
    ]
    print(f"{'figure':44s} {'value':>8s}  target")
    for label, value, target in targets:
        print(f"{label:44s} {'n/a' if value is None else f'{value:8.3f}':>8s}  {target}")
    means = figures["ratios_of_means"]
    print("[1] median over adjacent block pairs (paired_ratio); the ratios of the means over the whole run: "
          f"{means['step_over_raster']:.3f}, {means['step_over_raster_sh3']:.3f}, {means['hooks_over_base']:.3f}")
    if turns:
        print("[2] two worker processes taking turns block by block, one running at a time; median over the "
              f"block pairs (paired_ratio); the ratio of the means: {means['speedup_vs_reference']:.3f}")
    figures["bench_seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
