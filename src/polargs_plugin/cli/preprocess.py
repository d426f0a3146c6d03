"""``polargs preprocess``: compute and cache the PC maps of a dataset and draw them."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torch import Tensor

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

_SPECULAR_TINT = (1.0, 0.0, 1.0)
_OVEREXPOSED_TINT = (0.0, 1.0, 1.0)


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
    from polargs_plugin.cli.train import PRESETS, add_reader_options

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


def _load_config(path: Path | None, preset: str = "synthetic"):
    """The PolarConfig of ``preset`` with the settings of ``path`` (either layout)."""
    import json

    from polargs_plugin.cli.train import load_config_file, polar_config
    from polargs_plugin.io import PolarInputError

    if path is None:
        return polar_config(preset, None, {}, "settings")
    try:
        data = json.loads(Path(path).read_text())
    except OSError as err:
        raise PolarInputError(path, f"cannot read the settings file ({err.strerror or err})") from None
    except ValueError as err:
        raise PolarInputError(path, f"not valid JSON ({err})") from None
    if isinstance(data, dict) and data and set(data) <= {"polar", "train"}:
        overrides, _ = load_config_file(path)
    elif isinstance(data, dict):
        overrides = data  # a bare PolarConfig
    else:
        raise PolarInputError(path, 'expected {"polar": {...}, "train": {...}} or a PolarConfig object')
    return polar_config(preset, None, overrides, str(path))


def _overlay(image: "Tensor", masks: list) -> "Tensor":
    import torch

    out = image.clamp(0, 1).clone()
    for mask, tint in masks:
        colour = torch.tensor(tint, dtype=out.dtype)[:, None, None]
        out = torch.where(mask, 0.4 * out + 0.6 * colour, out)
    return out


def save_map_pictures(maps, out_dir: Path, prefix: str) -> list[Path]:
    """Write the pictures of one view's :class:`~polargs_plugin.types.PolarMaps` (see the epilog).

    Args:
        maps: the view's maps (masks and CRMs may be ``None`` when PC is disabled).
        out_dir: folder to write into.
        prefix: file name prefix (the view name).

    Returns:
        The paths written.
    """
    import torch
    from torch import Tensor

    from polargs_plugin.viz import aolp_to_rgb, dolp_to_rgb, save_png

    maps_cpu = {name: value.detach().cpu().float() for name, value in vars(maps).items() if isinstance(value, Tensor)}
    pictures = {
        "aolp": aolp_to_rgb(maps_cpu["aolp"], maps_cpu["dolp"].clamp(0, 1), "dark"),
        "dolp": dolp_to_rgb(maps_cpu["dolp"]),
    }
    if maps.specular_mask is not None:
        specular = maps.specular_mask.cpu()
        chro = (maps.overexposed_mask & maps.extras["i_chro_valid"]).cpu()
        image = maps_cpu["intensity"]
        pictures["masks"] = _overlay(image, [(specular, _SPECULAR_TINT), (maps.overexposed_mask.cpu(), _OVEREXPOSED_TINT)])
        pictures["i_diff"] = maps_cpu["i_diff"]
        pictures["i_chro"] = maps_cpu["i_chro"]
        pictures["target"] = torch.where(specular, maps_cpu["i_diff"], torch.where(chro, maps_cpu["i_chro"], image))
        pictures["pri"] = maps_cpu["pri"]
    return [save_png(out_dir / f"{prefix}_{name}.png", picture.clamp(0, 1)) for name, picture in pictures.items()]


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.cli.train import MAPS_NAME, PREPROCESSED_NAME, _maps_entries, load_dataset, reader_kwargs
    from polargs_plugin.io import PolarInputError, check_writable

    out = args.out if args.out is not None else args.dataset / PREPROCESSED_NAME
    created = not out.exists()
    try:
        config = _load_config(args.config, args.preset)
        config.densify.enabled = False  # preprocessing only: no densifier to build
        cache = out / MAPS_NAME
        config.cache_dir = str(cache)
        info: dict = {}
        views = load_dataset(str(args.dataset), args.format, info, **reader_kwargs(args))
        if not views:
            raise PolarInputError(args.dataset, "the dataset holds no views")
        if info.get("pattern"):
            print(f"raw mosaics: {info['pattern']}" + (" (told from the frames)" if args.pattern in (None, "auto") else ""))
        if info.get("sfm"):
            print(f"SfM: model written to {info.get('model')}")
        check_writable(out)
        from polargs_plugin.hooks import PolarHooks

        reused = sum(path.is_file() for path in _maps_entries(views, config, cache).values())
        maps = PolarHooks(config).preprocess(views)
    except PolarInputError as err:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"error: {err.filename or out}: {err.strerror or err}", file=sys.stderr)
        return 2
    print(f"maps: reused {reused} of {len(views)} views from {cache}" if reused else f"maps: computed {len(views)} views")
    for view, view_maps in zip(views, maps):
        line = f"{view.name}: {view.width}x{view.height}"
        if view_maps.specular_mask is not None:
            pixels = view.width * view.height
            over = int(view_maps.overexposed_mask.sum())
            filled = int(view_maps.extras["i_chro_valid"].sum())
            line += (
                f", specular {int(view_maps.specular_mask.sum()) / pixels:.1%}, overexposed {over / pixels:.1%}"
                f" (I_chro found for {filled}/{over})"
            )
        if not args.no_pictures:
            save_map_pictures(view_maps, out / "pictures", view.name)
        print(line)
    print(f"maps cached in {cache}" + ("" if args.no_pictures else f", pictures in {out / 'pictures'}"))
    return 0
