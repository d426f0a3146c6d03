"""Reflective regions from DoLP and brightness (PolarGS module PC).

Specular pixels are strongly polarized and bright; overexposed pixels are bright but lost their
polarization to clipping. Both thresholds come from ``CorrectionConfig`` in [0, 1] units (the
paper's 8-bit 160..255 divided by 255).

Brightness is the *peak intensity*: the brightest of the four polarizer-angle images of the
channel-mean colour. Overexposure first shows in the brightest angle, and the channel mean keeps
saturated but unclipped diffuse colours (a bright red) from counting as overexposed.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["peak_intensity", "reflective_masks"]

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
) -> tuple[Tensor, Tensor]:
    r"""Specular and overexposed masks (inclusive ranges).

    - specular: DoLP in ``specular_dolp`` and peak intensity in ``intensity_range``;
    - overexposed: DoLP in ``overexposed_dolp`` and peak intensity in ``intensity_range``.

    Args:
        dolp: :math:`(*, 1, H, W)` DoLP in [0, 1].
        peak: :math:`(*, 1, H, W)` brightness in [0, 1] (see :func:`peak_intensity`).
        specular_dolp: DoLP range of specular pixels.
        overexposed_dolp: DoLP range of overexposed pixels.
        intensity_range: brightness range shared by both.

    Returns:
        ``(specular, overexposed)``, each :math:`(*, 1, H, W)` bool.

    Example:
        >>> spec, over = reflective_masks(torch.tensor([0.5, 0.05, 0.5]), torch.tensor([0.9, 0.9, 0.2]))
        >>> spec.tolist(), over.tolist()
        ([True, False, False], [False, True, False])
    """
    if dolp.shape != peak.shape:
        raise ValueError(f"dolp {tuple(dolp.shape)} and peak {tuple(peak.shape)} must have the same shape")
    bright = _in_range(peak, intensity_range)
    return bright & _in_range(dolp, specular_dolp), bright & _in_range(dolp, overexposed_dolp)
