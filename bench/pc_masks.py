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
  remove only part of a halo;
- the masks against the generator's split: the specular mask's recall and precision against the
  object pixels whose true specular part exceeds the diffuse part (channel means), and the
  overexposed mask's precision and recall against the object pixels clipped in some polarizer
  image (``SyntheticScene.overexposed_masks``).

The masks use ``CorrectionConfig``'s defaults (brightness >= 160/255 of the channel-mean peak,
overexposed = clipped); ``--intensity-low`` changes the lower brightness bound and
``--overexposed-rule paper`` puts back the paper's overexposed rule. Scenes are bundled names or
``family:K`` (the seed's own views and size unless ``--views`` / ``--size`` are given).
docs/results.md reads these figures. A few seconds per scene on 2 cores.

Usage: python bench/pc_masks.py [--scenes glossy_plane_sphere,family:20001,...] [--views 24] [--size 128]
       [--intensity-low 0.627] [--overexposed-rule saturated|paper]
"""

from __future__ import annotations

import argparse
import json

import torch
import torch.nn.functional as F

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.data.family import generate_family_scene, parse_family
from polargs_plugin.data.scenes import SCENE_BUILDERS
from polargs_plugin.data.synthetic import SyntheticScene, generate_scene


def render(name: str, views: int | None, size: int | None) -> SyntheticScene:
    """A bundled scene (``views`` x ``size`` default 24 x 128) or ``family:K`` (its own unless given)."""
    seed = parse_family(name)
    if seed is not None:
        return generate_family_scene(seed, num_views=views, size=None if size is None else (size, size))
    return generate_scene(name, num_views=views or 24, width=size or 128, height=size or 128)


def _share(hits: int, total: int) -> float | None:
    """hits / total; None where there is nothing to count (the table prints it as -)."""
    return hits / total if total else None


def _cell(value: float | None, width: int, digits: int = 2) -> str:
    return f"{'-' if value is None else f'{value:.{digits}f}':>{width}}"


def scene_figures(name: str, views: int | None, size: int | None, config: CorrectionConfig) -> dict[str, float]:
    scene = render(name, views, size)
    sums = {key: torch.zeros(3, dtype=torch.float64) for key in ("specular", "overexposed", "halo", "ring")}
    counts = dict.fromkeys(sums, 0)
    highlights = reflective_total = covered = 0
    split = dict.fromkeys(("spec_hit", "spec_true", "spec_said", "over_hit", "over_true", "over_said"), 0)
    for view, diffuse, specular_gt, highlight, clipped in zip(scene.views, scene.diffuse_gt, scene.specular_gt,
                                                               scene.highlight_masks, scene.overexposed_masks):
        maps = compute_polar_maps(view.stokes, view.mask, config)
        specular, overexposed = maps.specular_mask[0], maps.overexposed_mask[0]
        inside = view.mask[0]
        dominant = inside & (specular_gt.mean(0) > diffuse.mean(0))
        clipped = inside & clipped[0]
        split["spec_hit"] += int((specular & dominant).sum())
        split["spec_true"] += int(dominant.sum())
        split["spec_said"] += int((specular & inside).sum())
        split["over_hit"] += int((overexposed & clipped).sum())
        split["over_true"] += int(clipped.sum())
        split["over_said"] += int((overexposed & inside).sum())
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
        "specular_dominant_share": _share(split["spec_true"], sum(int(v.mask.sum()) for v in scene.views)),
        "specular_recall": _share(split["spec_hit"], split["spec_true"]),
        "specular_precision": _share(split["spec_hit"], split["spec_said"]),
        "clipped_share": _share(split["over_true"], sum(int(v.mask.sum()) for v in scene.views)),
        "overexposed_precision": _share(split["over_hit"], split["over_said"]),
        "overexposed_recall": _share(split["over_hit"], split["over_true"]),
    }
    for key, total in sums.items():
        mean = (total / max(counts[key], 1)).tolist()
        figures.update({f"{key}_pixels": counts[key], f"{key}_colour": mean[0], f"{key}_target": mean[1],
                        f"{key}_diffuse": mean[2]})
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENE_BUILDERS))
    parser.add_argument("--views", type=int, default=None, help="views (default: 24, a family seed's own)")
    parser.add_argument("--size", type=int, default=None, help="square size (default: 128, a family seed's own)")
    parser.add_argument("--intensity-low", type=float, default=CorrectionConfig().intensity_range[0])
    parser.add_argument("--overexposed-rule", choices=("saturated", "paper"), default=CorrectionConfig().overexposed_rule)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = CorrectionConfig(intensity_range=(args.intensity_low, 1.0), overexposed_rule=args.overexposed_rule)
    results = {name: scene_figures(name, args.views, args.size, config) for name in args.scenes.split(",")}
    print(f"reflective masks at brightness >= {args.intensity_low:.3f}, overexposed rule {args.overexposed_rule!r}; "
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
    print(f"\n{'scene':<21}{'spec>diff px':>13}{'specular recall':>17}{'precision':>11}{'clipped px':>12}"
          f"{'overexposed precision':>23}{'recall':>8}")
    for name, f in results.items():
        print(f"{name:<21}" + _cell(f["specular_dominant_share"], 13, 3) + _cell(f["specular_recall"], 17)
              + _cell(f["specular_precision"], 11) + _cell(f["clipped_share"], 12, 3)
              + _cell(f["overexposed_precision"], 23) + _cell(f["overexposed_recall"], 8))
    print(json.dumps({"bench": "pc_masks", "views": args.views, "size": args.size, "intensity_low": args.intensity_low,
                      "overexposed_rule": args.overexposed_rule, "scenes": results}))


if __name__ == "__main__":
    main()
