"""``polargs mesh``: TSDF-fuse the depth maps a trained run renders for its training views."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

MESH_FILE = "tsdf_mesh.ply"

_EPILOG = """examples:
  polargs mesh runs/sphere                       # synthetic preset, writes runs/sphere/tsdf_mesh.ply
  polargs mesh runs/dtu24 --preset paper         # voxel 0.008, SDF truncation 0.04, depth truncation 10
  polargs mesh runs/sphere --voxel 0.004 --depth expected --out sphere_fine.ply

Presets (scene units): paper = 0.008 / 0.04 / 10 (PolarGS); synthetic = 1/128 / 4/128 / 6 for
objects of radius ~1 seen from distance ~3 at 128 px. --voxel alone keeps the preset's
truncation-to-voxel ratio. See docs/evaluation.md.
"""


class CommandError(SystemExit):
    """An ordinary error of ``polargs mesh`` / ``eval`` / ``check``, already printed as one
    ``error: FILE: problem`` line; exit status 2. ``str()`` is the message, so callers that
    catch it (the ablation grid) can log it."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message

    def __str__(self) -> str:
        return self.message


def fail(message: str) -> CommandError:
    """Print ``error: message`` to stderr (no traceback) and return the exception to raise."""
    print(f"error: {message}", file=sys.stderr)
    return CommandError(message)


def load_run(run_dir: Path) -> tuple[Any, list]:
    """(model, training views) of a run folder written by ``polargs train``.

    The views come from the dataset named in ``summary.json`` (re-rendered for ``synthetic:NAME``),
    the Gaussians from ``checkpoint.pt``; the checkpoint's view names must match the dataset's.
    """
    import torch

    from polargs_plugin.backends.reference.model import GaussianModel
    from polargs_plugin.backends.reference.trainer import CHECKPOINT_FORMAT
    from polargs_plugin.cli.train import CHECKPOINT_NAME, SUMMARY_NAME, load_dataset
    from polargs_plugin.io import PolarInputError

    summary_path, checkpoint_path = run_dir / SUMMARY_NAME, run_dir / CHECKPOINT_NAME
    for path in (summary_path, checkpoint_path):
        if not path.is_file():
            raise PolarInputError(path, "missing; is this a finished `polargs train` run folder?")
    try:
        summary = json.loads(summary_path.read_text())
        dataset, reader = summary["dataset"], summary.get("reader") or {}
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise PolarInputError(summary_path, f"no dataset entry ({type(err).__name__}: {err})") from err
    try:
        data = torch.load(checkpoint_path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated, not a torch file, or disallowed types
        raise PolarInputError(checkpoint_path, f"cannot read checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise PolarInputError(checkpoint_path, f"not a {CHECKPOINT_FORMAT} file")
    views = load_dataset(dataset, **reader)  # the reader options the run was trained with
    if [v.name for v in views] != data["view_names"]:
        raise PolarInputError(checkpoint_path, f"was trained on other views than those of {dataset}")
    return GaussianModel.from_checkpoint(data["model"]), views


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``mesh`` subcommand."""
    from polargs_plugin.mesh import MESH_PRESETS

    parser = subparsers.add_parser(
        "mesh",
        help="extract a mesh from a trained run by TSDF fusion",
        description="Render depth and colour of every training view of a trained run and fuse them "
        "into a triangle mesh (open3d TSDF on CPU); pixels outside the view masks or with low "
        "opacity are ignored and small disconnected pieces (floaters) are dropped.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("run_dir", type=Path, help="folder of a run written by `polargs train`")
    parser.add_argument("--preset", choices=sorted(MESH_PRESETS), default="synthetic", help="TSDF settings (default synthetic)")
    parser.add_argument("--voxel", type=float, help="voxel size (scene units), overrides the preset")
    parser.add_argument("--sdf-trunc", type=float, help="SDF truncation distance, overrides the preset")
    parser.add_argument("--depth-trunc", type=float, help="ignore depths beyond this, overrides the preset")
    parser.add_argument("--depth", choices=("median", "expected"), default="median",
                        help="rendered depth to fuse: median (transmittance 0.5 crossing, default) or alpha-normalised expected depth")
    parser.add_argument("--alpha-threshold", type=float, default=0.5, help="ignore pixels with opacity below this (default 0.5; 0 disables)")
    parser.add_argument("--no-masks", action="store_true", help="do not restrict fusion to the views' object masks")
    parser.add_argument("--min-cluster", type=float, default=0.05, metavar="FRACTION",
                        help="drop connected pieces with fewer triangles than FRACTION of the largest "
                        "(default 0.05; 1 keeps only the largest, 0 keeps all)")
    parser.add_argument("--out", type=Path, help=f"output mesh (default RUN_DIR/{MESH_FILE})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render, fuse, write the mesh and a JSON sidecar with the settings used.

    Ordinary errors are printed as one ``error: FILE: problem`` line and raise
    :class:`CommandError` (exit status 2).
    """
    from polargs_plugin.io import PolarInputError

    try:
        return _run(args)
    except PolarInputError as err:
        raise fail(str(err)) from None


def _run(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from polargs_plugin.io import PolarInputError, atomic_write
    from polargs_plugin.mesh import mesh_settings, tsdf_fuse, write_mesh

    try:
        settings = mesh_settings(args.preset, args.voxel, args.sdf_trunc, args.depth_trunc)
    except ValueError as err:
        raise PolarInputError(args.run_dir, f"bad TSDF settings: {err}") from None
    if not args.run_dir.is_dir():
        raise PolarInputError(args.run_dir, "run folder not found")
    start = time.perf_counter()
    model, views = load_run(args.run_dir)

    depths, colors, Ks, w2cs, masks, alphas = [], [], [], [], [], []
    with torch.no_grad():
        for view in tqdm(views, desc="rendering", unit="view", disable=getattr(args, "quiet", False)):
            out = model.render(view)
            depth = out.median_depth if args.depth == "median" else out.depth
            if depth is None:
                raise PolarInputError(args.run_dir, "the renderer returns no median depth; use --depth expected")
            depths.append(depth.cpu())
            colors.append(out.color.clamp(0, 1).cpu())
            alphas.append(out.alpha.cpu())
            masks.append(None if args.no_masks else view.mask)
            Ks.append(view.K)
            w2cs.append(view.world_to_camera)
    threshold = args.alpha_threshold if args.alpha_threshold > 0 else None
    mesh = tsdf_fuse(depths, colors, Ks, w2cs, masks=masks, keep_largest=args.min_cluster if args.min_cluster > 0 else False,
                     alphas=alphas, alpha_threshold=threshold, progress=not getattr(args, "quiet", False), **settings)
    if len(mesh.triangles) == 0:
        raise PolarInputError(args.run_dir, "the fused mesh is empty (check depth truncation, masks and alpha threshold)")
    out_path = args.out or args.run_dir / MESH_FILE
    try:
        write_mesh(out_path, mesh)
    except OSError as err:
        raise PolarInputError(out_path, f"cannot write the mesh ({err.strerror or err})") from None
    info = {
        "run_dir": str(args.run_dir),
        "preset": args.preset,
        **settings,
        "depth": args.depth,
        "alpha_threshold": threshold,
        "masks": not args.no_masks,
        "min_cluster_fraction": args.min_cluster,
        "views": len(views),
        "vertices": len(mesh.vertices),
        "triangles": len(mesh.triangles),
    }
    with atomic_write(out_path.with_suffix(".json")) as handle:
        json.dump(info, handle, indent=2)
    print(
        f"mesh: {out_path} ({info['vertices']} vertices, {info['triangles']} triangles) from {len(views)} views; "
        f"voxel {settings['voxel_size']:.4g}, SDF truncation {settings['sdf_trunc']:.4g}, "
        f"depth truncation {settings['depth_trunc']:.4g} (scene units); {time.perf_counter() - start:.1f} s"
    )
    return 0
