"""Reflective regions from DoLP and brightness (PolarGS module PC).

Specular pixels are strongly polarized and bright; overexposed pixels are bright but lost their
polarization to clipping. Both thresholds come from ``CorrectionConfig`` in [0, 1] units (the
paper's 8-bit 160..255 divided by 255).

Brightness is the *peak intensity*: the brightest of the four polarizer-angle images of the
channel-mean colour. Overexposure first shows in the brightest angle, and the channel mean keeps
saturated but unclipped diffuse colours (a bright red) from counting as overexposed.

Inputs that are not 8-bit LDR (docs/choices.md "HDR inputs"): brightness is measured in units of
a white level (``CorrectionConfig.white_level``, the value an 8-bit sensor records as 255);
anything above it is *saturated* and counts as 255, so highlight cores above the white level are
bright, not excluded. Pixels bright enough for the masks but with a DoLP between the two rules
(the paper is silent on them) are assigned by ``intermediate`` (:data:`INTERMEDIATE_CHOICES`).
"""

from __future__ import annotations

import typing

import torch
from torch import Tensor

from polargs_plugin.config import IntermediateDolp

__all__ = ["peak_intensity", "reflective_masks", "INTERMEDIATE_CHOICES"]

#: What happens to bright pixels whose DoLP lies between the overexposed and the specular rule:
#: "none" (the paper read literally: neither mask), "specular", "overexposed", or
#: "by_saturation" (saturated -> overexposed, unsaturated -> specular; the default): the values of
#: ``CorrectionConfig.intermediate_dolp``.
INTERMEDIATE_CHOICES: tuple[str, ...] = typing.get_args(IntermediateDolp)

# Inclusive range ends tolerate float32 rounding of 8-bit values (160 / 255 stored as float32).
_RANGE_TOL = 1e-6


def peak_intensity(stokes: Tensor) -> Tensor:
    r"""Brightest polarizer-angle image of the channel-mean colour.

    .. math:: P = \max_{\beta \in \{0, 45, 90, 135\}} \operatorname{mean}_c I_c(\beta)

    Args:
        stokes: :math:`(*, 3, C, H, W)` Stokes (s0, s1, s2).

    Returns:
        :math:`(*, 1, H, W)` peak intensity in the units of the angle images ([0, 1]).

    Example:
        >>> s = torch.tensor([1.0, 0.5, 0.0]).reshape(3, 1, 1, 1)  # I0 = 0.75
        >>> peak_intensity(s).flatten()
        tensor([0.7500])
    """
    # Malus is linear, so the channel mean commutes with it; over 0/45/90/135 deg the brightest
    # of (s0 +- s1) / 2, (s0 +- s2) / 2 is (s0 + max(|s1|, |s2|)) / 2.
    s0, s1, s2 = stokes.mean(dim=-3, keepdim=True).unbind(dim=-4)
    return (s0 + torch.maximum(s1.abs(), s2.abs())) / 2


def _in_range(x: Tensor, bounds: tuple[float, float]) -> Tensor:
    low, high = bounds
    return (x >= low - _RANGE_TOL) & (x <= high + _RANGE_TOL)


def reflective_masks(
    dolp: Tensor,
    peak: Tensor,
    specular_dolp: tuple[float, float] = (0.3, 1.0),
    overexposed_dolp: tuple[float, float] = (0.0, 0.1),
    intensity_range: tuple[float, float] = (160 / 255, 1.0),
    *,
    white_level: float = 1.0,
    intermediate: IntermediateDolp = "by_saturation",
    saturated: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Specular and overexposed masks (inclusive ranges).

    Brightness is ``min(peak / white_level, 1)``: a value above the white level is saturated and
    counts as full scale (an 8-bit sensor would record 255 there).

    - specular: DoLP in ``specular_dolp`` and brightness in ``intensity_range``;
    - overexposed: DoLP in ``overexposed_dolp`` and brightness in ``intensity_range``;
    - bright pixels in neither DoLP range: by ``intermediate`` (:data:`INTERMEDIATE_CHOICES`);
      with ``"by_saturation"`` a saturated one (its colour is clipped) is overexposed, an
      unsaturated one specular.

    Args:
        dolp: :math:`(*, 1, H, W)` DoLP in [0, 1].
        peak: :math:`(*, 1, H, W)` brightness (see :func:`peak_intensity`), white = ``white_level``.
        specular_dolp: DoLP range of specular pixels.
        overexposed_dolp: DoLP range of overexposed pixels.
        intensity_range: brightness range shared by both, in units of the white level.
        white_level: the peak value that maps to 8-bit 255 (1 for [0, 1] LDR data).
        intermediate: treatment of bright pixels between the two DoLP rules.
        saturated: optional :math:`(*, 1, H, W)` bool, pixels whose colour is clipped (e.g. some
            channel of some angle image at the clipping level); default: peak >= white level.

    Returns:
        ``(specular, overexposed)``, each :math:`(*, 1, H, W)` bool.

    Example:
        >>> spec, over = reflective_masks(torch.tensor([0.5, 0.05, 0.5]), torch.tensor([0.9, 0.9, 0.2]))
        >>> spec.tolist(), over.tolist()
        ([True, False, False], [False, True, False])
    """
    if dolp.shape != peak.shape:
        raise ValueError(f"dolp {tuple(dolp.shape)} and peak {tuple(peak.shape)} must have the same shape")
    if intermediate not in INTERMEDIATE_CHOICES:
        raise ValueError(f"intermediate must be one of {INTERMEDIATE_CHOICES}, got {intermediate!r}")
    if not white_level > 0:
        raise ValueError(f"white_level must be > 0, got {white_level}")
    level = peak / white_level
    bright = _in_range(level.clamp(max=1.0), intensity_range)
    specular = bright & _in_range(dolp, specular_dolp)
    overexposed = bright & _in_range(dolp, overexposed_dolp)
    if intermediate != "none":
        between = bright & ~specular & ~overexposed
        if intermediate == "specular":
            specular = specular | between
        elif intermediate == "overexposed":
            overexposed = overexposed | between
        else:
            if saturated is None:
                saturated = level >= 1.0 - _RANGE_TOL
            overexposed = overexposed | (between & saturated)
            specular = specular | (between & ~saturated)
    return specular, overexposed
