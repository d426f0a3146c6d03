"""PolarConfig: every PolarGS knob with its paper default (the PolarGS paper; choices in docs/choices.md).

Thresholds the paper writes in 8-bit units (160..255) are converted here, once, to [0, 1].
Choices the paper leaves open are documented in docs/choices.md and exposed as fields.
Presets: ``PolarConfig.real()`` and ``PolarConfig.synthetic()`` (the paper's two settings) and
``PolarConfig.cpu_demo()`` (schedules scaled for CPU runs; :func:`polar_schedule_factor` gives the
factor that goes with a vanilla schedule factor, docs/speed.md "CPU preset").
"""

from __future__ import annotations

import math
import types
import typing
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Any

__all__ = [
    "CorrectionConfig",
    "LossConfig",
    "DensifyConfig",
    "PatchMatchConfig",
    "FilterConfig",
    "PolarConfig",
    "eight_bit",
    "CPU_FACTOR",
    "POLAR_SCHEDULE_STRETCH",
    "polar_schedule_factor",
    "check_setting",
]

#: Vanilla schedule factor of the CPU preset (``TrainConfig.cpu()``): 30k iterations -> 5000.
CPU_FACTOR = 1 / 6

#: The CPU preset compresses the PolarGS schedules (Dense window and interval, L_dn start, L_n end)
#: this many times less than the vanilla one (``TrainConfig.cpu``'s factor): at the preset's
#: vanilla factor 1/6 (5000 iterations), the paper's Dense 1k-7k every 100 and L_dn from 7k become
#: 500-3500 every 50 and 3500, i.e. scaled by 1/2 (docs/speed.md, "CPU preset").
POLAR_SCHEDULE_STRETCH = 3.0


def polar_schedule_factor(train_factor: float) -> float:
    """Factor of the PolarGS schedules for a run whose vanilla schedule is scaled by
    ``train_factor``: :data:`POLAR_SCHEDULE_STRETCH` times it, at most 1 (the paper's own counts).

    >>> polar_schedule_factor(1 / 6)
    0.5
    >>> polar_schedule_factor(1.0)
    1.0
    """
    if not train_factor > 0:
        raise ValueError(f"train_factor must be positive, got {train_factor}")
    return min(1.0, POLAR_SCHEDULE_STRETCH * train_factor)


def eight_bit(value: float) -> float:
    """Convert a threshold written in 8-bit units (0..255) to the [0, 1] image range."""
    return value / 255.0


@dataclass
class CorrectionConfig:
    """Module PC: reflective masks, PRI, colour refinement maps."""

    enabled: bool = True
    specular_dolp: tuple[float, float] = (0.3, 1.0)
    overexposed_dolp: tuple[float, float] = (0.0, 0.1)
    intensity_range: tuple[float, float] = (eight_bit(160), eight_bit(255))
    mahalanobis_threshold: float = 0.8
    propagation_radius: int = 7
    # docs/choices.md: the propagation window is sampled every `propagation_step` pixels (speed).
    propagation_step: int = 2
    # docs/choices.md: angles whose brightest channel reaches this level are left out of PRI.
    pri_saturation: float = eight_bit(254)
    # docs/choices.md: None = brightness-preserving rho_d (I_chro keeps the donors' colour).
    rho_d: float | None = None
    # docs/choices.md "HDR inputs": the value of a polarizer-angle image (in the units of the
    # training colour s0 / 2) that an 8-bit sensor records as 255. Brightness thresholds are in
    # units of it; anything above it is saturated (bright for the masks, never an I_chro donor).
    # 1.0 = the [0, 1] convention, where the trainers clamp the colour target.
    white_level: float = 1.0
    # docs/choices.md "Between the DoLP rules": bright pixels whose DoLP is in neither the
    # specular nor the overexposed range: "by_saturation" (saturated -> overexposed, otherwise
    # specular), "specular", "overexposed" or "none" (the paper read literally: no mask).
    intermediate_dolp: str = "by_saturation"
    # docs/choices.md "Impossible Stokes": noise allowance (units of s0, times white_level) for
    # s0 < 0 and sqrt(s1^2 + s2^2) > s0; beyond it a pixel counts as impossible. Every pixel is
    # projected onto the physical cone; a view with more than `max_impossible_fraction` of its
    # (masked) pixels impossible is refused (a reader's scale or sign convention is wrong).
    stokes_tolerance: float = 0.02
    max_impossible_fraction: float = 0.05


@dataclass
class LossConfig:
    """Loss weights: L = L_c + alpha L_n + beta L_dn + gamma L_scale, L_c = L_non + lambda_ref L_ref."""

    lambda_ref: float = 1.0
    alpha_normal: float = 0.2
    beta_depth_normal: float = 0.05
    gamma_scale: float = 50.0
    ssim_weight: float = 0.2
    depth_normal_from_iter: int = 7000
    # docs/patchmatch.md "Effect": N_opt is refreshed only inside the Dense window, so L_n on every
    # target pixel ends this many iterations after densify.end_iter (one Dense interval); None =
    # on every target pixel to the end.
    normal_until_after_dense: int | None = 100
    # After that, L_n holds each view's last N_opt where the rendered normal still lies within this
    # many degrees of it and releases the rest (a stale target the model has left is either wrong
    # or overruled); None: L_n stops.
    normal_hold_deg: float | None = 10.0
    use_ref: bool = True
    use_normal: bool = True
    use_depth_normal: bool = True
    use_scale: bool = True


@dataclass
class PatchMatchConfig:
    """Polar-enhanced PatchMatch (densify/patchmatch)."""

    num_sources: int = 4
    iterations: int = 4
    window_radius: int = 5
    window_step: int = 2
    sigma_spatial: float = -1.0
    sigma_color: float = 0.2
    lambda_aolp: float = 0.02
    lambda_normal_depth: float = 0.05
    tau: float = 0.1
    sigma_dolp: float = 0.5
    depth_perturbation: float = 0.02
    top_k_sources: int = 2
    propagation_distances: tuple[int, ...] = (1, 3, 5)
    refine_depth_range: float = 0.05
    refine_normal_deg: float = 20.0
    azimuth_model: str = "orthographic"
    ncc_backend: str = "auto"
    chunk_elements: int = 1 << 22
    seed: int = 0


@dataclass
class FilterConfig:
    """Multi-view geometric and polarimetric consistency filters."""

    max_reprojection_px: float = 1.0
    max_relative_depth: float = 0.01
    min_consistent_views: int = 2
    max_polar_residual: float = 0.3
    use_polar: bool = True
    polar_dolp_reference: float = 0.1
    azimuth_model: str = "orthographic"
    max_photometric_cost: float = 0.9


@dataclass
class DensifyConfig:
    """Module Dense: schedule and seeding (docs/patchmatch.md).

    Attributes:
        enabled: run Dense at all.
        start_iter, end_iter, interval: Dense runs at the iterations ``start_iter <= it <=
            end_iter`` with ``it % interval == 0`` (the paper's 1k-7k every 100).
        stride: seeds on every ``stride``-th pixel each way.
        max_new_per_call: at most this many new Gaussians a call (a random subset).
        initial_opacity: the seeded Gaussians' opacity.
        alpha_threshold: rendered alpha below which a pixel is a hole (seeded); above it a source
            view's rendered depth serves the consistency filters.
        seed_depth_footprints: how far, in pixel footprints (depth / focal), the rendered surface
            must lie behind PatchMatch's to count as wrong (either side with
            ``seed_behind_surface``). 0.88: 0.5 % of the depth at the bundled scenes' 128 px, 2 %
            at 40 px. Below about a footprint, PatchMatch's own sub-pixel noise (its multi-view
            filter allows 1 % of the depth) would seed where the render is right; far above it, a
            surface recessed by a pixel goes unseeded (docs/patchmatch.md "Seeding"). The paper
            seeds every pixel that passes the filters.
        seed_max_plane_deviation: seeds only where the 3x3 neighbours' PatchMatch depths stay on
            the pixel's PatchMatch plane within this fraction of its depth (occlusion edges fail);
            None: no such test.
        seed_behind_surface: also seed where PatchMatch's depth lies *behind* an opaque rendered
            surface. Off by default: the seed would be hidden in its own view, and on a glossy
            surface PatchMatch matches the mirror image behind it (docs/patchmatch.md "Seeding").
        thin_scale_ratio: a seed's scale along its normal, as a fraction of its tangent scales.
        use_view_mask: PatchMatch only inside the view's object mask, where it has one.
        patchmatch, filters: the search and the multi-view consistency filters.
    """

    enabled: bool = True
    start_iter: int = 1000
    end_iter: int = 7000
    interval: int = 100
    stride: int = 2
    max_new_per_call: int = 5000
    initial_opacity: float = 0.5
    alpha_threshold: float = 0.5
    seed_depth_footprints: float = 0.88
    seed_max_plane_deviation: float | None = 0.04
    seed_behind_surface: bool = False
    thin_scale_ratio: float = 0.1
    use_view_mask: bool = True
    patchmatch: PatchMatchConfig = field(default_factory=PatchMatchConfig)
    filters: FilterConfig = field(default_factory=FilterConfig)


@dataclass
class PolarConfig:
    """All PolarGS settings. Defaults are the paper's synthetic-data values."""

    correction: CorrectionConfig = field(default_factory=CorrectionConfig)
    losses: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    refractive_index: float = 1.5
    cache_dir: str | None = None

    @classmethod
    def synthetic(cls) -> "PolarConfig":
        """Paper values for synthetic data: lambda1 = 0.02, alpha = 0.2; azimuth model "perspective".

        The azimuth model is a preset choice (docs/patchmatch.md "Effect"): the field
        default stays the orthographic AoLP convention of docs/conventions.md, while synthetic data rendered by a
        physical polarization renderer, the bundled scenes included (``data.synthetic``), follow
        the perspective phase-angle model of an on-sensor polarizer.
        """
        cfg = cls()
        cfg.densify.patchmatch.lambda_aolp = 0.02
        cfg.losses.alpha_normal = 0.2
        cfg.densify.patchmatch.azimuth_model = "perspective"
        cfg.densify.filters.azimuth_model = "perspective"
        return cfg

    @classmethod
    def real(cls) -> "PolarConfig":
        """Paper values for real captures: lambda1 = 0.2, alpha = 0.1."""
        cfg = cls()
        cfg.densify.patchmatch.lambda_aolp = 0.2
        cfg.losses.alpha_normal = 0.1
        return cfg

    @classmethod
    def cpu_demo(cls, factor: float = 0.5) -> "PolarConfig":
        """Synthetic preset with every iteration schedule multiplied by ``factor``; the default 0.5
        is the CPU preset's (Dense 500-3500 every 50, L_dn from 3500, L_n on every target pixel until
        3550 and where the render agrees with it after), which goes
        with ``TrainConfig.cpu()`` (see :func:`polar_schedule_factor`)."""
        cfg = cls.synthetic()
        d = cfg.densify
        d.start_iter = int(d.start_iter * factor)
        d.end_iter = int(d.end_iter * factor)
        d.interval = max(1, int(d.interval * factor))
        cfg.losses.depth_normal_from_iter = int(cfg.losses.depth_normal_from_iter * factor)
        if cfg.losses.normal_until_after_dense is not None:
            cfg.losses.normal_until_after_dense = max(1, int(cfg.losses.normal_until_after_dense * factor))
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PolarConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ``KeyError`` naming the key, values of
        the wrong kind ``ValueError`` naming the setting (:func:`check_setting`)."""
        return _fill(cls(), data, "config")

    def update(self, data: dict[str, Any]) -> "PolarConfig":
        """Set the fields named in a (nested, partial) dict, e.g. ``{"losses": {"alpha_normal": 0.1}}``,
        on this config (a preset, say); unknown keys raise ``KeyError`` naming the key, values of
        the wrong kind ``ValueError`` (:func:`check_setting`). Returns self."""
        return _fill(self, data, "config")


def _fill(obj: Any, data: dict[str, Any], where: str) -> Any:
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a dict of settings, got {data!r}")
    known = {f.name for f in fields(obj)}
    hints = typing.get_type_hints(type(obj))
    for key, value in data.items():
        if key not in known:
            raise KeyError(f"{where}: unknown setting '{key}' (known: {sorted(known)})")
        current = getattr(obj, key)
        if is_dataclass(current):
            _fill(current, value, f"{where}.{key}")
        else:
            setattr(obj, key, check_setting(value, hints[key], f"{where}.{key}"))
    return obj


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "null"}
_PLURALS = {bool: "true / false values", int: "integers", float: "numbers", str: "strings"}


def _kind(hint: Any) -> str:
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return " or ".join(_kind(h) for h in typing.get_args(hint))
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_PLURALS.get(args[0], _kind(args[0]))}"
        return f"a list of {len(args)} ({', '.join(_kind(a) for a in args)})"
    return _KINDS.get(hint, str(hint))


def _fits(value: Any, hint: Any) -> tuple[bool, Any]:
    """(whether ``value`` fits ``hint``, the value as the field holds it)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        for option in typing.get_args(hint):
            ok, converted = _fits(value, option)
            if ok:
                return True, converted
        return False, value
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            return False, value
        items = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(value):
            return False, value
        pairs = [_fits(v, h) for v, h in zip(value, items)]
        return all(ok for ok, _ in pairs), tuple(v for _, v in pairs)
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)
        return number, float(value) if number else value
    if hint is str:
        return isinstance(value, str), value
    if hint is type(None):
        return value is None, value
    return True, value  # other annotations are not checked here


def check_setting(value: Any, hint: Any, where: str) -> Any:
    """``value`` as a field annotated ``hint`` holds it (a list becomes a tuple, an int in a float
    field a float); ValueError naming ``where``, the expected kind and the value otherwise.

    Checked: bool, int, float (not NaN), str, None, their unions (``float | None``) and tuples
    (``tuple[float, float]``, ``tuple[int, ...]``); other annotations pass unchecked.

    >>> check_setting([1, 2.5], tuple[float, float], "correction.specular_dolp")
    (1.0, 2.5)
    >>> check_setting("0.1", float | None, "densify.seed_max_plane_deviation")
    Traceback (most recent call last):
    ...
    ValueError: densify.seed_max_plane_deviation: expected a number or null, got '0.1'
    """
    ok, converted = _fits(value, hint)
    if not ok:
        raise ValueError(f"{where}: expected {_kind(hint)}, got {value!r}")
    return converted
