"""``polargs generate``: render a procedural polarimetric scene into a scene folder."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from polargs_plugin.cli.argtypes import image_size, positive_int

_EPILOG = """examples:
  polargs generate --scene glossy_plane_sphere --out scenes/sphere
  polargs generate --scene bumpy_mixed --out scenes/bumpy --views 36 --size 160x120 --pictures
  polargs generate --scene shiny_torus --out out/torus --small      # 8 views of 48x48, for tests

The folder holds four RGB angle images per view (0/45/90/135 deg), cameras.json (K and
world_to_camera, OpenCV frame), masks, ground-truth normals/depth/diffuse/specular, highlight and
overexposure masks, the ground-truth mesh (mesh.ply) and scene.json; see docs/dataset-format.md.

An existing non-empty --out is refused (scenes are never mixed); --overwrite replaces a previous
scene folder as a whole. The scene is written beside --out and moved into place when complete,
so --out holds a whole scene or nothing.
"""

#: Files that mark a folder as a scene folder `polargs generate` may replace with --overwrite.
_SCENE_MARKERS = ("scene.json", "cameras.json")






def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``generate`` subcommand."""
    from polargs_plugin.data.synthetic import MASK_KINDS, SCENE_NAMES

    parser = subparsers.add_parser(
        "generate",
        help="render a synthetic polarimetric scene with ground truth",
        description="Render multi-view polarized images (four polarizer angles, Fresnel diffuse + "
        "specular polarization, sensor noise, clipping and quantisation) of a procedural scene, "
        "with ground-truth mesh, normals, depth and diffuse/specular split.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scene", required=True, choices=SCENE_NAMES, help="which procedural scene")
    parser.add_argument("--out", required=True, type=Path, help="output folder (created; must be absent or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing scene folder --out (as a whole)")
    parser.add_argument("--views", type=positive_int, default=24, help="number of cameras (default 24)")
    parser.add_argument("--size", type=image_size, default=(128, 128), metavar="WxH", help="image size (default 128x128)")
    parser.add_argument("--small", action="store_true", help="test-sized scene: 8 views of 48x48 (overrides --views/--size)")
    parser.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default 0)")
    parser.add_argument("--noise", type=float, default=0.005, help="Gaussian noise std per angle image (default 0.005)")
    parser.add_argument("--bits", type=int, choices=(8, 16), default=8, help="sensor bit depth (default 8)")
    parser.add_argument("--ior", type=float, default=1.5, help="refractive index for the Fresnel DoLP (default 1.5)")
    parser.add_argument("--mask", choices=MASK_KINDS, default="object",
                        help="what the masks mark: object = the object's own pixels, a floor it stands on is "
                        "background (default); surface = every surface seen, the floor included")
    parser.add_argument("--pictures", action="store_true", help="also save AoLP/DoLP pictures per view under OUT/pictures")
    parser.set_defaults(func=run)


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def _check_out(out: Path, overwrite: bool) -> str | None:
    """The problem with writing a scene to ``out``, or None."""
    if out.exists() and not out.is_dir():
        return f"{out}: exists and is not a folder"
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            return f"{out}: exists and is not empty; choose another --out, or pass --overwrite to replace the scene in it"
        if not any((out / name).is_file() for name in _SCENE_MARKERS):
            return (f"{out}: --overwrite replaces scene folders only (with {' or '.join(_SCENE_MARKERS)}); "
                    "this one is not: remove it yourself if it should go")
    return None


def run(args: argparse.Namespace) -> int:
    """Generate, write and summarise one scene."""
    out: Path = args.out
    problem = _check_out(out, args.overwrite)
    if problem is not None:
        return _error(problem)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.generating-", dir=out.parent))
    except OSError as err:
        return _error(f"{out}: cannot write there ({err.strerror or err})")
    try:
        status = _generate(args, staging)
        if status == 0:
            _swap_in(staging, out)
        return status
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _swap_in(staging: Path, out: Path) -> None:
    """Move the complete scene ``staging`` to ``out``, replacing what --overwrite allowed."""
    os.chmod(staging, 0o777 & ~_umask())  # mkdtemp made it 0700
    old = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old / "scene")
    os.replace(staging, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    from polargs_plugin.io import current_umask

    return current_umask()


def _generate(args: argparse.Namespace, folder: Path) -> int:
    import torch

    from polargs_plugin.data.scene_format import write_scene
    from polargs_plugin.data.synthetic import SMALL_SETTINGS, generate_scene
    from polargs_plugin.optics.stokes import dolp_from_stokes

    if args.small:
        args.views, args.size = SMALL_SETTINGS["num_views"], (SMALL_SETTINGS["width"], SMALL_SETTINGS["height"])
    width, height = args.size
    start = time.perf_counter()
    scene = generate_scene(
        args.scene,
        num_views=args.views,
        width=width,
        height=height,
        seed=args.seed,
        noise_std=args.noise,
        quantize_bits=args.bits,
        refractive_index=args.ior,
        mask=args.mask,
        progress=True,
    )
    rendered = time.perf_counter() - start
    write_scene(scene, folder)
    pictures = 0
    if args.pictures:
        from polargs_plugin.viz import polar_panels, save_contact_sheet, save_polar_pictures

        for view in scene.views:
            pictures += len(save_polar_pictures(view.stokes, folder / "pictures", view.name))
        # One overview picture: a few views as rows, s0 / AoLP / DoLP / AoLP-with-DoLP as columns.
        step = max(1, len(scene.views) // 4)
        rows = [[polar_panels(v.stokes)[k] for k in ("s0", "aolp", "dolp", "aolp_dolp")] for v in scene.views[::step][:4]]
        save_contact_sheet(rows, folder / "pictures" / "overview.png")
        pictures += 1
    mask = torch.stack([v.mask for v in scene.views])
    dolp = torch.stack([dolp_from_stokes(v.stokes.mean(dim=1, keepdim=True)) for v in scene.views])

    def fraction(masks: list[torch.Tensor]) -> float:
        return float(torch.stack(masks).sum() / mask.sum().clamp(min=1))

    print(f"scene       {scene.name}: {scene.meta['description']}")
    print(f"views       {len(scene.views)} x {width}x{height}, {args.bits}-bit, noise {args.noise}, seed {args.seed}")
    print(f"object      {float(mask.float().mean()):.1%} of pixels; mesh {len(scene.mesh_vertices)} vertices")
    print(f"highlights  {fraction(scene.highlight_masks):.1%} of object pixels, overexposed {fraction(scene.overexposed_masks):.1%}")
    print(f"DoLP        median {float(dolp[mask].median()):.3f} on the object (AoLP model: {scene.meta['azimuth_model']})")
    print(f"time        {rendered:.1f} s rendering, {time.perf_counter() - start - rendered:.1f} s writing")
    print(f"written     {args.out}" + (f" (+{pictures} pictures)" if pictures else ""))
    return 0
