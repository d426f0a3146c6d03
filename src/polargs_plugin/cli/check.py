"""``polargs check``: does a dataset's AoLP follow the package's convention? (silhouette check)"""

from __future__ import annotations

import argparse
import json
import math
import warnings
from pathlib import Path

from polargs_plugin.cli.common import add_reader_options, reader_options

_EPILOG = """examples:
  polargs check data/RMVP3D/shisa
  polargs check synthetic:shiny_torus --json report.json

Reads the dataset with its reader (warnings of the reader, e.g. an 8-bit picture that disagrees
with the Stokes scale or NeISF poses outside NeISF's normalisation, are printed) and compares,
along every mask edge, the AoLP with the direction of the edge: diffuse polarization is
perpendicular to the edge, specular parallel. Verdicts: consistent, rotated (constant offset),
mirrored (AoLP direction reversed: the reader's convention is wrong for this data), inconclusive.
Exit status 0 for consistent or inconclusive, 1 for mirrored or rotated, 2 for an input error.
See docs/readers.md.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``check`` subcommand."""
    parser = subparsers.add_parser(
        "check",
        help="check a dataset's AoLP direction on its silhouettes (and its Stokes scale)",
        description="Check that a dataset read by polargs follows the package's polarization "
        "conventions: the AoLP direction along the object silhouettes and, where the dataset has "
        "8-bit pictures, the Stokes scale.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (any supported format) or synthetic:NAME")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON")
    parser.add_argument("--views", action="store_true", help="print one line per view")
    add_reader_options(parser)
    parser.set_defaults(func=run)


def _line(stats) -> str:
    diffuse = "-" if math.isnan(stats.diffuse_fraction) else f"{100 * stats.diffuse_fraction:.0f} %"
    return (f"{stats.name:<16} {stats.verdict:<12} strength {stats.strength:.2f} (offset {stats.offset_deg:+.1f} deg)  "
            f"mirrored {stats.mirror_strength:.2f}  diffuse {diffuse}  {stats.samples} px")


def run(args: argparse.Namespace) -> int:
    """Load the dataset, run :func:`~polargs_plugin.data.checks.check_views`, print the verdict."""
    from polargs_plugin.data.checks import check_views
    from polargs_plugin.io import atomic_write
    from polargs_plugin.service.data import load_dataset

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        views = load_dataset(args.dataset, reader_options(args)).views
    for warning in caught:
        if issubclass(warning.category, UserWarning) and "TBB" not in str(warning.message):
            print(f"warning: {warning.message}")
    report = check_views(views)
    print(f"{args.dataset}: {len(views)} views, AoLP along the silhouettes: {report.verdict}")
    print(_line(report.overall))
    if args.views:
        for stats in report.views:
            print(_line(stats))
    for message in report.messages:
        print(f"note: {message}")
    if args.json is not None:
        with atomic_write(args.json) as handle:
            json.dump(report.to_dict(), handle, indent=2, default=lambda x: None)
    return 1 if report.verdict in ("mirrored", "rotated") else 0
