"""The five ablation variants of ``polargs ablate`` as (TrainConfig, PolarConfig | None) pairs.

Every variant is the same reference training (same preset, seed and initial points); only the
PolarGS switches differ (docs/ablation.md):

- ``base``: plain 3D Gaussian Splatting, no hooks at all (no PolarGS code runs);
- ``reg``: base + L_dn (depth-normal consistency) + L_scale (flat Gaussians), the geometry
  regularisers a PGSR-like trainer already has; PC off, Dense off, L_n off. It separates what
  polarization adds from what the regularisers add;
- ``no-dense``: reg + PC (reflection-aware colour loss L_ref on specular / overexposed pixels);
- ``no-pc``: reg + Dense (polar-enhanced PatchMatch densification) + L_n (normal loss against
  the PatchMatch normals);
- ``full``: everything (PC + Dense + L_n + L_dn + L_scale).
"""

from __future__ import annotations

from typing import Any

from polargs_plugin.config import CPU_FACTOR

__all__ = ["VARIANTS", "DESCRIPTIONS", "PRESETS", "DEFAULT_FACTOR", "variant_configs", "polar_config", "train_config", "parse_variants"]

VARIANTS: tuple[str, ...] = ("base", "reg", "no-dense", "no-pc", "full")

DESCRIPTIONS: dict[str, str] = {
    "base": "plain 3DGS, no hooks",
    "reg": "base + L_dn + L_scale (no PC, no Dense, no L_n)",
    "no-dense": "reg + PC (L_ref)",
    "no-pc": "reg + Dense + L_n",
    "full": "PC + Dense + L_n + L_dn + L_scale",
}

#: ``cpu``: the vanilla schedule x factor (TrainConfig.cpu), the PolarGS schedules x
#: polar_schedule_factor(factor) (PolarConfig.cpu_demo); ``paper``: vanilla 3DGS schedule with the
#: paper's synthetic-data PolarGS settings (for a GPU).
PRESETS: tuple[str, ...] = ("cpu", "paper")
DEFAULT_FACTOR = CPU_FACTOR

# (PC, Dense, L_n, L_dn + L_scale) per variant with hooks.
_SWITCHES: dict[str, tuple[bool, bool, bool, bool]] = {
    "reg": (False, False, False, True),
    "no-dense": (True, False, False, True),
    "no-pc": (False, True, True, True),
    "full": (True, True, True, True),
}


def parse_variants(text: str) -> list[str]:
    """``"base,full"`` -> ``["base", "full"]``; ``"all"`` -> every variant; raises ValueError."""
    names = list(VARIANTS) if text.strip() == "all" else [v.strip() for v in text.split(",") if v.strip()]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown or not names:
        raise ValueError(f"unknown variant(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(VARIANTS)}")
    return list(dict.fromkeys(names))


def _check(variant: str, preset: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant '{variant}' (known: {', '.join(VARIANTS)})")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}' (known: {', '.join(PRESETS)})")


def train_config(preset: str = "cpu", factor: float | None = None, seed: int = 0, overrides: dict[str, Any] | None = None):
    """The :class:`TrainConfig` of every variant: the preset, the seed, then ``overrides``
    (a nested partial dict, e.g. ``{"iterations": 100, "density": {"max_gaussians": 800}}``;
    checked, errors name ``--train-set``)."""
    from polargs_plugin.service.configs import train_config as build

    _check("base", preset)
    schedule_factor = (DEFAULT_FACTOR if factor is None else factor) if preset == "cpu" else None
    return build(preset, schedule_factor, {"seed": int(seed), **(overrides or {})}, "--train-set")


def polar_config(variant: str, preset: str = "cpu", factor: float | None = None, seed: int = 0,
                 overrides: dict[str, Any] | None = None):
    """The :class:`PolarConfig` of ``variant`` (None for ``base``): the paper's synthetic values
    with the preset's schedules, the variant's switches and the PatchMatch seed, then
    ``overrides`` (nested partial dict; checked, errors name ``--polar-set``)."""
    from polargs_plugin.service.configs import apply_overrides
    from polargs_plugin.service.configs import polar_config as build

    _check(variant, preset)
    if variant == "base":
        return None
    config = build("synthetic", (DEFAULT_FACTOR if factor is None else factor) if preset == "cpu" else None)
    pc, dense, normal, regularisers = _SWITCHES[variant]
    config.correction.enabled = pc
    config.losses.use_ref = pc
    config.densify.enabled = dense
    config.losses.use_normal = normal
    config.losses.use_depth_normal = regularisers
    config.losses.use_scale = regularisers
    config.densify.patchmatch.seed = int(seed)
    return apply_overrides(config, overrides, "--polar-set") if overrides else config


def variant_configs(variant: str, preset: str = "cpu", factor: float | None = None, seed: int = 0,
                    train_overrides: dict[str, Any] | None = None, polar_overrides: dict[str, Any] | None = None):
    """``(TrainConfig, PolarConfig | None)`` of one variant.

    Args:
        variant: one of :data:`VARIANTS`.
        preset: ``cpu`` (schedules x ``factor``) or ``paper``.
        factor: vanilla schedule factor of the cpu preset (default 1/6: 5000 iterations).
        seed: training seed (TrainConfig.seed and the PatchMatch seed).
        train_overrides / polar_overrides: nested partial dicts applied last.
    """
    train = train_config(preset, factor, seed, train_overrides)
    polar = polar_config(variant, preset, factor, seed, polar_overrides)
    return train, polar


def describe(variant: str) -> str:
    """One line for tables and help texts."""
    return DESCRIPTIONS[variant]


if __name__ == "__main__":  # pragma: no cover - a quick look at the switches
    for name in VARIANTS:
        _, polar = variant_configs(name)
        if polar is None:
            print(f"{name:9s} hooks off")
        else:
            l = polar.losses
            print(f"{name:9s} PC={polar.correction.enabled} Dense={polar.densify.enabled} L_ref={l.use_ref} "
                  f"L_n={l.use_normal} L_dn={l.use_depth_normal} L_scale={l.use_scale}")
