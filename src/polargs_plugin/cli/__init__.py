"""The ``polargs`` command. Each subcommand lives in its own module ``cli/<name>.py`` exposing
``register(subparsers)``; this file only dispatches."""

from __future__ import annotations

import argparse
import importlib
import sys

# Subcommand modules, in the order `polargs --help` lists them.
_COMMANDS = ("demo", "generate", "preprocess", "train", "mesh", "eval", "ablate")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="polargs",
        description="PolarGS polarization cues for 3D Gaussian Splatting: generate synthetic "
        "polarimetric scenes, preprocess captures, train the reference backend, mesh and evaluate, "
        "run the ablation (polargs demo, polargs ablate).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"polargs_plugin.cli.{name}")
        except ModuleNotFoundError as err:
            if err.name == f"polargs_plugin.cli.{name}":
                continue  # subcommand not part of this build yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
