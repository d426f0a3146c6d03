"""``polargs preprocess``: compute and cache the PC maps of a dataset and draw them."""

from __future__ import annotations

import argparse
from pathlib import Path

from polargs_plugin.cli.common import add_reader_options, command_line_of, reader_options
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.configs import PRESETS

_EPILOG = """examples:
  polargs preprocess scenes/sphere                      # writes scenes/sphere/preprocessed/
  polargs preprocess data/frog --out out/frog --format nersp
  polargs preprocess captures/ --pattern auto --bit-depth 12 --sfm --preset real
  polargs preprocess scenes/sphere --config settings.json --no-pictures

Writes DIR/maps/<view>-<hash>.pt (maps keyed by the content of the Stokes images, the mask and
the correction settings: a rerun on unchanged input loads them). `polargs train DATASET` reuses
the maps of DATASET/preprocessed/maps (the default DIR); for another DIR pass
`polargs train --maps-cache DIR`, or preprocess with --out RUN_DIR, the run folder of the
training (its maps/ is the run's cache). Per view, DIR/pictures/
<view>_masks.png (specular magenta, overexposed cyan over the image), _i_diff.png, _i_chro.png,
_target.png (the colour target with I_diff / I_chro swapped in), _pri.png, _aolp.png (hue, DoLP
as brightness), _dolp.png. Images are linear, as trained on.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``preprocess`` subcommand."""
    parser = subparsers.add_parser(
        "preprocess",
        help="compute, cache and draw the photometric-correction maps of a dataset",
        description="Compute Stokes-derived AoLP/DoLP, specular and overexposed masks, PRI and the "
        "colour refinement maps I_diff / I_chro of every view, cache them keyed by input content, "
        "and write pictures.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("dataset", type=Path, help="dataset folder (any format polargs reads)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default DATASET/preprocessed)")
    parser.add_argument("--preset", choices=PRESETS, default="synthetic",
                        help="PolarGS values of the paper for synthetic data or real captures, as `polargs train --preset` "
                        "(default synthetic; the maps depend only on the correction settings, which both share)")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                        help='settings file as for `polargs train --config` ({"polar": {...}, "train": {...}}; only "polar" '
                        "is used), or a bare PolarConfig (PolarConfig.to_dict layout); unknown keys are an error")
    parser.add_argument("--no-pictures", action="store_true", help="only compute and cache the maps")
    add_reader_options(parser)
    parser.set_defaults(func=run)


def _view_line(view, view_maps) -> str:
    line = f"{view.name}: {view.width}x{view.height}"
    if view_maps.specular_mask is not None:
        pixels = view.width * view.height
        over = int(view_maps.overexposed_mask.sum())
        filled = int(view_maps.extras["i_chro_valid"].sum())
        line += (
            f", specular {int(view_maps.specular_mask.sum()) / pixels:.1%}, overexposed {over / pixels:.1%}"
            f" (I_chro found for {filled}/{over})"
        )
    return line


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.service.configs import polar_config, read_settings
    from polargs_plugin.service.data import load_dataset
    from polargs_plugin.service.maps import PREPROCESSED_NAME, preprocess

    out = args.out if args.out is not None else args.dataset / PREPROCESSED_NAME
    created = not out.exists()
    try:
        settings = read_settings(args.config, bare_polar=True)
        config = polar_config(args.preset, None, settings.polar, settings.source)
        dataset = load_dataset(str(args.dataset), reader_options(args))
        if dataset.pattern:
            told = " (told from the frames)" if args.pattern in (None, "auto") else ""
            print(f"raw mosaics: {dataset.pattern}{told}")
        if dataset.sfm_model:
            print(f"SfM: model written to {dataset.sfm_model}")
        done = preprocess(dataset.views, config, out, pictures=not args.no_pictures, command=command_line_of(args, "preprocess"))
    except (PolarInputError, OSError) as err:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        if isinstance(err, PolarInputError):
            raise
        raise PolarInputError(err.filename or out, err.strerror or str(err)) from None
    views = dataset.views
    for note in done.notes:
        print(note)
    print(done.describe())
    for view, view_maps in zip(views, done.maps):
        print(_view_line(view, view_maps))
    print(f"maps cached in {done.cache}" + ("" if done.pictures is None else f", pictures in {done.pictures}"))
    return 0
