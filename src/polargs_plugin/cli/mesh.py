"""``polargs mesh``: TSDF-fuse the depth maps a trained run renders for its training views."""

from __future__ import annotations

import argparse
from pathlib import Path

from polargs_plugin.cli.argtypes import factor_at_least_one, unit_fraction
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.mesh import MeshSettings, mesh_run
from polargs_plugin.service.runs import MESH_NAME, load_run

_EPILOG = """examples:
  polargs mesh runs/sphere                       # synthetic preset, writes runs/sphere/tsdf_mesh.ply
  polargs mesh runs/dtu24 --preset paper         # voxel 0.008, SDF truncation 0.04, depth truncation 10
  polargs mesh runs/sphere --voxel 0.004 --depth expected --out sphere_fine.ply
  polargs mesh runs/sphere --data /new/place/scenes/sphere   # the run's dataset moved since training

Presets (scene units): paper = 0.008 / 0.04 / 10 (PolarGS); synthetic = 1/128 / 4/128 / 6 for
objects of radius ~1 seen from distance ~3 at 128 px. --voxel alone keeps the preset's
truncation-to-voxel ratio. See docs/evaluation.md.
"""


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
    parser.add_argument("--alpha-threshold", type=unit_fraction, default=MeshSettings.alpha_threshold,
                        help=f"ignore pixels with opacity below this (default {MeshSettings.alpha_threshold:g}; 0 disables), "
                        "except the partly transparent ones inside the masks (--partial-alpha)")
    parser.add_argument("--partial-alpha", type=unit_fraction, default=MeshSettings.partial_alpha, metavar="ALPHA",
                        help="inside the masks, fuse the expected depth of pixels with opacity from ALPHA up to "
                        f"--alpha-threshold (default {MeshSettings.partial_alpha:g}; --alpha-threshold's value disables): "
                        "keeps the surface that views see only at grazing angles")
    parser.add_argument("--no-masks", action="store_true", help="do not restrict fusion to the views' object masks")
    parser.add_argument("--min-cluster", type=float, default=0.05, metavar="FRACTION",
                        help="drop connected pieces with fewer triangles than FRACTION of the largest "
                        "(default 0.05; 1 keeps only the largest, 0 keeps all)")
    parser.add_argument("--spare-pieces-in-masks", action="store_true",
                        help="keep the small pieces of --min-cluster that lie inside every view's mask "
                        "(a floater sticks out of some silhouette); default: drop by size alone")
    parser.add_argument("--incidence-trunc", type=factor_at_least_one, default=MeshSettings.incidence_trunc, metavar="FACTOR",
                        help="widen each pixel's SDF truncation by 1/cos of its incidence angle, up to FACTOR "
                        f"(default {MeshSettings.incidence_trunc:g}; 1 disables): closes holes where views see "
                        "the surface at grazing angles")
    parser.add_argument("--out", type=Path, help=f"output mesh (default RUN_DIR/{MESH_NAME})")
    parser.add_argument("--data", metavar="NEW_PATH", default=None,
                        help="the run's dataset, moved since training (checked against the run's fingerprint.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> MeshSettings:
    """The :class:`MeshSettings` of parsed ``polargs mesh`` options."""
    return MeshSettings(preset=args.preset, voxel=args.voxel, sdf_trunc=args.sdf_trunc, depth_trunc=args.depth_trunc,
                        depth=args.depth, alpha_threshold=args.alpha_threshold, partial_alpha=args.partial_alpha,
                        masks=not args.no_masks,
                        min_cluster=args.min_cluster, spare_pieces_in_masks=args.spare_pieces_in_masks,
                        incidence_trunc=args.incidence_trunc)


def run(args: argparse.Namespace) -> int:
    """Render, fuse, write the mesh and a JSON sidecar with the settings used; print one line."""
    settings = settings_from_args(args)
    settings.tsdf(str(args.run_dir))  # bad settings are refused before a dataset is read
    if not args.run_dir.is_dir():
        raise PolarInputError(args.run_dir, "run folder not found")
    result, path = mesh_run(load_run(args.run_dir, args.data), settings, args.out, progress=not args.quiet)
    info = result.info
    print(
        f"mesh: {path} ({info['vertices']} vertices, {info['triangles']} triangles) from {info['views']} views; "
        f"voxel {info['voxel_size']:.4g}, SDF truncation {info['sdf_trunc']:.4g}, "
        f"depth truncation {info['depth_trunc']:.4g} (scene units); {result.seconds:.1f} s"
    )
    return 0
