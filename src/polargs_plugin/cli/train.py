"""``polargs train``: train the bundled reference 3D Gaussian Splatting backend on a dataset.

This module parses the options and prints; :func:`polargs_plugin.service.train.train_run` does the
work and owns the run folder (docs/cli.md). Every error is one line ``error: FILE: problem`` on
stderr (exit status 2); Ctrl-C / SIGTERM stop after the current iteration with a final checkpoint
(exit status 130 / 143).
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from polargs_plugin.cli.argtypes import non_negative_int, positive_float, positive_int
from polargs_plugin.cli.common import add_reader_options, command_line_of, on_stop_signals, print_error, reader_options
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.configs import PRESETS, SCHEDULES, SWITCHES

if TYPE_CHECKING:
    from polargs_plugin.service.train import StopRequest, TrainRequest


_DESCRIPTION = """\
Train 3D Gaussians on a polarimetric dataset with the bundled reference trainer (vanilla 3D
Gaussian Splatting on the s0/2 colour images), optionally with the PolarGS hooks (reflection-aware
colour losses and polar-guided PatchMatch densification).

DATASET is a dataset folder in any supported format (detected automatically), or
synthetic:NAME to render one of the bundled synthetic scenes on the fly (24 views, 128x128).

Two independent choices:
  --schedule cpu|paper   how long and how big the TRAINING is: cpu = the vanilla schedule x1/6
                         (5000 iterations, SH degree 1, <= 6000 Gaussians from density control,
                         no opacity reset) for a CPU in minutes, with PolarGS' own schedules x1/2
                         (Dense 500-3500 every 50, L_dn from 3500; --factor F: x F and x min(1, 3F));
                         paper = vanilla 3DGS (30k iterations, SH degree 3, no cap), for a GPU.
  --preset synthetic|real  the paper's PolarGS VALUES for synthetic data (lambda1 = 0.02, alpha =
                         0.2, perspective azimuth model) or for real captures (lambda1 = 0.2,
                         alpha = 0.1, orthographic).
Then --config FILE.json ({"polar": {...}, "train": {...}}: any PolarConfig / TrainConfig field,
nested as in summary.json) and the --no-* switches are applied, in that order.

Run folder RUN_DIR: checkpoint.pt (every 10 % of the run and at the end; --resume continues it),
fingerprint.json (cameras + image content of the data, checked on --resume), maps/ (the PolarGS
maps cache: maps that `polargs preprocess DATASET` left in DATASET/preprocessed/maps, or that a
previous run left here, are reused), summary.json (every setting incl. the full PolarConfig, and
the final figures: training-view PSNR, number of Gaussians, time), train.lock while it runs.
Ctrl-C (or SIGTERM) stops after the current iteration, writes the checkpoint and prints the
command that resumes. See docs/cli.md.

Examples:
  polargs train synthetic:glossy_plane_sphere --out runs/base --no-polar
  polargs train my_scene/ --out runs/polar --preset real --iters 3000
  polargs train captures/ --out runs/raw --preset real --pattern auto --bit-depth 12 --sfm
  polargs train my_scene/ --out runs/nodense --no-dense --config polar.json
  polargs train my_scene/ --out runs/polar --resume --iters 6000
  polargs train captures/ --out runs/half --sfm --pattern auto --resolution 2   # raw 2448x2048 frames at 1224x1024

Before training the command prints the estimated peak memory and time (docs/real-size.md) and
refuses a run whose peak is beyond the memory left, naming the --resolution that fits.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train the reference Gaussian Splatting backend (with or without PolarGS)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset folder, or synthetic:NAME for a bundled scene")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder (see above)")
    p.add_argument("--schedule", choices=SCHEDULES, default=None,
                   help="training schedule: cpu (5000 iterations, minutes on a CPU) or paper (30k, a GPU) (default cpu)")
    p.add_argument("--preset", choices=PRESETS + SCHEDULES, default=None, metavar="{synthetic,real}",
                   help="PolarGS values of the paper for synthetic data or real captures (default synthetic); "
                   "the old --preset cpu|paper still selects the schedule, with a note")
    p.add_argument("--factor", type=positive_float, default=None, metavar="F",
                   help="vanilla schedule factor of --schedule cpu (default 1/6: 5000 iterations; the PolarGS "
                        "schedules get min(1, 3F): Dense 500-3500 every 50, L_dn from 3500)")
    p.add_argument("--iters", type=positive_int, default=None, metavar="N", help="number of iterations (default: the schedule's)")
    p.add_argument("--polar", action=argparse.BooleanOptionalAction, default=True,
                   help="use the PolarGS hooks (default; --no-polar: plain 3DGS, the ablation baseline)")
    g = p.add_argument_group("PolarGS ablation switches (applied after --preset and --config)")
    g.add_argument("--no-pc", action="store_true", help="no photometric correction (module PC; PolarConfig.correction.enabled)")
    g.add_argument("--no-dense", action="store_true", help="no polar PatchMatch densification (module Dense; densify.enabled)")
    g.add_argument("--no-ref-loss", action="store_true", help="no reflection-aware colour loss L_ref (losses.use_ref)")
    g.add_argument("--no-normal-loss", action="store_true", help="no normal loss L_n (losses.use_normal)")
    g.add_argument("--no-depth-normal-loss", action="store_true", help="no depth-normal loss L_dn (losses.use_depth_normal)")
    g.add_argument("--no-scale-loss", action="store_true", help="no flatness loss L_scale (losses.use_scale)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                   help='settings file {"polar": {...}, "train": {...}}: any PolarConfig / TrainConfig field, nested '
                   "(e.g. {\"train\": {\"density\": {\"max_gaussians\": 3000}}}); unknown keys are an error")
    p.add_argument("--maps-cache", type=Path, default=None, metavar="DIR",
                   help="PolarGS maps cache (a folder of maps, or a `polargs preprocess --out` folder holding maps/); "
                   "default RUN_DIR/maps, seeded from DATASET/preprocessed/maps when that exists")
    p.add_argument("--seed", type=int, default=0, help="random seed; equal seeds give identical runs (default 0)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt (same data: checked)")
    p.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda (default: cuda if available)")
    p.add_argument(
        "--checkpoint-every", type=non_negative_int, default=None, metavar="N",
        help="save the checkpoint every N iterations (default: every 10 %% of the run; 0: only at the end)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-memory-check", action="store_true",
                   help="train even when the estimated peak memory is beyond what the machine has left (the estimate "
                   "is printed before training; by default such a run is refused, naming --resolution)")
    add_reader_options(p)
    p.set_defaults(func=run)



# ------------------------------------------------------------------------------ run
def _request(args: argparse.Namespace) -> TrainRequest:
    """The training request of the options: settings first, so that a typo costs nothing."""
    from polargs_plugin.service.configs import polar_config, read_settings, resolve_device, train_config
    from polargs_plugin.service.train import TrainRequest

    schedule, preset = args.schedule, args.preset
    if preset in SCHEDULES:  # the old meaning of --preset
        if schedule is not None and schedule != preset:
            raise PolarInputError(f"--preset {preset}", f"the old name of --schedule {preset}, which contradicts --schedule {schedule}")
        print(f"note: --preset {preset} is now --schedule {preset} (--preset chooses the PolarGS values: synthetic or real)",
              file=sys.stderr)
        schedule, preset = preset, None
    schedule, preset = schedule or "cpu", preset or "synthetic"
    switches = [name for name in SWITCHES if getattr(args, name, False)]
    flags = [f"--{name.replace('_', '-')}" for name in switches]
    if not args.polar and flags:
        raise PolarInputError(", ".join(flags), "switches of the PolarGS hooks, which --no-polar turns off")
    if args.factor is not None and schedule != "cpu":
        raise PolarInputError("--factor", "scales the cpu schedule only (drop it, or use --schedule cpu)")
    settings = read_settings(args.config)
    fields: dict[str, Any] = {"seed": args.seed, "device": resolve_device(args.device), "progress": not args.quiet}
    if args.iters is not None:
        fields["iterations"] = args.iters
    train = train_config(schedule, args.factor if schedule == "cpu" else None, settings.train, settings.source, **fields)
    factor = train.schedule_scale if schedule == "cpu" else None
    polar = polar_config(preset, factor, settings.polar, settings.source, switches) if args.polar else None
    if polar is None and settings.polar:
        raise PolarInputError(settings.source, "has \"polar\" settings but --no-polar trains without the PolarGS hooks")
    return TrainRequest(
        dataset=args.dataset, out=Path(args.out), train=train, polar=polar, reader=reader_options(args),
        maps_cache=args.maps_cache, resume=args.resume, checkpoint_every=args.checkpoint_every,
        command=command_line_of(args, "train"), memory_check=not args.no_memory_check,
        labels={"schedule": schedule, "preset": preset, "switches": flags,
                "config_file": None if args.config is None else str(args.config)},
    )


def _resume_command(args: argparse.Namespace) -> str:
    argv = [a for a in getattr(args, "_argv", None) or [] if a != "--resume"]
    if not argv or argv[0] != "train":
        argv = ["train", args.dataset, "--out", str(args.out)]
    return shlex.join(["polargs", *argv, "--resume"])


def _note(line: str) -> None:
    print(line, file=sys.stderr if line.startswith("note:") else sys.stdout, flush=True)


@contextlib.contextmanager
def _stop_on_signals(stop: StopRequest):
    """SIGINT / SIGTERM ask ``stop`` to end the training (after this iteration; a second: at once)."""
    def handler(signum: int) -> None:
        stop.request(signum)  # raises KeyboardInterrupt when it stops at once
        print(f"\n{signal.Signals(signum).name}: stopping after this iteration (again to stop at once)",
              file=sys.stderr, flush=True)

    with on_stop_signals(handler):
        yield stop


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.backends.reference.trainer import TrainingDiverged
    from polargs_plugin.service.train import StopRequest, TrainingInterrupted, train_run

    try:
        request = _request(args)
        with _stop_on_signals(StopRequest()) as stop:
            result = train_run(request, notify=_note, stop=stop)
    except TrainingInterrupted as stopped:
        print(stopped.message(_resume_command(args)), file=sys.stderr)
        return stopped.status
    except TrainingDiverged as err:  # the last periodic checkpoint (if any) predates the bad values
        return print_error(f"{args.out}: training stopped: {err}")
    except PolarInputError as err:
        return print_error(str(err))
    except OSError as err:
        return print_error(f"{err.filename or args.out}: {err.strerror or err}")
    figures = result.summary
    print(
        f"done: {figures['iterations']} iterations, {figures['num_gaussians']} Gaussians, "
        f"training-view PSNR {figures['psnr']:.2f} dB, {figures['seconds']:.0f} s -> {result.run_dir}"
    )
    return 0
