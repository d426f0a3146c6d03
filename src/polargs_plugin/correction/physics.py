"""Physical validity of Stokes images and the input range (docs/choices.md "Impossible Stokes").

Light has ``s0 >= 0`` and ``s1^2 + s2^2 <= s0^2`` (DoLP <= 1). Measured Stokes break both by
noise (dark pixels, quantisation); a *convention or scale error* of a reader (s1 and s2 at twice
the scale of s0, a black level not subtracted) breaks them on a large share of the image.

:func:`physical_stokes` counts the pixels that break either rule by more than a tolerance and
returns the Stokes projected onto the physical cone (``s0`` clamped at 0, then ``(s1, s2)``
scaled down to length ``s0``), so every map computed from them has DoLP in [0, 1]. The caller
(``PolarHooks.preprocess``) reports the counts per view and refuses a view whose share of
impossible pixels exceeds ``CorrectionConfig.max_impossible_fraction``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["StokesCheck", "physical_stokes", "input_range"]


@dataclass
class StokesCheck:
    """Counts of physically impossible pixels (a pixel counts once whatever its channels).

    Attributes:
        negative: pixels with ``s0 < -tolerance`` in some channel.
        over_polarized: pixels with ``sqrt(s1^2 + s2^2) > s0 + tolerance`` in some channel.
        impossible: pixels with either (inside the mask when one was given).
        total: pixels considered (the mask's area, or H W).
    """

    negative: int
    over_polarized: int
    impossible: int
    total: int

    @property
    def fraction(self) -> float:
        return self.impossible / max(self.total, 1)


def physical_stokes(stokes: Tensor, tolerance: float, mask: Tensor | None = None) -> tuple[Tensor, StokesCheck]:
    r"""Project Stokes onto the physical cone and count the pixels beyond ``tolerance``.

    Clamping (every pixel, any size of violation): :math:`s_0 \leftarrow \max(s_0, 0)`; where
    :math:`m = \sqrt{s_1^2 + s_2^2} > s_0`, :math:`(s_1, s_2) \leftarrow (s_1, s_2)\, s_0 / m`
    (AoLP kept, DoLP set to 1; a pixel with :math:`s_0 = 0` becomes unpolarized black).

    Args:
        stokes: :math:`(3, C, H, W)` Stokes.
        tolerance: noise allowance in the units of ``s0`` (violations up to it are not counted,
            but still clamped).
        mask: optional :math:`(1, H, W)` bool; only its pixels are counted.

    Returns:
        ``(clamped, check)``: the clamped Stokes (the input itself when nothing needed clamping)
        and the :class:`StokesCheck`.

    Example:
        >>> s = torch.tensor([[1.0, -0.5], [2.0, 0.0], [0.0, 0.0]]).reshape(3, 1, 1, 2)
        >>> clamped, check = physical_stokes(s, tolerance=0.01)
        >>> clamped.flatten().tolist(), check.impossible
        ([1.0, 0.0, 1.0, 0.0, 0.0, 0.0], 2)
    """
    s0, s1, s2 = stokes.unbind(0)
    magnitude = torch.hypot(s1, s2)
    negative = (s0 < -tolerance).any(dim=0, keepdim=True)  # (1, H, W)
    over = (magnitude > s0.clamp_min(0) + tolerance).any(dim=0, keepdim=True)
    considered = torch.ones_like(negative) if mask is None else mask.to(torch.bool).reshape(negative.shape)
    check = StokesCheck(
        negative=int((negative & considered).sum()),
        over_polarized=int((over & considered).sum()),
        impossible=int(((negative | over) & considered).sum()),
        total=int(considered.sum()),
    )
    positive = s0.clamp_min(0)
    excess = magnitude > positive
    if not bool((s0 < 0).any()) and not bool(excess.any()):
        return stokes, check
    scale = torch.where(excess, positive / torch.where(excess, magnitude, torch.ones_like(magnitude)), torch.ones_like(magnitude))
    return torch.stack([positive, s1 * scale, s2 * scale]), check


def input_range(stokes: Tensor) -> tuple[float, float]:
    """``(min, max)`` of the training colour s0 / 2, the mean of the four angle images: within
    [0, 1] for any LDR capture (the brightest angle re-synthesised from Stokes by Malus may exceed
    1 at clipped pixels of LDR data, so it is not the test)."""
    half = stokes[0] / 2
    return float(half.min()), float(half.max())
