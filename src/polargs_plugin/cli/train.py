"""``polargs train``: train the bundled reference 3D Gaussian Splatting backend on a dataset."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from polargs_plugin.io import PolarInputError, atomic_write

CHECKPOINT_NAME = "checkpoint.pt"
SUMMARY_NAME = "summary.json"

_DESCRIPTION = """\
Train 3D Gaussians on a polarimetric dataset with the bundled reference trainer (vanilla 3D
Gaussian Splatting on the s0/2 colour images), optionally with the PolarGS hooks (reflection-aware
colour losses and polar-guided PatchMatch densification).

DATASET is a dataset folder in any supported format (detected automatically), or
synthetic:NAME to render one of the bundled synthetic scenes on the fly (24 views, 128x128).

The run folder gets checkpoint.pt (resumable with --resume) and summary.json (settings and final
figures: training-view PSNR, number of Gaussians, time).

Examples:
  polargs train synthetic:glossy_plane_sphere --out runs/base --no-polar
  polargs train my_scene/ --out runs/polar --preset cpu --iters 3000
  polargs train my_scene/ --out runs/polar --resume --iters 6000
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train the reference Gaussian Splatting backend (with or without PolarGS)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset folder, or synthetic:NAME for a bundled scene")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="folder for the checkpoint and summary.json")
    p.add_argument(
        "--preset",
        choices=("cpu", "paper"),
        default="cpu",
        help="cpu: every schedule x0.02 (600 iterations, SH degree 1, <= 6000 Gaussians, no opacity "
        "reset) for a CPU in minutes; paper: vanilla 3DGS (30k iterations, SH degree 3, no cap), "
        "for a GPU (default: cpu)",
    )
    p.add_argument("--iters", type=int, default=None, metavar="N", help="number of iterations (default: the preset's)")
    p.add_argument(
        "--polar",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="use the PolarGS hooks (--no-polar: plain 3DGS, the ablation baseline; "
        "default: PolarGS when polargs_plugin.hooks is available)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed; equal seeds give identical runs (default 0)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt")
    p.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda (default: cuda if available)")
    p.add_argument(
        "--checkpoint-every", type=int, default=0, metavar="N", help="also save a checkpoint every N iterations"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def load_dataset(spec: str) -> list:
    """Views of ``spec``: a dataset folder (format detected) or ``synthetic:NAME``."""
    if spec.startswith("synthetic:"):
        from polargs_plugin.data.synthetic import SCENE_NAMES, generate_scene

        name = spec.split(":", 1)[1]
        if name not in SCENE_NAMES:
            raise PolarInputError(spec, f"unknown synthetic scene '{name}' (known: {', '.join(SCENE_NAMES)})")
        return generate_scene(name, num_views=24, width=128, height=128).views
    path = Path(spec)
    if not path.exists():
        raise PolarInputError(path, "dataset not found")
    try:
        from polargs_plugin.data.registry import load_views
    except ModuleNotFoundError as err:
        if err.name != "polargs_plugin.data.registry":
            raise
        from polargs_plugin.data.scene_format import read_scene_folder

        return read_scene_folder(path)
    return load_views(path)


def _make_hooks(polar: bool | None, preset: str, factor: float):
    """PolarHooks for ``--polar`` (required) or the default (when importable); None otherwise."""
    if polar is False:
        return None
    try:
        from polargs_plugin.config import PolarConfig
        from polargs_plugin.hooks import PolarHooks
    except ImportError as err:
        if polar:
            raise SystemExit(f"error: --polar needs polargs_plugin.hooks, which cannot be imported ({err})")
        print(f"note: PolarGS hooks unavailable ({err}); training plain 3DGS", file=sys.stderr)
        return None
    config = PolarConfig.cpu_demo(factor) if preset == "cpu" else PolarConfig.synthetic()
    return PolarHooks(config)


def run(args: argparse.Namespace) -> int:
    import torch

    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer

    out = Path(args.out)
    checkpoint = out / CHECKPOINT_NAME
    if checkpoint.exists() and not args.resume:
        print(f"error: {checkpoint} exists; pass --resume to continue it or choose another --out", file=sys.stderr)
        return 2
    if args.resume and not checkpoint.exists():
        print(f"error: --resume given but {checkpoint} does not exist", file=sys.stderr)
        return 2
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    config = TrainConfig.cpu() if args.preset == "cpu" else TrainConfig.paper()
    overrides = {"seed": args.seed, "device": device, "progress": not args.quiet}
    if args.iters is not None:
        if args.iters < 1:
            print("error: --iters must be >= 1", file=sys.stderr)
            return 2
        overrides["iterations"] = args.iters
    config = TrainConfig.from_dict({**config.to_dict(), **overrides})
    try:
        views = load_dataset(args.dataset)
        hooks = _make_hooks(args.polar, args.preset, config.schedule_scale)
        trainer = Trainer(views, config, hooks=hooks)
        if args.resume:
            trainer.load_checkpoint(checkpoint)
        start = time.perf_counter()
        figures = trainer.train(checkpoint=checkpoint, checkpoint_every=args.checkpoint_every)
    except PolarInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    summary = {
        "dataset": args.dataset,
        "num_views": len(views),
        "polar": hooks is not None,
        "preset": args.preset,
        "resumed": bool(args.resume),
        "checkpoint": str(checkpoint),
        "wall_seconds": time.perf_counter() - start,
        **figures,
        "config": config.to_dict(),
    }
    with atomic_write(out / SUMMARY_NAME) as f:
        json.dump(summary, f, indent=2)
    print(
        f"done: {figures['iterations']} iterations, {figures['num_gaussians']} Gaussians, "
        f"training-view PSNR {figures['psnr']:.2f} dB, {figures['seconds']:.0f} s -> {out}"
    )
    return 0
