"""``polargs generate``: render a procedural polarimetric scene into a scene folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from polargs_plugin.cli.argtypes import image_size, non_negative_int, positive_int

_EPILOG = """examples:
  polargs generate --scene glossy_plane_sphere --out scenes/sphere
  polargs generate --scene bumpy_mixed --out scenes/bumpy --views 36 --size 160x120 --pictures
  polargs generate --scene shiny_torus --out out/torus --small      # 8 views of 48x48, for tests
  polargs generate --scene bumpy_mixed --out raw36 --views 36 --size 2448x2048 --mosaic rgb --bits 16 --no-cameras
  polargs generate --scene glossy_plane_sphere --out raw-sfm --views 36 --size 2448x2048 --mosaic rgb --bits 16 \
      --no-cameras --floor-texture speckle                           # raw frames SfM can register
  polargs generate --scene family:17 --out scenes/family-17        # a scene of the procedural family

--scene family:K renders the family's scene of seed K (shape, materials, lights, exposure, noise,
cameras, views and size all drawn from the seed; --views, --size and --noise override theirs), as
`polargs ablate --scenes family:K` and `polargs demo --scene family:K` spell it; `--scene family
--seed K` is the same scene.
Seeds 0-9999 and 20000-29999 are for development, 10000-19999 and from 30000 on are test seeds;
from 20000 on, seeds draw their lighting (lights, surroundings they mirror, or both) and may raise
the object on a stand (docs/scene-family.md).

The folder holds four RGB angle images per view (0/45/90/135 deg), cameras.json (K and
world_to_camera, OpenCV frame), masks, ground-truth normals/depth/diffuse/specular, highlight and
overexposure masks, the ground-truth mesh (mesh.ply) and scene.json; see docs/dataset-format.md.
With --mosaic it is a polar folder of raw sensor frames instead (docs/readers.md): what a
polarization camera records, for `polargs train FOLDER --pattern auto` (with --sfm when written
with --no-cameras); views are rendered and written one at a time, so any size fits in memory.

An existing non-empty --out is refused (scenes are never mixed); --overwrite replaces a previous
scene folder as a whole. The scene is written beside --out and moved into place when complete,
so --out holds a whole scene or nothing.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``generate`` subcommand."""
    from polargs_plugin.data.family import FAMILY
    from polargs_plugin.data.scenes import FLOOR_TEXTURES
    from polargs_plugin.data.synthetic import MASK_KINDS, SCENE_NAMES
    from polargs_plugin.service.scenes import EXPORTS

    parser = subparsers.add_parser(
        "generate",
        help="render a synthetic polarimetric scene with ground truth",
        description="Render multi-view polarized images (four polarizer angles, Fresnel diffuse + "
        "specular polarization, sensor noise, clipping and quantisation) of a procedural scene, "
        "with ground-truth mesh, normals, depth and diffuse/specular split.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scene", required=True, type=_scene_name, metavar="SCENE",
                        help=f"which procedural scene: {', '.join(SCENE_NAMES)}, or {FAMILY}:K (the procedural "
                        f"family's scene of seed K; {FAMILY} alone: of --seed)")
    parser.add_argument("--out", required=True, type=Path, help="output folder (created; must be absent or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing scene folder --out (as a whole)")
    parser.add_argument("--views", type=positive_int, default=None, help="number of cameras (default 24; family: the seed's)")
    parser.add_argument("--size", type=image_size, default=None, metavar="WxH",
                        help="image size (default 128x128; family: the seed's)")
    parser.add_argument("--small", action="store_true", help="test-sized scene: 8 views of 48x48 (overrides --views/--size)")
    parser.add_argument("--seed", type=non_negative_int, default=None,
                        help="sensor-noise seed (default 0; family:K: K); for a family scene also the scene's seed")
    parser.add_argument("--noise", type=float, default=None,
                        help="Gaussian noise std per angle image (default 0.005; family: the seed's)")
    parser.add_argument("--bits", type=int, choices=(8, 16), default=8, help="sensor bit depth (default 8)")
    parser.add_argument("--ior", type=float, default=1.5,
                        help="refractive index for the Fresnel DoLP (default 1.5; a family scene's materials have their own)")
    parser.add_argument("--mask", choices=MASK_KINDS, default="object",
                        help="what the masks mark: object = the object's own pixels, a floor it stands on is "
                        "background (default); surface = every surface seen, the floor included")
    parser.add_argument("--pictures", action="store_true", help="also save AoLP/DoLP pictures per view under OUT/pictures")
    parser.add_argument("--export", choices=EXPORTS,
                        help="also write the scene as an upstream trainer's input: colmap = OUT/colmap (images/, "
                             "sparse/0) for the graphdeco-family trainers, with OUT as their POLARGS_DATA")
    parser.add_argument("--mosaic", choices=("rgb", "mono"), default=None,
                        help="write raw sensor frames instead: a polar folder with raw/<view>.png (rgb: IMX250MYR colour "
                        "polarization mosaic; mono: IMX250MZR), masks/, the GT meshes and the cameras in sparse/0. --size "
                        "is the frame's size (2448x2048 for the IMX250: 1224x1024 per polarizer angle)")
    parser.add_argument("--floor-texture", choices=FLOOR_TEXTURES, default=None,
                        help="replace the texture of the scene's floor (glossy_plane_sphere; family seeds with a floor): "
                        "uniform, checker (glossy_plane_sphere's own) or speckle (a granite-like mat whose corners "
                        "let SfM register the views; default: the scene's own)")
    parser.add_argument("--no-cameras", action="store_true",
                        help="with --mosaic: leave out the COLMAP model sparse/0 (for `polargs train --sfm`)")
    parser.set_defaults(func=run)


def _scene_name(text: str) -> tuple[str, int | None]:
    """``--scene``: a bundled scene's name, ``family``, or ``family:K`` -> (name, K or None)."""
    from polargs_plugin.data.family import FAMILY, parse_family
    from polargs_plugin.data.synthetic import SCENE_NAMES

    seed = parse_family(text)
    if seed is not None:
        return FAMILY, seed
    if text in (*SCENE_NAMES, FAMILY):
        return text, None
    raise argparse.ArgumentTypeError(f"unknown scene {text!r} (known: {', '.join(SCENE_NAMES)}, {FAMILY}:K)")


def _scene_and_seed(scene: tuple[str, int | None], seed: int | None) -> tuple[str, int]:
    """The scene's name and its seed: K of ``family:K``, else ``--seed`` (default 0)."""
    from polargs_plugin.io import PolarInputError

    name, own_seed = scene
    if own_seed is not None and seed is not None and seed != own_seed:
        raise PolarInputError("--seed", f"{seed} disagrees with the seed {own_seed} of --scene {name}:{own_seed}; give one")
    return name, own_seed if own_seed is not None else (seed or 0)


def run(args: argparse.Namespace) -> int:
    """Generate, write and summarise one scene."""
    from polargs_plugin.data.synthetic import SMALL_SETTINGS
    from polargs_plugin.io import PolarInputError
    from polargs_plugin.service.scenes import SceneRequest, generate_scene_folder

    scene, seed = _scene_and_seed(args.scene, args.seed)
    if args.small:
        args.views, args.size = SMALL_SETTINGS["num_views"], (SMALL_SETTINGS["width"], SMALL_SETTINGS["height"])
    width, height = args.size or (None, None)
    if args.no_cameras and args.mosaic is None:
        raise PolarInputError("--no-cameras", "only with --mosaic (a scene folder always holds its cameras)")
    request = SceneRequest(scene, views=args.views, width=width, height=height, seed=seed,
                           noise_std=args.noise, bits=args.bits, refractive_index=args.ior, mask=args.mask,
                           pictures=args.pictures, mosaic=args.mosaic, cameras=not args.no_cameras,
                           floor_texture=args.floor_texture)
    made = generate_scene_folder(request, args.out, overwrite=args.overwrite, progress=True, export=args.export)
    stats, meta = made.statistics, made.meta
    print(f"scene       {made.name}: {meta['description']}")
    print(f"views       {made.num_views} x {meta['width']}x{meta['height']}, {args.bits}-bit, "
          f"noise {meta['noise_std']:.4g}, seed {seed}"
          + (f"; {args.mosaic} raw mosaics" + ("" if request.cameras else ", no cameras (for --sfm)") if args.mosaic else ""))
    print(f"object      {stats['object_fraction']:.1%} of pixels; mesh {stats['mesh_vertices']} vertices")
    print(f"highlights  {stats['highlight_fraction']:.1%} of object pixels, overexposed {stats['overexposed_fraction']:.1%}")
    print(f"DoLP        median {stats['dolp_median']:.3f} on the object (AoLP model: {meta['azimuth_model']})")
    if "visibility" in stats:
        shares = ", ".join(f"{name} {share:.1%}" for name, share in stats["visibility"].items())
        print(f"visibility  of the seen surface: {shares}; unseen {stats['unseen_fraction']:.1%}")
    print(f"time        {made.render_seconds:.1f} s rendering, {made.write_seconds:.1f} s writing")
    print(f"written     {args.out}" + (f" (+{made.pictures} pictures)" if made.pictures else ""))
    if args.export:
        print(f"trainer     {args.out / args.export} (train.py -s), POLARGS_DATA={args.out}")
    return 0
