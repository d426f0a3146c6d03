"""Where does PatchMatch put a surface it starts on? Depth bias of Dense's PatchMatch on the bundled scenes.

PatchMatch (Dense's, at the CPU preset's settings, with the view's AoLP / DoLP) is started on
the ground-truth depth and normal of a few reference views of each bundled scene (24 views of
128 px, the grid's), so every error it ends with is its own: where the photometric cost has its
minimum away from the true surface. Run twice per view: on the training colour s0 / 2 (what
Dense sees) and on the scene's true diffuse colour (the same views without the specular
reflection, noise-free), which separates what the highlights do from what the matching window
does on a curved, weakly textured surface.

Pixels (inside the mask, photometric cost within the densifier's filter) are grouped by the true
specular colour at the pixel (mean over RGB; the bundled scenes' highlight threshold is 0.1):
``none`` below 0.003, ``halo`` 0.003-0.1, ``highlight`` from 0.1.

Printed per scene, image and group: pixels, median relative depth error (PatchMatch - GT) / GT
(positive = behind the surface), the share behind by more than Dense's seeding threshold
(``densify.seed_depth_footprints`` pixel footprints; the default 2.5 is 1.4 % of the depth at
these cameras), and the median normal error (degrees). GT is used
only to start PatchMatch and to score it.

Usage (about 20 seconds on 2 cores):
python bench/patchmatch_bias.py [--scenes torus_knot,shiny_torus,bumpy_mixed,glossy_plane_sphere]
    [--refs 4] [--threads 2] [--set densify.patchmatch.KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os

import torch

from polargs_plugin.cli.ablate import parse_assignments
from polargs_plugin.config import PolarConfig
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.densify.patchmatch import patchmatch
from polargs_plugin.densify.seeding import seed_relative_depth
from polargs_plugin.densify.view_selection import scene_center, select_sources
from polargs_plugin.hooks import PolarHooks

GROUPS = (("none", -1.0, 0.003), ("halo", 0.003, 0.1), ("highlight", 0.1, float("inf")))


def load() -> str:
    return "load average %.2f, %.2f, %.2f" % os.getloadavg()


def scene_errors(name: str, refs: int, config: PolarConfig) -> dict[str, dict[str, list[torch.Tensor]]]:
    """{image kind: {group: [relative depth errors, normal errors (deg), behind the seeding threshold]}}
    over ``refs`` views."""
    scene = generate_scene(name, num_views=24, width=128, height=128)
    maps = PolarHooks(config).preprocess(scene.views)
    w2c = torch.stack([v.world_to_camera.to(torch.float64) for v in scene.views])
    centre = scene_center(w2c)
    pm = config.densify.patchmatch
    out = {kind: {g[0]: [[], [], []] for g in GROUPS} for kind in ("s0/2", "diffuse")}
    for ref in torch.linspace(0, len(scene.views) - 1, refs).round().long().tolist():
        view = scene.views[ref]
        src = select_sources(w2c[ref], w2c, pm.num_sources, centre, exclude=ref)
        specular = scene.specular_gt[ref].mean(0, keepdim=True)
        inside = view.mask.bool()
        threshold = seed_relative_depth(config.densify.seed_depth_footprints, view.K)
        for kind in out:
            images = [scene.views[j].image if kind == "s0/2" else scene.diffuse_gt[j] for j in [ref] + src]
            result = patchmatch(
                images[0], view.K, view.world_to_camera, torch.stack(images[1:]),
                torch.stack([scene.views[j].K for j in src]), torch.stack([scene.views[j].world_to_camera for j in src]),
                view.depth_gt, view.normal_gt, aolp=maps[ref].aolp, dolp=maps[ref].dolp, mask=inside,
                init_valid=inside, config=pm, generator=torch.Generator().manual_seed(ref),
            )
            scored = inside & (result.depth > 0) & (result.photometric_cost <= config.densify.filters.max_photometric_cost)
            relative = (result.depth - view.depth_gt) / view.depth_gt.clamp_min(1e-6)
            cosine = (torch.nn.functional.normalize(result.normal, dim=0) * view.normal_gt).sum(0, keepdim=True)
            angle = torch.rad2deg(torch.arccos(cosine.clamp(-1, 1)))
            for group, low, high in GROUPS:
                sel = scored & (specular > low) & (specular <= high)
                out[kind][group][0].append(relative[sel])
                out[kind][group][1].append(angle[sel])
                out[kind][group][2].append(relative[sel] > threshold)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="torus_knot,shiny_torus,bumpy_mixed,glossy_plane_sphere")
    parser.add_argument("--refs", type=int, default=4, help="reference views per scene (evenly spaced)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a PolarConfig setting over the CPU preset's, as `polargs ablate --polar-set`")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = PolarConfig.cpu_demo()
    config.update(parse_assignments(args.set, "--set"))
    print(load())
    print(f"PatchMatch started on the GT depth and normal; CPU preset settings{' with ' + ', '.join(args.set) if args.set else ''}; "
          f"{args.refs} reference views per scene")
    print(f"{'scene':20s} {'image':8s} {'group':10s} {'pixels':>7s} {'median rel. depth':>18s} "
          f"{'behind > seed':>15s} {'normal err (deg)':>17s}")
    figures = {}
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        for kind, groups in scene_errors(name, args.refs, config).items():
            for group, (rel, ang, behind) in groups.items():
                rel, ang, behind = torch.cat(rel), torch.cat(ang), torch.cat(behind)
                if rel.numel() == 0:
                    continue
                row = {"pixels": rel.numel(), "median_relative_depth": float(rel.median()),
                       "behind_share": float(behind.float().mean()), "median_normal_deg": float(ang.median())}
                figures.setdefault(name, {}).setdefault(kind, {})[group] = row
                print(f"{name:20s} {kind:8s} {group:10s} {row['pixels']:7d} {row['median_relative_depth']:+18.4f} "
                      f"{row['behind_share']:15.2f} {row['median_normal_deg']:17.1f}")
    print(load())
    print(json.dumps({"bench": "patchmatch_bias", "refs": args.refs, "settings": args.set, "behind_threshold_footprints": config.densify.seed_depth_footprints, "figures": figures}))


if __name__ == "__main__":
    main()
