"""The ``polargs`` command. Each subcommand lives in its own module ``cli/<name>.py`` exposing
``register(subparsers)``; this file only dispatches.

Start-up is kept light: only the module of the subcommand being run is imported (``polargs
--help`` imports none: the one-line summaries are listed here), and the threading policy's
environment (:mod:`polargs_plugin.threads`) is set before torch or numba are loaded, so numba never
tries (and warns about) an unusable TBB threading layer in the middle of a progress bar.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

# Subcommand modules, in the order `polargs --help` lists them, with their one-line summaries
# (each module's register() passes the same text as help=; tests/test_cli_faults.py checks it).
_COMMANDS: dict[str, str] = {
    "demo": "train Base and Full on a bundled scene, mesh, evaluate, write a report",
    "generate": "render a synthetic polarimetric scene with ground truth",
    "preprocess": "compute, cache and draw the photometric-correction maps of a dataset",
    "check": "check a dataset's AoLP direction on its silhouettes (and its Stokes scale)",
    "train": "train the reference Gaussian Splatting backend (with or without PolarGS)",
    "mesh": "extract a mesh from a trained run by TSDF fusion",
    "eval": "Chamfer distance, F-score and normal MAE of a run or mesh",
    "ablate": "run the ablation grid (scenes x variants x seeds) and write a report",
    "dryrun": "run a patched upstream train.py on the CPU for a few hundred iterations and check it",
}

_DESCRIPTION = (
    "PolarGS polarization cues for 3D Gaussian Splatting: generate synthetic polarimetric scenes, "
    "preprocess captures, train the reference backend, mesh and evaluate, run the ablation "
    "(polargs demo, polargs ablate). `polargs COMMAND --help` describes each command; docs/cli.md "
    "all of them."
)


def _register(sub: argparse._SubParsersAction, name: str) -> bool:
    """Register the real parser of ``name``; False when the module is not part of this build."""
    try:
        module = importlib.import_module(f"polargs_plugin.cli.{name}")
    except ModuleNotFoundError as err:
        if err.name == f"polargs_plugin.cli.{name}":
            return False  # subcommand not part of this build yet
        raise
    module.register(sub)
    return True


def build_parser(command: str | None = None, lazy: bool = False) -> argparse.ArgumentParser:
    """The ``polargs`` parser.

    Args:
        command: with ``lazy``, the one subcommand whose module is imported and registered in
            full; the others get a placeholder with their summary (enough for ``--help``).
        lazy: False (default) registers every subcommand in full.
    """
    parser = argparse.ArgumentParser(prog="polargs", description=_DESCRIPTION)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in _COMMANDS.items():
        if lazy and name != command:
            sub.add_parser(name, help=summary, add_help=False)
        else:
            _register(sub, name)
    return parser


def _command_of(argv: list[str]) -> str | None:
    """The subcommand named in ``argv`` (the first word that is not an option), if known."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in _COMMANDS else None
    return None


def _prepare_process() -> None:
    """Thread policy environment before torch / numba load; numba's TBB warning filtered."""
    from polargs_plugin.threads import ThreadPolicy

    if "torch" not in sys.modules:  # in time for torch's and numba's runtimes (not when embedded)
        ThreadPolicy().apply_environment(override=False)  # the user's environment wins
    # numba warns once that the system TBB is too old when it probes the "default" layer (only
    # if someone chooses it): the layer falls back to omp/workqueue, the text would split the bar.
    warnings.filterwarnings("ignore", message=r"The TBB threading layer requires TBB version")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    _prepare_process()
    command = _command_of(argv)
    parser = build_parser(command, lazy=True)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args._argv = argv  # the command line as given (for "resume with: ..." messages)
    from polargs_plugin.io import PolarInputError

    try:
        return int(args.func(args) or 0)
    except PolarInputError as err:  # an ordinary error: one line, no traceback (docs/cli.md)
        from polargs_plugin.cli.common import print_error

        return print_error(str(err))


if __name__ == "__main__":
    sys.exit(main())
