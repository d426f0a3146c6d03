"""How much of each bundled scene's highlights PC's reflective masks reach, and what they put there.

Against the generator's truth (``SyntheticScene.highlight_masks``: specular part >= 0.1 of the
channel mean; ``diffuse_gt``: the true diffuse colour), over all views of each scene:

- coverage: the share of highlight pixels inside PC's reflective masks (specular | overexposed);
  outside: the share of reflective pixels that are not highlights;
- the channel-mean colour, averaged over the pixels, of the training colour s0 / 2, of PC's
  target (I_diff on specular pixels, I_chro on overexposed ones with a donor) and of the true
  diffuse colour, on three sets: the specular pixels, the overexposed ones, and the "halo", the
  highlight pixels that no mask reaches (there the target stays the training colour);
- on the "ring", the 1-px ring around the reflective masks inside the object mask: the training
  colour, I_diff (= I_min, what PC's target would be there if the masks were grown) and the
  diffuse colour. I_min keeps (1 - DoLP) of the specular reflection, so growing the masks would
  remove only part of a halo.

The masks use the paper's thresholds (``CorrectionConfig``: brightness >= 160/255 of the
channel-mean peak); ``--intensity-low`` changes the lower brightness bound. docs/results.md
"Known limits" reads these figures. A few seconds per scene on 2 cores.

Usage: python bench/pc_masks.py [--scenes glossy_plane_sphere,...] [--views 24] [--size 128] [--intensity-low 0.627]
"""

from __future__ import annotations

import argparse
import json

import torch
import torch.nn.functional as F

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.data.scenes import SCENE_BUILDERS
from polargs_plugin.data.synthetic import generate_scene


def scene_figures(name: str, views: int, size: int, config: CorrectionConfig) -> dict[str, float]:
    scene = generate_scene(name, num_views=views, width=size, height=size)
    sums = {key: torch.zeros(3, dtype=torch.float64) for key in ("specular", "overexposed", "halo", "ring")}
    counts = dict.fromkeys(sums, 0)
    highlights = reflective_total = covered = 0
    for view, diffuse, highlight in zip(scene.views, scene.diffuse_gt, scene.highlight_masks):
        maps = compute_polar_maps(view.stokes, view.mask, config)
        specular, overexposed = maps.specular_mask[0], maps.overexposed_mask[0]
        i_chro_valid = maps.extras["i_chro_valid"].reshape(specular.shape)
        highlight, reflective = highlight[0], specular | overexposed
        highlights += int(highlight.sum())
        reflective_total += int(reflective.sum())
        covered += int((highlight & reflective).sum())
        image, i_diff = view.image.mean(0), maps.i_diff.mean(0)
        grown = F.max_pool2d(reflective.float()[None, None], 3, stride=1, padding=1)[0, 0] > 0
        sets = {
            "specular": (specular, i_diff),
            "overexposed": (overexposed & i_chro_valid, maps.i_chro.mean(0)),
            "halo": (highlight & ~reflective, image),
            "ring": (grown & ~reflective & view.mask[0], i_diff),
        }
        for key, (pixels, target) in sets.items():
            values = torch.stack([image[pixels], target[pixels], diffuse.mean(0)[pixels]]).double()
            sums[key] += values.sum(1)
            counts[key] += int(pixels.sum())
    figures: dict[str, float] = {
        "highlight_pixels": highlights, "reflective_pixels": reflective_total,
        "coverage": covered / max(highlights, 1), "outside": (reflective_total - covered) / max(reflective_total, 1),
    }
    for key, total in sums.items():
        mean = (total / max(counts[key], 1)).tolist()
        figures.update({f"{key}_pixels": counts[key], f"{key}_colour": mean[0], f"{key}_target": mean[1],
                        f"{key}_diffuse": mean[2]})
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENE_BUILDERS))
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--intensity-low", type=float, default=CorrectionConfig().intensity_range[0])
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = CorrectionConfig(intensity_range=(args.intensity_low, 1.0))
    results = {name: scene_figures(name, args.views, args.size, config) for name in args.scenes.split(",")}
    print(f"{args.views} views {args.size}x{args.size}, reflective masks at brightness >= {args.intensity_low:.3f}; "
          f"colours: channel mean of the training colour / PC's target / the true diffuse colour")
    print(f"{'scene':<21}{'highlight px':>13}{'coverage':>10}{'outside':>9}"
          f"{'specular px: colour / target / diffuse':>42}{'overexposed px: ...':>34}{'halo px: ...':>34}"
          f"{'ring px: colour / I_diff / diffuse':>38}")
    for name, f in results.items():
        row = f"{name:<21}{f['highlight_pixels']:>13d}{f['coverage']:>10.2f}{f['outside']:>9.2f}"
        for key, width in (("specular", 42), ("overexposed", 34), ("halo", 34), ("ring", 38)):
            cell = (f"{f[f'{key}_pixels']:d}: {f[f'{key}_colour']:.3f} / {f[f'{key}_target']:.3f} / "
                    f"{f[f'{key}_diffuse']:.3f}")
            row += f"{cell:>{width}}"
        print(row)
    print(json.dumps({"bench": "pc_masks", "views": args.views, "size": args.size,
                      "intensity_low": args.intensity_low, "scenes": results}))


if __name__ == "__main__":
    main()
