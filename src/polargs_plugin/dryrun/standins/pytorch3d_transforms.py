"""Stand-in for ``pytorch3d.transforms``, served (as ``pytorch3d`` and ``pytorch3d.transforms``)
only where pytorch3d itself is not installed: it has no PyPI wheels for torch 2.x. PGSR's
``GaussianModel.get_rotation_matrix`` calls ``quaternion_to_matrix``; the other rotation
conversions of the same family are here too, with pytorch3d's names, arguments and conventions:
quaternions real part first ``(w, x, y, z)``, ``(..., 4)``; rotation matrices ``(..., 3, 3)`` that
act on column vectors; axis-angle vectors ``(..., 3)``, the axis times the angle in radians.
Pure torch, differentiable, any leading batch shape.
"""

from __future__ import annotations

import torch
from torch import Tensor

from polargs_plugin.geometry import quat_to_rotmat

__all__ = ["quaternion_to_matrix", "matrix_to_quaternion", "standardize_quaternion", "quaternion_raw_multiply",
           "quaternion_multiply", "quaternion_invert", "quaternion_apply", "axis_angle_to_quaternion",
           "quaternion_to_axis_angle", "axis_angle_to_matrix", "matrix_to_axis_angle"]

_SMALL_ANGLE = 1e-6


def _last_dims(tensor: Tensor, shape: tuple[int, ...], what: str) -> None:
    if tuple(tensor.shape[-len(shape):]) != shape:
        raise ValueError(f"{what} must have shape (..., {', '.join(map(str, shape))}), got {tuple(tensor.shape)}")


def quaternion_to_matrix(quaternions: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions, real part first; a quaternion that is
    not of unit length gives the rotation of its normalised form."""
    _last_dims(quaternions, (4,), "quaternions")
    return quat_to_rotmat(quaternions)


def standardize_quaternion(quaternions: Tensor) -> Tensor:
    """The same rotations with a non-negative real part (q and -q are one rotation)."""
    return torch.where(quaternions[..., :1] < 0, -quaternions, quaternions)


def matrix_to_quaternion(matrix: Tensor) -> Tensor:
    """(..., 4) unit quaternions, real part first and non-negative, of (..., 3, 3) rotation matrices.

    Each of 4w², 4x², 4y², 4z² is a sum of diagonal entries, and each product 4ab of two
    components a sum or difference of two off-diagonal ones; the quaternion is read from the
    products with its largest component, which keeps the division well away from zero."""
    _last_dims(matrix, (3, 3), "matrix")
    m = matrix.unbind(-1)
    m00, m10, m20 = m[0].unbind(-1)
    m01, m11, m21 = m[1].unbind(-1)
    m02, m12, m22 = m[2].unbind(-1)
    squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    products = torch.stack([  # row k: 4 * q_k * (w, x, y, z)
        torch.stack([squares[..., 0], wx, wy, wz], -1),
        torch.stack([wx, squares[..., 1], xy, xz], -1),
        torch.stack([wy, xy, squares[..., 2], yz], -1),
        torch.stack([wz, xz, yz, squares[..., 3]], -1),
    ], -2)
    best = squares.argmax(-1, keepdim=True)
    row = torch.gather(products, -2, best[..., None].expand(*best.shape, 4)).squeeze(-2)
    largest = torch.gather(squares, -1, best).clamp_min(1e-12).sqrt()  # 2 |q_k|
    return standardize_quaternion(row / (2 * largest))


def quaternion_raw_multiply(a: Tensor, b: Tensor) -> Tensor:
    """The Hamilton product a b (the rotation b, then a), not standardised."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """The Hamilton product a b, standardised (non-negative real part)."""
    return standardize_quaternion(quaternion_raw_multiply(a, b))


def quaternion_invert(quaternion: Tensor) -> Tensor:
    """The conjugate (the inverse of a unit quaternion)."""
    return quaternion * quaternion.new_tensor([1.0, -1.0, -1.0, -1.0])


def quaternion_apply(quaternion: Tensor, point: Tensor) -> Tensor:
    """(..., 3) points rotated by unit quaternions: q (0, p) q*."""
    if point.shape[-1] != 3:
        raise ValueError(f"points must have 3 coordinates, got shape {tuple(point.shape)}")
    pure = torch.cat([torch.zeros_like(point[..., :1]), point], -1)
    return quaternion_raw_multiply(quaternion_raw_multiply(quaternion, pure), quaternion_invert(quaternion))[..., 1:]


def _sin_half_over_angle(angles: Tensor) -> Tensor:
    """sin(angle / 2) / angle, with its Taylor series near 0."""
    small = angles.abs() < _SMALL_ANGLE
    safe = torch.where(small, torch.ones_like(angles), angles)
    return torch.where(small, 0.5 - angles * angles / 48, torch.sin(safe / 2) / safe)


def axis_angle_to_quaternion(axis_angle: Tensor) -> Tensor:
    """(..., 4) unit quaternions of (..., 3) axis-angle vectors."""
    _last_dims(axis_angle, (3,), "axis_angle")
    angles = torch.linalg.vector_norm(axis_angle, dim=-1, keepdim=True)
    return torch.cat([torch.cos(angles / 2), axis_angle * _sin_half_over_angle(angles)], -1)


def quaternion_to_axis_angle(quaternions: Tensor) -> Tensor:
    """(..., 3) axis-angle vectors of unit quaternions (angle in [0, 2 pi]; in [0, pi] for a
    standardised quaternion)."""
    _last_dims(quaternions, (4,), "quaternions")
    vector = quaternions[..., 1:]
    angles = 2 * torch.atan2(torch.linalg.vector_norm(vector, dim=-1, keepdim=True), quaternions[..., :1])
    return vector / _sin_half_over_angle(angles)


def axis_angle_to_matrix(axis_angle: Tensor, fast: bool = False) -> Tensor:
    """(..., 3, 3) rotation matrices of (..., 3) axis-angle vectors (``fast`` is accepted and
    changes nothing)."""
    return quaternion_to_matrix(axis_angle_to_quaternion(axis_angle))


def matrix_to_axis_angle(matrix: Tensor, fast: bool = False) -> Tensor:
    """(..., 3) axis-angle vectors, angle in [0, pi], of (..., 3, 3) rotation matrices (``fast``
    is accepted and changes nothing)."""
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))
