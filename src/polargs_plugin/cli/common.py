"""What the ``polargs`` commands share: the dataset reader's options and one error style.

Every ordinary error of a command is one line ``error: FILE: problem`` on stderr with exit status
2 (docs/cli.md): commands raise :class:`~polargs_plugin.io.PolarInputError`, and ``polargs``'s
``main`` prints it.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import signal
import sys
from typing import Callable, Iterator

from polargs_plugin.cli.argtypes import positive_int
from polargs_plugin.service.data import PATTERNS, ReaderOptions

__all__ = ["add_reader_options", "reader_options", "print_error", "on_stop_signals", "command_line_of", "EXIT_BAD_INPUT"]

#: Exit status of an ordinary error (bad input, a missing file, a refused setting).
EXIT_BAD_INPUT = 2


def command_line_of(args: argparse.Namespace, name: str) -> str:
    """The command line as the user typed it (``polargs NAME ...``; ``polargs NAME`` when the
    command was called from Python without one), for provenance and locks."""
    return shlex.join(["polargs", *(getattr(args, "_argv", None) or [name])])


def _bit_depth(text: str) -> int:
    value = positive_int(text)
    if not 1 <= value <= 16:
        raise argparse.ArgumentTypeError(f"must be between 1 and 16, got {text}")
    return value


def _resolution(text: str) -> int:
    from polargs_plugin.data.resolution import check_resolution

    try:
        return check_resolution(int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be 1, 2, 4 or 8 (divide the image size) or a target width above 8 pixels, got {text!r}") from None


def add_reader_options(p: argparse.ArgumentParser) -> None:
    """The dataset reader's options (--format, --pattern, --no-pattern-check, --bit-depth, --sfm,
    --resolution), shared by every command that reads data."""
    g = p.add_argument_group("reading the dataset")
    g.add_argument("-r", "--resolution", type=_resolution, default=1, metavar="R",
                   help="read the images at 1/R of their size (R = 1, 2, 4 or 8) or at a width of R pixels (R above "
                   "8), as the upstream trainers' -r: Stokes area-averaged, masks sampled at the new pixel centres, "
                   "K scaled with them; recorded in the run (default 1: full size)")
    g.add_argument("--format", default="auto", metavar="FMT",
                   help="dataset format: auto (detect, default), polargs, neisf, pandora, nersp, polar")
    g.add_argument("--pattern", choices=PATTERNS, default=None,
                   help="raw mosaics (a polar folder's raw/): mono (IMX250MZR), rgb (IMX250MYR) or auto (told from "
                   "the frames; default). A given pattern is checked against every frame: a mono frame read as "
                   "rgb is an error")
    g.add_argument("--no-pattern-check", action="store_true",
                   help="do not check --pattern against the frames (a colour frame of a grey, white-balanced scene "
                   "looks mono)")
    g.add_argument("--bit-depth", type=_bit_depth, default=None, metavar="BITS",
                   help="significant bits of integer images, e.g. 12 for 12-bit data in 16-bit files "
                   "(default: the file's dtype, 8 or 16)")
    g.add_argument("--sfm", action=argparse.BooleanOptionalAction, default=False,
                   help="a polar folder without a COLMAP model: run SfM (pycolmap, the sfm extra) and write "
                   "sparse/0; needs at least 3 overlapping views (default: --no-sfm, a missing model is an error)")


def reader_options(args: argparse.Namespace) -> ReaderOptions:
    """The reader options of parsed arguments (see :func:`add_reader_options`)."""
    return ReaderOptions(fmt=args.format or "auto", pattern=args.pattern, bit_depth=args.bit_depth, sfm=bool(args.sfm),
                         check_pattern=not args.no_pattern_check, resolution=getattr(args, "resolution", 1))


def print_error(message: str) -> int:
    """Print ``error: message`` on stderr; returns :data:`EXIT_BAD_INPUT`."""
    print(f"error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


@contextlib.contextmanager
def on_stop_signals(handler: Callable[[int], None]) -> Iterator[None]:
    """Call ``handler(signum)`` on SIGINT and SIGTERM while the block runs (in the main thread;
    elsewhere signals cannot be handled and nothing changes); the previous handlers come back after."""
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(ValueError, OSError):  # not the main thread
            previous[signum] = signal.signal(signum, lambda number, frame: handler(number))
    try:
        yield
    finally:
        for signum, old in previous.items():
            with contextlib.suppress(ValueError, OSError):
                signal.signal(signum, old)
