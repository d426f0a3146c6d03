"""Linear Stokes vectors from polarizer-angle images, and the quantities derived from them.

Conventions (docs/conventions.md), pinned by tests:

- Malus: I(beta) = (s0 + s1 cos 2beta + s2 sin 2beta) / 2, so s0 is the full intensity.
- Four angles 0/45/90/135 deg: s0 = (I0 + I45 + I90 + I135) / 2, s1 = I0 - I90, s2 = I45 - I135.
- AoLP = atan2(s2, s1) / 2 wrapped (never clipped) into [0, pi), counter-clockwise on screen
  from image +x towards image up.

Tensors carry the polarizer-angle axis (size A) or the Stokes axis (size 3) at dim -4, in front
of (C, H, W); any leading batch dimensions are allowed. Results keep the input dtype and device.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = [
    "POLARIZER_ANGLES_DEG",
    "POLARIZER_ANGLES_RAD",
    "stokes_from_intensities",
    "intensities_from_stokes",
    "aolp_from_stokes",
    "dolp_from_stokes",
    "linear_magnitude",
    "imax_imin_from_stokes",
    "wrap_angle",
]

#: Polarizer angles of a division-of-focal-plane sensor, in the order of the angle axis.
POLARIZER_ANGLES_DEG = (0, 45, 90, 135)
POLARIZER_ANGLES_RAD = tuple(math.radians(a) for a in POLARIZER_ANGLES_DEG)
# s0 = (I0 + I45 + I90 + I135) / 2, s1 = I0 - I90, s2 = I45 - I135 (rows; columns = angles).
_CLOSED_FORM = ((0.5, 0.5, 0.5, 0.5), (1.0, 0.0, -1.0, 0.0), (0.0, 1.0, 0.0, -1.0))


def wrap_angle(angle: Tensor, period: float = math.pi) -> Tensor:
    """Wrap angles into ``[0, period)`` (modulo, never clipping).

    ``torch.remainder`` can round up to exactly ``period`` for tiny negative inputs; those are
    folded back to 0 so the half-open range holds in every dtype.

    Args:
        angle: angles in radians, shape :math:`(*)`.
        period: the period, pi for AoLP, 2 pi for azimuths.

    Returns:
        :math:`(*)` angles in ``[0, period)``.

    Example:
        >>> wrap_angle(torch.tensor([-0.5, 3.5]), 3.0)
        tensor([2.5000, 0.5000])
    """
    wrapped = torch.remainder(angle, period)
    return torch.where(wrapped >= period, wrapped - period, wrapped)


def _check_angle_axis(x: Tensor, name: str, expected: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 4:
        raise ValueError(f"{name} must have shape {expected}, got {tuple(x.shape)}")


def _angles_tensor(angles_rad: Sequence[float] | Tensor, like: Tensor) -> Tensor:
    angles = torch.as_tensor(angles_rad, dtype=torch.float64).to(like.device).reshape(-1)
    if angles.numel() < 3:
        raise ValueError(
            f"at least 3 polarizer angles are needed to recover (s0, s1, s2), got {angles.numel()}"
        )
    return angles


def _malus_matrix(angles: Tensor) -> Tensor:
    """(A, 3) float64 rows (1, cos 2b, sin 2b) / 2."""
    return 0.5 * torch.stack([torch.ones_like(angles), torch.cos(2 * angles), torch.sin(2 * angles)], dim=-1)


def stokes_from_intensities(intensities: Tensor, angles_rad: Sequence[float] | Tensor | None = None) -> Tensor:
    r"""Linear Stokes vector from images taken behind linear polarizers.

    With ``angles_rad=None`` the four images are at 0/45/90/135 deg and the closed form
    :math:`s_0 = (I_0+I_{45}+I_{90}+I_{135})/2,\ s_1 = I_0 - I_{90},\ s_2 = I_{45} - I_{135}`
    is used. Otherwise the least-squares solution :math:`s = A^+ I` with rows
    :math:`A_k = \tfrac12[1, \cos 2\beta_k, \sin 2\beta_k]` (equal to the closed form for the
    four standard angles).

    Args:
        intensities: :math:`(*, A, C, H, W)` images, one per polarizer angle.
        angles_rad: ``A`` polarizer angles in radians (A >= 3, not all equal modulo pi), or
            ``None`` for the standard four.

    Returns:
        :math:`(*, 3, C, H, W)` Stokes (s0, s1, s2).

    Raises:
        ValueError: fewer than 3 angles, an angle count that does not match dim -4, or angles
            that do not determine the Stokes vector.

    Example:
        >>> i = torch.tensor([1.0, 0.5, 0.0, 0.5]).reshape(4, 1, 1, 1)
        >>> stokes_from_intensities(i).flatten()
        tensor([1., 1., 0.])
    """
    _check_angle_axis(intensities, "intensities", "(..., A, C, H, W)")
    count = intensities.shape[-4]
    if angles_rad is None:
        if count != 4:
            raise ValueError(
                f"without angles_rad the angle axis (dim -4) must hold 0/45/90/135 deg, got size {count}"
            )
        # One pass over the images (a matrix product) instead of an expression per component.
        solve = torch.tensor(_CLOSED_FORM, dtype=intensities.dtype, device=intensities.device)
        return torch.einsum("sa,...achw->...schw", solve, intensities)
    angles = _angles_tensor(angles_rad, intensities)
    if angles.numel() != count:
        raise ValueError(f"{angles.numel()} angles given but the angle axis (dim -4) has size {count}")
    matrix = _malus_matrix(angles)
    if torch.linalg.matrix_rank(matrix) < 3:
        raise ValueError("the polarizer angles do not determine (s0, s1, s2): use 3 distinct angles modulo pi")
    solve = torch.linalg.pinv(matrix).to(intensities.dtype)  # (3, A)
    return torch.einsum("sa,...achw->...schw", solve, intensities)


def intensities_from_stokes(stokes: Tensor, angles_rad: Sequence[float] | Tensor | None = None) -> Tensor:
    r"""Malus forward model: the image seen behind a linear polarizer at each angle.

    .. math:: I(\beta) = \tfrac12 (s_0 + s_1\cos 2\beta + s_2\sin 2\beta)

    Args:
        stokes: :math:`(*, 3, C, H, W)` Stokes (s0, s1, s2).
        angles_rad: polarizer angles in radians (any count >= 1), ``None`` for 0/45/90/135 deg.

    Returns:
        :math:`(*, A, C, H, W)` intensities.

    Example:
        >>> s = torch.tensor([1.0, 1.0, 0.0]).reshape(3, 1, 1, 1)
        >>> intensities_from_stokes(s).flatten()
        tensor([1.0000, 0.5000, 0.0000, 0.5000])
    """
    _check_stokes(stokes)
    angles = torch.as_tensor(POLARIZER_ANGLES_RAD if angles_rad is None else angles_rad, dtype=torch.float64)
    angles = angles.to(stokes.device).reshape(-1)
    if angles.numel() == 0:
        raise ValueError("angles_rad is empty")
    matrix = _malus_matrix(angles).to(stokes.dtype)  # (A, 3)
    return torch.einsum("as,...schw->...achw", matrix, stokes)


def _check_stokes(stokes: Tensor) -> None:
    _check_angle_axis(stokes, "stokes", "(..., 3, C, H, W)")
    if stokes.shape[-4] != 3:
        raise ValueError(f"stokes must have 3 components (s0, s1, s2) at dim -4, got shape {tuple(stokes.shape)}")


def linear_magnitude(stokes: Tensor) -> Tensor:
    r"""Polarized intensity :math:`\sqrt{s_1^2 + s_2^2}` with a finite gradient at 0.

    Args:
        stokes: :math:`(*, 3, C, H, W)`.

    Returns:
        :math:`(*, C, H, W)`.

    Example:
        >>> linear_magnitude(torch.tensor([2.0, 0.3, 0.4]).reshape(3, 1, 1, 1)).flatten()
        tensor([0.5000])
    """
    _check_stokes(stokes)
    s1, s2 = stokes.select(-4, 1), stokes.select(-4, 2)
    squared = s1 * s1 + s2 * s2
    # Double where: exact 0 for unpolarized pixels, and a zero (not NaN) gradient there.
    positive = squared > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, squared, torch.ones_like(squared))), 0.0)


def aolp_from_stokes(stokes: Tensor) -> Tensor:
    r"""Angle of linear polarization :math:`\tfrac12\,\mathrm{atan2}(s_2, s_1)` wrapped into [0, pi).

    Args:
        stokes: :math:`(*, 3, C, H, W)`.

    Returns:
        :math:`(*, C, H, W)` AoLP in radians, ccw on screen from image +x towards image up.

    Example:
        >>> s = torch.tensor([1.0, 0.0, -0.5]).reshape(3, 1, 1, 1)
        >>> round(float(aolp_from_stokes(s)), 4)  # 3 pi / 4
        2.3562
    """
    _check_stokes(stokes)
    return wrap_angle(0.5 * torch.atan2(stokes.select(-4, 2), stokes.select(-4, 1)))


def dolp_from_stokes(stokes: Tensor, eps: float = 1e-8) -> Tensor:
    r"""Degree of linear polarization :math:`\sqrt{s_1^2+s_2^2}/s_0`, clamped to [0, 1].

    Pixels with :math:`s_0 \le` ``eps`` (dark, or negative from noise) get 0 instead of inf/NaN.

    Args:
        stokes: :math:`(*, 3, C, H, W)`.
        eps: intensity below which DoLP is defined as 0.

    Returns:
        :math:`(*, C, H, W)` DoLP in [0, 1].

    Example:
        >>> s = torch.tensor([[2.0, 0.0], [1.0, 0.0], [0.0, 0.0]]).reshape(3, 1, 1, 2)
        >>> dolp_from_stokes(s).flatten()
        tensor([0.5000, 0.0000])
    """
    magnitude = linear_magnitude(stokes)
    s0 = stokes.select(-4, 0)
    valid = s0 > eps
    safe_s0 = torch.where(valid, s0, torch.ones_like(s0))
    return torch.where(valid, torch.clamp(magnitude / safe_s0, 0.0, 1.0), torch.zeros_like(s0))


def imax_imin_from_stokes(stokes: Tensor) -> tuple[Tensor, Tensor]:
    r"""Largest and smallest intensity over all polarizer angles.

    .. math:: I_{max}, I_{min} = \tfrac12 (s_0 \pm \sqrt{s_1^2 + s_2^2})

    Args:
        stokes: :math:`(*, 3, C, H, W)`.

    Returns:
        ``(imax, imin)``, each :math:`(*, C, H, W)`.

    Example:
        >>> imax, imin = imax_imin_from_stokes(torch.tensor([1.0, 0.6, 0.0]).reshape(3, 1, 1, 1))
        >>> round(float(imax), 6), round(float(imin), 6)
        (0.8, 0.2)
    """
    magnitude = linear_magnitude(stokes)
    s0 = stokes.select(-4, 0)
    return 0.5 * (s0 + magnitude), 0.5 * (s0 - magnitude)
