"""PolarConfig: every PolarGS knob with its paper default (the PolarGS paper; choices in docs/choices.md).

Thresholds the paper writes in 8-bit units (160..255) are converted here, once, to [0, 1].
Choices the paper leaves open are documented in docs/choices.md and exposed as fields.
Presets: ``PolarConfig.real()`` and ``PolarConfig.synthetic()`` (the paper's two settings) and
``PolarConfig.cpu_demo()`` (schedules scaled for CPU runs; :func:`polar_schedule_factor` gives the
factor that goes with a vanilla schedule factor, docs/speed.md "CPU preset").

Checked settings. Every settings dataclass of the package (these, and the reference trainer's
``TrainConfig`` with what it holds) derives from :class:`CheckedConfig`: each value must fit its
field's type (:func:`check_setting`; mode strings are ``Literal`` types) and the values its field
declares in its metadata (:func:`at_least`, :func:`above`, :func:`within`, :func:`pair_within`,
:func:`not_below`, :func:`satisfies`). The check runs when a config is built (constructor,
``from_dict``, ``update``, presets) and again where one is used (``PolarHooks``, the reference
``Trainer``), since attributes can be reassigned in between. A refusal is one ``ValueError``
line naming the field by its dotted path, the value and what is allowed:

>>> PolarConfig.synthetic().update({"densify": {"interval": 0}})
Traceback (most recent call last):
...
ValueError: densify.interval: must be a positive integer, got 0
"""

from __future__ import annotations

import copy
import functools
import math
import numbers
import types
import typing
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Any, Callable, ClassVar, Literal, TypeVar

__all__ = [
    "VANILLA_SSIM_WEIGHT",
    "CorrectionConfig",
    "LossConfig",
    "DensifyConfig",
    "PatchMatchConfig",
    "FilterConfig",
    "PolarConfig",
    "CheckedConfig",
    "AzimuthModel",
    "NccBackend",
    "IntermediateDolp",
    "OverexposedRule",
    "at_least",
    "above",
    "within",
    "pair_within",
    "not_below",
    "satisfies",
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

#: How the azimuth of a normal is read from the AoLP (docs/patchmatch.md "Cost"): ``"orthographic"``
#: (the AoLP convention of docs/conventions.md) or ``"perspective"`` (the phase angle of an
#: on-sensor polarizer seen along each pixel's ray); the values of ``optics.AZIMUTH_MODELS``.
AzimuthModel = Literal["orthographic", "perspective"]

#: PatchMatch's cost backend: ``"torch"`` (the reference; CPU and CUDA), ``"numba"`` (fused CPU
#: kernels, same costs) or ``"auto"`` (numba on CPU when installed, torch otherwise).
NccBackend = Literal["auto", "torch", "numba"]

#: What becomes of bright pixels whose DoLP lies in neither reflective range (docs/choices.md
#: "Between the DoLP rules").
IntermediateDolp = Literal["none", "specular", "overexposed", "by_saturation"]
#: Which pixels the overexposed mask holds (docs/choices.md "What overexposed means"): the
#: clipped ones, or the paper's bright and weakly polarized ones.
OverexposedRule = Literal["saturated", "paper"]


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


# ------------------------------------------------------------------------------ declared values
def _number(value: float) -> str:
    return f"{value:g}"


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


@dataclass(frozen=True)
class _Range:
    """Numbers between two bounds (each item, for a tuple field); None: no bound on that side."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    unit: str = ""

    def _allows(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)

    def _describe(self, integer: bool) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if integer and self.high is None and (self.low, self.low_open) in ((1, False), (0, True)):
            return "a positive integer"
        if integer and self.high is None and (self.low, self.low_open) == (0, False):
            return "a non-negative integer"
        if self.low is not None and self.high is not None:
            text = (f"in {'(' if self.low_open else '['}{_number(self.low)}, "
                    f"{_number(self.high)}{')' if self.high_open else ']'}")
        elif self.low is not None:
            text = f"{'>' if self.low_open else '>='} {_number(self.low)}"
        else:
            text = f"{'<' if self.high_open else '<='} {_number(self.high)}"
        return (f"an integer {text}" if integer else text) + unit

    def problem(self, value: Any, config: Any, where: str, integer: bool) -> str | None:
        items = value if isinstance(value, (tuple, list)) else (value,)
        if all(self._allows(item) for item in items):
            return None
        text = self._describe(integer)
        return f"a list of numbers each {text}" if isinstance(value, (tuple, list)) else text


@dataclass(frozen=True)
class _OrderedPair:
    """A ``(low, high)`` pair with ``bottom <= low <= high <= top``."""

    bottom: float
    top: float

    def problem(self, value: Any, config: Any, where: str, integer: bool) -> str | None:
        low, high = value
        if self.bottom <= low <= high <= self.top:
            return None
        return f"a pair (low, high) with {_number(self.bottom)} <= low <= high <= {_number(self.top)}"


@dataclass(frozen=True)
class _NotBelow:
    """At least the value of another field of the same config (a window's end and its start)."""

    other: str

    def problem(self, value: Any, config: Any, where: str, integer: bool) -> str | None:
        bound = getattr(config, self.other)
        if value >= bound:
            return None
        return f">= {_join(where, self.other)} ({bound!r})"


@dataclass(frozen=True)
class _Satisfies:
    """A rule no range expresses: ``test(value, config)`` holds; ``text`` says what is allowed."""

    test: Callable[[Any, Any], bool]
    text: str

    def problem(self, value: Any, config: Any, where: str, integer: bool) -> str | None:
        return None if self.test(value, config) else self.text


def at_least(low: float) -> dict[str, Any]:
    """Field metadata: values ``>= low`` (an integer field with ``low`` 1 reads "a positive integer").

    >>> @dataclass
    ... class Schedule(CheckedConfig):
    ...     every: int = field(default=10, metadata=at_least(1))
    >>> Schedule(every=0)
    Traceback (most recent call last):
    ...
    ValueError: every: must be a positive integer, got 0
    """
    return {"allowed": _Range(low=low)}


def above(low: float) -> dict[str, Any]:
    """Field metadata: values ``> low``."""
    return {"allowed": _Range(low=low, low_open=True)}


def within(low: float, high: float, *, low_open: bool = False, high_open: bool = False, unit: str = "") -> dict[str, Any]:
    """Field metadata: values in ``[low, high]`` (each bound excluded with ``low_open`` / ``high_open``;
    ``unit`` is said after the range). For a tuple field, every item."""
    return {"allowed": _Range(low, high, low_open, high_open, unit)}


def pair_within(bottom: float, top: float) -> dict[str, Any]:
    """Field metadata: a ``(low, high)`` pair with ``bottom <= low <= high <= top``."""
    return {"allowed": _OrderedPair(bottom, top)}


def not_below(other: str) -> dict[str, Any]:
    """Field metadata: at least the value of the field ``other`` of the same config."""
    return {"allowed": _NotBelow(other)}


def satisfies(test: Callable[[Any, Any], bool], text: str) -> dict[str, Any]:
    """Field metadata: ``test(value, config)`` holds; ``text`` completes "must be ..."."""
    return {"allowed": _Satisfies(test, text)}


_C = TypeVar("_C", bound="CheckedConfig")


class CheckedConfig:
    """Base of the settings dataclasses: checked when built, rebuilt from plain data, updated.

    Subclasses are dataclasses whose fields all have defaults. Each field's value must fit its
    type (:func:`check_setting`) and the values its metadata allows (:func:`at_least` ...); a
    field holding a settings dataclass is checked recursively. Messages name the field by its
    dotted path below ``where`` (e.g. ``densify.interval``).
    """

    #: Settings this config had once, each with where it went (or why it went): a saved config
    #: that still holds one is refused with that note rather than as an unknown setting.
    RETIRED: ClassVar[dict[str, str]] = {}

    def __post_init__(self) -> None:
        self.validate()

    def validate(self: _C, where: str = "") -> _C:
        """Check every field (recursively); ValueError naming the first bad one. Returns self.

        Args:
            where: the dotted name of this config in the messages ('' for none, e.g. "config").
        """
        _validate(self, where)
        return self

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain data (nested configs as dicts, tuples kept)."""
        return asdict(self)

    @classmethod
    def from_dict(cls: type[_C], data: dict[str, Any], where: str = "") -> _C:
        """Inverse of :meth:`to_dict`; keys left out keep their defaults. Unknown keys raise
        ``KeyError`` naming the key, values of the wrong kind or out of range ``ValueError``
        naming the field (:meth:`validate`); ``where`` names the root in those messages."""
        return _fill(cls(), data, where).validate(where)

    def update(self: _C, data: dict[str, Any], where: str = "") -> _C:
        """Set the fields named in a (nested, partial) dict, e.g. ``{"losses": {"alpha_normal": 0.1}}``,
        on this config (a preset, say), as :meth:`from_dict` checks them; on a refusal nothing
        is changed. Returns self."""
        _fill(copy.deepcopy(self), data, where).validate(where)
        return _fill(self, data, where)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _validate(config: Any, where: str) -> None:
    hints = _hints(type(config))
    for f in fields(config):
        path = _join(where, f.name)
        value, hint = getattr(config, f.name), hints[f.name]
        if not _fits(value, hint)[0]:
            shown = type(value).__name__ if is_dataclass(value) else repr(value)
            raise ValueError(f"{path}: expected {_kind(hint)}, got {shown}")
        if is_dataclass(value):
            _validate(value, path)
            continue
        rule = f.metadata.get("allowed")
        problem = None if rule is None or value is None else rule.problem(value, config, where, _is_integer(hint))
        if problem is not None:
            nullable = " or null" if _options(hint)[1] else ""
            raise ValueError(f"{path}: must be {problem}{nullable}, got {value!r}")


def _fill(obj: Any, data: dict[str, Any], where: str) -> Any:
    if not isinstance(data, dict):
        raise ValueError(f"{where + ': ' if where else ''}expected a dict of settings, got {data!r}")
    known = {f.name for f in fields(obj)}
    hints = _hints(type(obj))
    for key, value in data.items():
        if key not in known:
            note = type(obj).RETIRED.get(key)
            if note is not None:
                raise KeyError(f"{where + ': ' if where else ''}setting '{key}' is no longer here: {note}")
            raise KeyError(f"{where + ': ' if where else ''}unknown setting '{key}' (known: {sorted(known)})")
        current = getattr(obj, key)
        if is_dataclass(current) and not isinstance(value, type(current)):
            _fill(current, value, _join(where, key))
        else:
            setattr(obj, key, check_setting(value, hints[key], _join(where, key)))
    return obj


# ------------------------------------------------------------------------------ the settings
@dataclass
class CorrectionConfig(CheckedConfig):
    """Module PC: reflective masks, PRI, colour refinement maps (docs/choices.md).

    Brightness thresholds are in units of ``white_level`` (1 = the [0, 1] image range).

    Attributes:
        enabled: compute the reflective masks and the colour refinement maps at all (False: only
            AoLP, DoLP and intensity, which Dense still needs). Default True.
        specular_dolp: (low, high) DoLP range of specular pixels, inclusive, within [0, 1].
            Default and paper (0.3, 1.0).
        overexposed_dolp: (low, high) DoLP range of overexposed pixels, inclusive, within [0, 1].
            Default and paper (0.0, 0.1).
        intensity_range: (low, high) brightness range of both reflective kinds, inclusive, in
            units of the white level within [0, 1]; the brightness is the peak of the four
            polarizer-angle images (docs/choices.md "Brightness used by the reflective masks").
            Default and paper 8-bit [160, 255], i.e. (160/255, 1.0).
        mahalanobis_threshold: largest Mahalanobis distance of the (DoLP, PRI) features at which
            a non-reflective pixel donates its I_diff to an overexposed one (docs/choices.md
            "Mahalanobis features of the I_chro propagation"); > 0. Default and paper 0.8.
        propagation_radius: half size r, in pixels, of the (2r+1)^2 window in which an
            overexposed pixel looks for donors; >= 0. Default 7 (the paper does not say).
        propagation_step: the propagation window is sampled every ``propagation_step`` pixels
            each way (speed; docs/choices.md); >= 1. Default 2.
        pri_saturation: clipping level, as a fraction of the white level: an angle whose
            brightest channel reaches it is left out of PRI, and a pixel with a channel of an
            angle image there is saturated, never an I_chro donor (docs/choices.md "PRI weights
            over the four angles"); in (0, 1]. Default 254/255.
        rho_d: the constant rho_d of ``I_chro = rho_d I_prop / (sum_c I_prop + mean_c I_diff)``,
            > 0, or None: brightness-preserving, I_chro keeps the donors' colour (docs/choices.md
            "rho_d in I_chro"; the paper leaves it undefined). Default None.
        white_level: the value of a polarizer-angle image (in the units of the training colour
            s0 / 2) that an 8-bit sensor records as 255 (docs/choices.md "HDR inputs").
            Brightness thresholds are in units of it; anything above it is saturated (bright for
            the masks, never an I_chro donor). 1.0 = the [0, 1] convention, where the trainers
            clamp the colour target; > 0. Default 1.0.
        intermediate_dolp: what becomes of bright pixels whose DoLP is in neither the specular
            nor the overexposed range (docs/choices.md "Between the DoLP rules"):
            ``"by_saturation"`` (saturated -> overexposed, otherwise specular), ``"specular"``,
            ``"overexposed"`` or ``"none"`` (the paper read literally: no mask). Default
            ``"by_saturation"``.
        overexposed_rule: which pixels are overexposed (docs/choices.md "What overexposed
            means"): ``"saturated"``, those the sensor clipped (some channel of some angle image
            at ``pri_saturation * white_level``), whatever their DoLP, and a saturated pixel is
            never specular; ``"paper"``, DoLP in ``overexposed_dolp`` and brightness in
            ``intensity_range`` (with ``intermediate_dolp``), which also takes in bright,
            weakly polarized pixels the sensor did not clip (a light-coloured matte surface).
            Default ``"saturated"``.
        stokes_tolerance: noise allowance, in units of s0 times ``white_level``, for s0 < 0 and
            sqrt(s1^2 + s2^2) > s0; beyond it a pixel counts as physically impossible
            (docs/choices.md "Impossible Stokes"). Every pixel is projected onto the physical
            cone whatever its count; >= 0. Default 0.02.
        max_impossible_fraction: a view with more than this fraction of its (masked) pixels
            impossible is refused (a reader's scale or sign convention is wrong); in [0, 1].
            Default 0.05.
    """

    enabled: bool = True
    specular_dolp: tuple[float, float] = field(default=(0.3, 1.0), metadata=pair_within(0, 1))
    overexposed_dolp: tuple[float, float] = field(default=(0.0, 0.1), metadata=pair_within(0, 1))
    intensity_range: tuple[float, float] = field(default=(eight_bit(160), eight_bit(255)), metadata=pair_within(0, 1))
    mahalanobis_threshold: float = field(default=0.8, metadata=above(0))
    propagation_radius: int = field(default=7, metadata=at_least(0))
    propagation_step: int = field(default=2, metadata=at_least(1))
    pri_saturation: float = field(default=eight_bit(254), metadata=within(0, 1, low_open=True))
    rho_d: float | None = field(default=None, metadata=above(0))
    white_level: float = field(default=1.0, metadata=above(0))
    intermediate_dolp: IntermediateDolp = "by_saturation"
    overexposed_rule: OverexposedRule = "saturated"
    stokes_tolerance: float = field(default=0.02, metadata=at_least(0))
    max_impossible_fraction: float = field(default=0.05, metadata=within(0, 1))


#: Vanilla 3DGS's share of D-SSIM in its colour loss (``lambda_dssim``).
VANILLA_SSIM_WEIGHT = 0.2


@dataclass
class LossConfig(CheckedConfig):
    """Loss weights: L = L_c + alpha L_n + beta L_dn + gamma L_scale, L_c = L_non + lambda_ref L_ref.

    Iterations are the trainer's (1-based). docs/choices.md "Other loss details" defines each term.

    Attributes:
        lambda_ref: weight of the reflective-aware colour loss L_ref that replaces the plain
            colour loss on reflective pixels (docs/choices.md "lambda_ref and how L_ref replaces
            the plain colour loss"); >= 0. Default 1.0 (the paper gives no value).
        alpha_normal: weight alpha of L_n, the rendered normal against PatchMatch's; >= 0.
            Default 0.2; the paper uses 0.2 on synthetic and 0.1 on real data
            (:meth:`PolarConfig.real`).
        beta_depth_normal: weight beta of L_dn, depth-normal consistency; >= 0. Default and
            paper 0.05.
        gamma_scale: weight gamma of L_scale, the mean smallest scale (flat Gaussians); >= 0.
            Default and paper 50.
        ssim_weight: share of D-SSIM in the trainer's colour loss, ``(1 - w) L1 + w D-SSIM``,
            which L_ref's replacement cancels on reflective pixels: set it to your trainer's
            (graphdeco's, GOF's and PGSR's ``lambda_dssim``). The reference trainer's colour loss
            takes it from here; in [0, 1]. Default 0.2 (:data:`VANILLA_SSIM_WEIGHT`, vanilla 3DGS).
        depth_normal_from_iter: first iteration of L_dn; >= 0. Default and paper 7000.
        normal_until_after_dense: N_opt is refreshed only inside the Dense window, so L_n on
            every target pixel ends this many iterations after ``densify.end_iter`` (one Dense
            interval; docs/patchmatch.md "Effect"); >= 0, or None: on every target pixel to the
            end. Default 100.
        normal_hold_deg: after that, L_n holds each view's last N_opt where the rendered normal
            still lies within this many degrees of it and releases the rest (a stale target the
            model has left is either wrong or overruled); in (0, 180] (outside it L_n would hold
            nothing, or everything), or None: L_n stops. Default 10.
        use_ref: L_ref on (with ``correction.enabled``). Default True.
        use_normal: L_n on (with Dense, which provides N_opt). Default True.
        use_polar_normal: where a view's N_opt is invalid (PatchMatch confirmed nothing there:
            under-sides, recesses seen by few cameras), L_n's target is the view's own
            single-view polarimetric normal (azimuth from the AoLP, zenith from the diffuse DoLP,
            ambiguities resolved by the rendered normal; ``optics.single_view_normals``,
            docs/choices.md "Single-view polarimetric normals"), in the azimuth model of
            ``densify.patchmatch.azimuth_model``. Active only with L_n (``use_normal``, Dense on,
            once the view has an N_opt, on L_n's schedule), on pixels where the render is opaque
            (``densify.alpha_threshold``) and inside the view's mask. Default False: it has not
            been shown to help yet (the ablation decides).
        alpha_polar_normal: weight of that term (its pixels weigh ``alpha_polar_normal / (H W)``
            as L_n's weigh ``alpha_normal / (H W)``); >= 0. Default 0.1, half of ``alpha_normal``'s
            synthetic value: one view's evidence, whose zenith rests on an assumed refractive
            index, is weaker than a normal confirmed by several views.
        polar_normal_min_dolp: DoLP below which the AoLP is taken for noise and a pixel gets no
            single-view target; in [0, 1]. Default 0.02 (a diffuse surface of index 1.5 seen at
            32 degrees; an AoLP error of about 7 degrees for a DoLP error of 0.005).
        polar_normal_zenith_min_dolp: DoLP from which the zenith is read from the diffuse DoLP;
            below it, and on PC's specular and overexposed pixels, on pixels whose light the
            rendered normal calls specular, and at or above the diffuse maximum, only the azimuth
            is constrained; in [0, 1]. Default 0.05 (47 degrees at index 1.5, where a DoLP error
            of 0.005 moves the zenith by 1.8 degrees, against 3.3 at a DoLP of 0.02).
        polar_normal_refractive_index: refractive index n whose diffuse DoLP is inverted for the
            zenith; > 1. Default 1.5 (``optics.DEFAULT_REFRACTIVE_INDEX``, the value PANDORA,
            NeRSP, PolGS and NeISF assume).
        use_depth_normal: L_dn on. Default True.
        use_scale: L_scale on. Default True.
    """

    lambda_ref: float = field(default=1.0, metadata=at_least(0))
    alpha_normal: float = field(default=0.2, metadata=at_least(0))
    beta_depth_normal: float = field(default=0.05, metadata=at_least(0))
    gamma_scale: float = field(default=50.0, metadata=at_least(0))
    ssim_weight: float = field(default=VANILLA_SSIM_WEIGHT, metadata=within(0, 1))
    depth_normal_from_iter: int = field(default=7000, metadata=at_least(0))
    normal_until_after_dense: int | None = field(default=100, metadata=at_least(0))
    normal_hold_deg: float | None = field(default=10.0, metadata=within(0, 180, low_open=True, unit="degrees"))
    use_ref: bool = True
    use_normal: bool = True
    use_depth_normal: bool = True
    use_scale: bool = True
    use_polar_normal: bool = False
    alpha_polar_normal: float = field(default=0.1, metadata=at_least(0))
    polar_normal_min_dolp: float = field(default=0.02, metadata=within(0, 1))
    polar_normal_zenith_min_dolp: float = field(default=0.05, metadata=within(0, 1))
    polar_normal_refractive_index: float = field(default=1.5, metadata=above(1))


def _odd_distances(value: tuple[int, ...], config: Any) -> bool:
    return len(value) > 0 and all(k >= 1 and k % 2 == 1 for k in value)


@dataclass
class PatchMatchConfig(CheckedConfig):
    """Polar-enhanced PatchMatch (densify/patchmatch.py; docs/patchmatch.md "Cost" and "Search").

    The cost is ``S = S_c + lambda1 S_a + lambda2 S_nd``: bilateral NCC, azimuth consistency with
    the AoLP, consistency with the normal of the depth map.

    Attributes:
        num_sources: source views per reference view, chosen by triangulation angle; >= 1.
            Default 4.
        iterations: red-black propagation + refinement iterations; >= 0 (0: the best initial
            hypothesis). Default 4.
        window_radius: NCC window half size, in pixels; >= 1. Default 5.
        window_step: the NCC window is sampled every ``window_step`` pixels; >= 1. Default 2
            (36 samples).
        sigma_spatial: bilateral spatial sigma, in pixels; <= 0 means the window radius.
            Default -1.
        sigma_color: bilateral intensity sigma, in grey levels of [0, 1]; > 0. Default 0.2.
        lambda_aolp: weight lambda1 of the azimuth cost S_a; >= 0 (0: off). Default 0.02; the
            paper uses 0.02 on synthetic and 0.2 on real data (:meth:`PolarConfig.real`).
        lambda_normal_depth: weight lambda2 of S_nd; >= 0 (0: off). Default and paper 0.05.
        tau: temperature of S_a, in radians^2; > 0. Default and paper 0.1.
        sigma_dolp: sigma of the DoLP confidence omega of S_a; > 0. Default and paper 0.5.
        depth_perturbation: relative half range delta of the perturbed initial depth
            ``d (1 + U(-delta, delta))``; in [0, 1). Default 0.02.
        top_k_sources: S_c is averaged over this many best sources; >= 1. Default 2.
        propagation_distances: pixel distances of the propagation candidates, all odd (so always
            of the other checkerboard colour: no data race between threads); a non-empty list.
            Default (1, 3, 5).
        refine_depth_range: relative depth range of the random refinements in the first
            iteration (halved every iteration); >= 0. Default 0.05.
        refine_normal_deg: normal angle of the random refinements in the first iteration, in
            degrees (halved every iteration); in [0, 180]. Default 20.
        azimuth_model: how a normal's azimuth is compared with the AoLP (:data:`AzimuthModel`).
            Default ``"orthographic"`` (docs/conventions.md); :meth:`PolarConfig.synthetic`
            sets ``"perspective"``.
        ncc_backend: cost backend (:data:`NccBackend`); the same costs either way (to ~1e-5).
            Default ``"auto"``.
        chunk_elements: memory bound of the torch backend, in window samples per chunk; >= 1.
            Default 2^22.
        seed: seed of Dense's own random generator (any integer). Default 0.
    """

    num_sources: int = field(default=4, metadata=at_least(1))
    iterations: int = field(default=4, metadata=at_least(0))
    window_radius: int = field(default=5, metadata=at_least(1))
    window_step: int = field(default=2, metadata=at_least(1))
    sigma_spatial: float = -1.0
    sigma_color: float = field(default=0.2, metadata=above(0))
    lambda_aolp: float = field(default=0.02, metadata=at_least(0))
    lambda_normal_depth: float = field(default=0.05, metadata=at_least(0))
    tau: float = field(default=0.1, metadata=above(0))
    sigma_dolp: float = field(default=0.5, metadata=above(0))
    depth_perturbation: float = field(default=0.02, metadata=within(0, 1, high_open=True))
    top_k_sources: int = field(default=2, metadata=at_least(1))
    propagation_distances: tuple[int, ...] = field(
        default=(1, 3, 5), metadata=satisfies(_odd_distances, "a non-empty list of odd positive integers")
    )
    refine_depth_range: float = field(default=0.05, metadata=at_least(0))
    refine_normal_deg: float = field(default=20.0, metadata=within(0, 180, unit="degrees"))
    azimuth_model: AzimuthModel = "orthographic"
    ncc_backend: NccBackend = "auto"
    chunk_elements: int = field(default=1 << 22, metadata=at_least(1))
    seed: int = 0


@dataclass
class FilterConfig(CheckedConfig):
    """Multi-view geometric and polarimetric consistency filters (densify/filters.py;
    docs/patchmatch.md "Filters").

    Attributes:
        max_reprojection_px: largest forward-backward reprojection error, in pixels, of a
            consistent source; >= 0. Default 1.
        max_relative_depth: largest relative depth error of a consistent source; >= 0.
            Default 0.01.
        min_consistent_views: a pixel is kept when at least this many sources are consistent;
            >= 0 (0: no multi-view test). Default 2.
        max_polar_residual: largest mean polarimetric residual ``sum_j w_j |sin 2 (phi_pred -
            phi_obs)| / k`` (our definition; the paper names it without a formula); >= 0.
            Default 0.3 (about 8.7 degrees at full confidence).
        use_polar: apply the polarimetric test. Default True.
        polar_dolp_reference: DoLP at which a source's AoLP gets full confidence
            ``w_j = clip(rho_j / polar_dolp_reference, 0, 1)``; > 0. Default 0.1.
        azimuth_model: as :attr:`PatchMatchConfig.azimuth_model`. Default ``"orthographic"``;
            :meth:`PolarConfig.synthetic` sets ``"perspective"``.
        max_photometric_cost: the densifier keeps only pixels whose PatchMatch photometric cost
            (1 - NCC, in [0, 2]) is at most this; in [0, 2]. Default 0.9 (COLMAP's minimum NCC 0.1).
        max_incidence_deg: a view supports a pixel only when it sees the pixel's surface (the
            point and its normal) from its front at an incidence angle below this: a source
            counts as consistent only then, and the reference view's own pixel is kept only then
            (docs/patchmatch.md "Filters"); in (0, 90], or None: no such test. Default None.
    """

    max_reprojection_px: float = field(default=1.0, metadata=at_least(0))
    max_relative_depth: float = field(default=0.01, metadata=at_least(0))
    min_consistent_views: int = field(default=2, metadata=at_least(0))
    max_polar_residual: float = field(default=0.3, metadata=at_least(0))
    use_polar: bool = True
    polar_dolp_reference: float = field(default=0.1, metadata=above(0))
    azimuth_model: AzimuthModel = "orthographic"
    max_photometric_cost: float = field(default=0.9, metadata=within(0, 2))
    max_incidence_deg: float | None = field(default=None, metadata=within(0, 90, low_open=True))


@dataclass
class DensifyConfig(CheckedConfig):
    """Module Dense: schedule and seeding (docs/patchmatch.md "Seeding" and "Densifier").

    Attributes:
        enabled: run Dense at all. Default True.
        start_iter: first iteration of the Dense window; >= 0. Dense runs at the iterations
            ``start_iter <= it <= end_iter`` with ``it % interval == 0``. Default and paper 1000.
        end_iter: last iteration of the Dense window; >= ``start_iter``. Default and paper 7000.
        interval: iterations between Dense calls; >= 1. Default and paper 100.
        stride: seeds on every ``stride``-th pixel each way; >= 1. Default 2.
        max_new_per_call: at most this many new Gaussians a call (a random subset); >= 0.
            Default 5000.
        budget_fraction: all calls together append at most this fraction of the number of
            Gaussians the model had at the first Dense call (a random subset of a call's seeds
            once the budget runs short; PatchMatch and L_n's targets go on); >= 0, or None: no
            budget beyond ``max_new_per_call``. Default None.
        initial_opacity: the seeded Gaussians' opacity; in (0, 1). Default 0.5.
        alpha_threshold: rendered alpha below which a pixel is a hole (seeded); above it a source
            view's rendered depth serves the consistency filters; in [0, 1]. Default 0.5.
        seed_depth_footprints: how far, in pixel footprints (depth / focal), the rendered surface
            must lie behind PatchMatch's to count as wrong (either side with
            ``seed_behind_surface``); >= 0. 2.5: 1.4 % of the depth at the bundled scenes'
            128 px, 5.7 % at 40 px. A regularised model's render commonly lies one or two
            footprints behind the true surface where the surface is dim and uniform or seen by few
            views; seeds there become a second layer that training turns into haze in front of
            the surface, so only a clearly wrong render (a recess, a missing part) is seeded.
            Lower values (about one footprint) also seed a shallow recess and help on textured
            shiny objects seen by many views (docs/patchmatch.md "Seeding"). The paper seeds every
            pixel that passes the filters. Default 2.5.
        seed_max_plane_deviation: seeds only where the 3x3 neighbours' PatchMatch depths stay on
            the pixel's PatchMatch plane within this fraction of its depth (occlusion edges
            fail); >= 0, or None: no such test. Default 0.04.
        seed_behind_surface: also seed where PatchMatch's depth lies *behind* an opaque rendered
            surface. Off by default: the seed would be hidden in its own view, and on a glossy
            surface PatchMatch matches the mirror image behind it (docs/patchmatch.md "Seeding").
        thin_scale_ratio: a seed's scale along its normal, as a fraction of its tangent scales
            (the normal stays the shortest axis); in (0, 1]. Default 0.1.
        use_view_mask: PatchMatch only inside the view's object mask, where it has one.
            Default True.
        patchmatch: the search (:class:`PatchMatchConfig`).
        filters: the multi-view consistency filters (:class:`FilterConfig`).
    """

    enabled: bool = True
    start_iter: int = field(default=1000, metadata=at_least(0))
    end_iter: int = field(default=7000, metadata=not_below("start_iter"))
    interval: int = field(default=100, metadata=at_least(1))
    stride: int = field(default=2, metadata=at_least(1))
    max_new_per_call: int = field(default=5000, metadata=at_least(0))
    budget_fraction: float | None = field(default=None, metadata=at_least(0))
    initial_opacity: float = field(default=0.5, metadata=within(0, 1, low_open=True, high_open=True))
    alpha_threshold: float = field(default=0.5, metadata=within(0, 1))
    seed_depth_footprints: float = field(default=2.5, metadata=at_least(0))
    seed_max_plane_deviation: float | None = field(default=0.04, metadata=at_least(0))
    seed_behind_surface: bool = False
    thin_scale_ratio: float = field(default=0.1, metadata=within(0, 1, low_open=True))
    use_view_mask: bool = True
    patchmatch: PatchMatchConfig = field(default_factory=PatchMatchConfig)
    filters: FilterConfig = field(default_factory=FilterConfig)


@dataclass
class PolarConfig(CheckedConfig):
    """All PolarGS settings. Defaults are the paper's synthetic-data values.

    Attributes:
        correction: module PC (:class:`CorrectionConfig`).
        losses: the loss weights and schedules (:class:`LossConfig`).
        densify: module Dense (:class:`DensifyConfig`).
        cache_dir: folder where ``PolarHooks.preprocess`` caches each view's maps (keyed by
            their inputs and the correction settings), or None: no cache. Default None.
    """

    correction: CorrectionConfig = field(default_factory=CorrectionConfig)
    losses: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    cache_dir: str | None = None

    RETIRED: ClassVar[dict[str, str]] = {
        "refractive_index": "nothing read it (the bundled scenes' generator takes its own, `polargs generate --ior`; "
                            "the single-view polarimetric normal's is losses.polar_normal_refractive_index); "
                            "remove it from the settings",
    }

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
        return cfg.validate()

    @classmethod
    def real(cls) -> "PolarConfig":
        """Paper values for real captures: lambda1 = 0.2, alpha = 0.1."""
        cfg = cls()
        cfg.densify.patchmatch.lambda_aolp = 0.2
        cfg.losses.alpha_normal = 0.1
        return cfg.validate()

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
        return cfg.validate()


# ------------------------------------------------------------------------------ kinds
_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "null"}
_PLURALS = {bool: "true / false values", int: "integers", float: "numbers", str: "strings"}


def _options(hint: Any) -> tuple[list[Any], bool]:
    """(the hint's non-None options, whether None is allowed)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        return [a for a in args if a is not type(None)], type(None) in args
    return [hint], hint is type(None)


def _is_integer(hint: Any) -> bool:
    return _options(hint)[0] == [int]


def _kind(hint: Any) -> str:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_kind(h) for h in typing.get_args(hint))
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if origin is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_PLURALS.get(args[0], _kind(args[0]))}"
        return f"a list of {len(args)} ({', '.join(_kind(a) for a in args)})"
    if isinstance(hint, type) and is_dataclass(hint):
        return f"{hint.__name__} settings"
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
    if origin is Literal:
        return any(type(value) is type(a) and value == a for a in typing.get_args(hint)), value
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
        return isinstance(value, numbers.Integral) and not isinstance(value, bool), value
    if hint is float:
        number = isinstance(value, numbers.Real) and not isinstance(value, bool) and not math.isnan(value)
        return number, float(value) if number else value
    if hint is str:
        return isinstance(value, str), value
    if hint is type(None):
        return value is None, value
    if isinstance(hint, type) and is_dataclass(hint):
        return isinstance(value, hint), value
    return True, value  # other annotations are not checked here


def check_setting(value: Any, hint: Any, where: str) -> Any:
    """``value`` as a field annotated ``hint`` holds it (a list becomes a tuple, an int in a float
    field a float); ValueError naming ``where``, the expected kind and the value otherwise.

    Checked: bool, int, float (not NaN), str, None, ``Literal`` choices, settings dataclasses,
    their unions (``float | None``) and tuples (``tuple[float, float]``, ``tuple[int, ...]``);
    other annotations pass unchecked. Ranges are the fields' own (:meth:`CheckedConfig.validate`).

    >>> check_setting([1, 2.5], tuple[float, float], "correction.specular_dolp")
    (1.0, 2.5)
    >>> check_setting("0.1", float | None, "densify.seed_max_plane_deviation")
    Traceback (most recent call last):
    ...
    ValueError: densify.seed_max_plane_deviation: expected a number or null, got '0.1'
    >>> check_setting("ortho", AzimuthModel, "densify.patchmatch.azimuth_model")
    Traceback (most recent call last):
    ...
    ValueError: densify.patchmatch.azimuth_model: expected one of 'orthographic', 'perspective', got 'ortho'
    """
    ok, converted = _fits(value, hint)
    if not ok:
        raise ValueError(f"{where}: expected {_kind(hint)}, got {value!r}")
    return converted
