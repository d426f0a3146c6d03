"""``polargs demo``: the newcomer's main command. Base and Full on one bundled scene, end to end
(generate or reuse the scene, train, mesh, evaluate, report), with the ablation machinery."""

from __future__ import annotations

import argparse
from pathlib import Path

_DESCRIPTION = """\
Generate the bundled scene (or reuse it from OUT/scenes), train Base (plain 3DGS) and Full
(PolarGS: PC + Dense + L_n + L_dn + L_scale) with the reference backend at the CPU preset, extract
TSDF meshes, evaluate them against the ground truth (Chamfer, normal MAE), and write OUT/report.md
with pictures. Prints the table and the report's path. Running it again reuses finished runs.

It is `polargs ablate` with two variants and one seed (docs/ablation.md); the same options apply.
The reader options (--pattern, --bit-depth, --sfm, --no-pattern-check) are for dataset folders
(polargs ablate, polargs train): with a bundled scene they are an error, as for `polargs train
synthetic:NAME`; --format is ignored.

Examples:
  polargs demo                                    # out/demo/report.md
  polargs demo --scene shiny_torus --out out/torus
  polargs demo --views 6 --size 32x32 --factor 0.002 --eval-samples 20000   # a smoke run in seconds
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from polargs_plugin.cli.ablate import add_run_options

    p = subparsers.add_parser(
        "demo",
        help="train Base and Full on a bundled scene, mesh, evaluate, write a report",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), metavar="DIR", help="output folder (default out/demo)")
    p.add_argument("--scene", default="glossy_plane_sphere", help="bundled scene, or family:K, a scene of the procedural family (default glossy_plane_sphere)")
    p.add_argument("--variants", default="base,full", metavar="V,...", help="variants to train (default base,full)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    add_run_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.ablation.scenes import bundled_names
    from polargs_plugin.ablation.variants import parse_variants
    from polargs_plugin.cli.ablate import build_cells, command_line, execute
    from polargs_plugin.data.family import FAMILY, parse_family
    from polargs_plugin.io import PolarInputError

    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise PolarInputError(out, "exists and is not a folder")
    if args.scene not in bundled_names() and parse_family(args.scene) is None:
        raise PolarInputError("--scene", f"unknown scene '{args.scene}' (known: {', '.join(bundled_names())}, {FAMILY}:K)")
    try:
        variants = parse_variants(args.variants)
    except ValueError as err:
        raise PolarInputError("--variants", str(err)) from None
    cells = build_cells(args, [args.scene], variants, [args.seed])
    extra = ["--scene", args.scene] + (["--variants", ",".join(variants)] if variants != ["base", "full"] else []) + (
        ["--seed", str(args.seed)] if args.seed else [])
    return execute(args, cells, command_line("demo", args, extra))
