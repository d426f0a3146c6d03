"""Polarimetric Reference Intensity (PRI): a specular-invariant colour cue.

Under a white illuminant the specular reflection adds the same amount to every colour channel, so
the spread ``max_c I - min_c I`` of one polarizer-angle image does not see it: it depends on the
diffuse colour only. PRI is that spread, per angle, then averaged over the four angles.

Weights (docs/choices.md): uniform over the angles whose brightest channel is below the clipping
level, uniform over all four where every angle clips. A clipped channel shrinks the spread, so
clipped angles are dropped (as PANDORA drops the brightest angle before fitting Stokes); and for
unclipped pixels the uniform mean over 0/45/90/135 cancels the cos(2 beta - 2 phi) modulation of
a weakly polarized diffuse component exactly, leaving the spread of the unpolarized colour.
"""

from __future__ import annotations

from functools import reduce

import torch
from torch import Tensor

__all__ = ["pri_per_angle", "clipped_angles", "pri_weights", "polarimetric_reference_intensity", "pri_with_clipping"]


def pri_per_angle(intensities: Tensor) -> Tensor:
    r"""Channel spread of each polarizer-angle image, :math:`\max_c I - \min_c I`.

    Args:
        intensities: :math:`(*, A, C, H, W)` angle images.

    Returns:
        :math:`(*, A, H, W)`; 0 for mono images (C = 1).

    Example:
        >>> i = torch.tensor([0.9, 0.5, 0.2]).reshape(1, 3, 1, 1)
        >>> pri_per_angle(i).flatten()
        tensor([0.7000])
    """
    high, low = _channel_max_min(intensities)
    return high - low


def _channel_max_min(intensities: Tensor) -> tuple[Tensor, Tensor]:
    # Elementwise over the few channels: much faster than a reduction over the strided dim -3.
    channels = intensities.unbind(dim=-3)
    return reduce(torch.maximum, channels), reduce(torch.minimum, channels)


def clipped_angles(intensities: Tensor, saturation: float) -> Tensor:
    """Angles whose brightest channel reaches ``saturation``.

    Args:
        intensities: :math:`(*, A, C, H, W)` angle images in [0, 1].
        saturation: clipping level in [0, 1].

    Returns:
        :math:`(*, A, H, W)` bool.
    """
    return _channel_max_min(intensities)[0] >= saturation


def pri_weights(intensities: Tensor, saturation: float) -> Tensor:
    r"""Per-angle PRI weights: uniform over unclipped angles (all angles if every one clips).

    An angle is clipped at a pixel when its brightest channel reaches ``saturation``.

    Args:
        intensities: :math:`(*, A, C, H, W)` angle images in [0, 1].
        saturation: clipping level in [0, 1].

    Returns:
        :math:`(*, A, H, W)` non-negative weights summing to 1 over A.

    Example:
        >>> i = torch.tensor([1.0, 0.8, 0.6, 0.8]).reshape(4, 1, 1, 1)
        >>> pri_weights(i, saturation=0.99).flatten()
        tensor([0.0000, 0.3333, 0.3333, 0.3333])
    """
    return _normalise_weights((~clipped_angles(intensities, saturation)).to(intensities.dtype))


def _normalise_weights(unclipped: Tensor) -> Tensor:
    count = unclipped.sum(dim=-3, keepdim=True)
    uniform = 1.0 / unclipped.shape[-3]
    return (unclipped / count.clamp_min(1.0)).where(count > 0, unclipped.new_full((), uniform))


def polarimetric_reference_intensity(intensities: Tensor, saturation: float = 254 / 255) -> Tensor:
    r"""PRI: the weighted mean over angles of :func:`pri_per_angle` (weights :func:`pri_weights`).

    Args:
        intensities: :math:`(*, A, C, H, W)` angle images in [0, 1].
        saturation: clipping level in [0, 1].

    Returns:
        :math:`(*, 1, H, W)` PRI in [0, 1].

    Example:
        >>> i = torch.tensor([[1.0, 1.0, 1.0], [0.9, 0.5, 0.3]]).reshape(2, 3, 1, 1)
        >>> polarimetric_reference_intensity(i, saturation=0.99).flatten()  # clipped angle 0 dropped
        tensor([0.6000])
    """
    return pri_with_clipping(intensities, saturation)[0]


def pri_with_clipping(intensities: Tensor, saturation: float = 254 / 255) -> tuple[Tensor, Tensor]:
    """:func:`polarimetric_reference_intensity` and where every angle clips, in one pass.

    Args:
        intensities: :math:`(*, A, C, H, W)` angle images in [0, 1].
        saturation: clipping level in [0, 1].

    Returns:
        ``(pri, all_clipped)``, :math:`(*, 1, H, W)` float and bool.
    """
    # One angle at a time keeps every temporary at one (H, W) plane per batch item.
    unclipped_sum = spread_sum = count = None
    for angle in intensities.unbind(dim=-4):
        high, low = _channel_max_min(angle)
        spread = high - low
        unclipped = high < saturation
        if count is None:
            unclipped_sum, spread_sum, count = spread * unclipped, spread, unclipped.to(spread.dtype)
        else:
            unclipped_sum = unclipped_sum + spread * unclipped
            spread_sum = spread_sum + spread
            count = count + unclipped
    all_clipped = count == 0
    pri = torch.where(all_clipped, spread_sum / intensities.shape[-4], unclipped_sum / count.clamp_min(1.0))
    return pri.unsqueeze(-3), all_clipped.unsqueeze(-3)
