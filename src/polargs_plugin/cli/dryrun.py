"""``polargs dryrun``: train a patched upstream trainer on the CPU for a few hundred iterations."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from polargs_plugin.cli.argtypes import positive_int
from polargs_plugin.cli.common import command_line_of

_SUMMARY = "run a patched upstream train.py on the CPU for a few hundred iterations and check it"

_EPILOG = """examples:
  python adapters/gof/patch.py ~/src/gaussian-opacity-fields
  polargs dryrun ~/src/gaussian-opacity-fields --trainer gof
  polargs dryrun ~/src/PGSR --trainer pgsr --iters 600 --workdir out/dryrun-pgsr
  python adapters/gsplat/patch.py ~/src/gsplat/examples
  polargs dryrun ~/src/gsplat/examples --trainer gsplat-mcmc

The trainer's CUDA extensions are replaced by CPU stand-ins and its CUDA requests go to the CPU,
in the dry run's own processes only: nothing is written into the checkout. The trainer reads a
small bundled scene exported as COLMAP input; its schedule is shrunk through its own arguments
(iterations, densification interval and window, checkpoint) and Dense's through POLARGS_CONFIG.
Arguments after -- go to train.py after the dry run's own. Modules the trainer imports that this
Python lacks are named before anything runs, all in one line with the command that installs them
(pytorch3d.transforms is served where pytorch3d is missing). One line per check, then the exit
status: 0 all passed, 1 a check failed, 2 an input error. See docs/adapters/dryrun.md.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``dryrun`` subcommand."""
    from polargs_plugin.dryrun.trainers import TRAINERS

    parser = subparsers.add_parser(
        "dryrun", help=_SUMMARY, epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run a patched upstream trainer's own train.py on the CPU, patched and unpatched, "
        "for a few hundred iterations on a small scene, and check that it finished, that the loss "
        "stayed finite, that Dense's Gaussians survived the trainer's densification with every "
        "per-Gaussian state in step, and that its checkpoint reloads.",
    )
    parser.add_argument("checkout", type=Path, metavar="CHECKOUT", help="the trainer's checkout, patched")
    parser.add_argument("--trainer", required=True, choices=sorted(TRAINERS), help="which upstream trainer it is")
    parser.add_argument("--iters", type=positive_int, default=300, help="iterations of each run (default 300)")
    parser.add_argument("--interval", type=positive_int, default=30,
                        help="iterations between densifications and between Dense calls (default 30)")
    parser.add_argument("--workdir", type=Path, help="where the scene, outputs and logs go (default: a temporary folder, kept)")
    parser.add_argument("--no-compare", action="store_true", help="skip the unpatched run (no step-time ratio)")
    parser.add_argument("train_arguments", nargs="*", metavar="-- TRAIN_ARGS", help="more train.py arguments, after --")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the dry run and print one line per check."""
    from polargs_plugin.service.dryrun import DryRunRequest, describe, dry_run

    extra = list(args.train_arguments)
    if extra[:1] == ["--"]:
        extra = extra[1:]
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="polargs-dryrun-"))
    request = DryRunRequest(checkout=args.checkout, trainer=args.trainer, workdir=workdir, iterations=args.iters,
                            interval=args.interval, train_arguments=tuple(extra), compare=not args.no_compare,
                            command=command_line_of(args, "dryrun"))
    result = dry_run(request, progress=lambda message: print(message, flush=True))
    for line in describe(result.checks):
        print(line)
    print(f"logs        {', '.join(str(p) for p in result.logs.values())}")
    print(f"summary     {workdir / 'summary.json'}")
    return 0 if result.ok else 1
