"""Normals <-> image-plane azimuth <-> AoLP, the four azimuth candidates and the DoLP weight.

Conventions (docs/conventions.md), pinned by tests on a rendered sphere:

- Normals are unit vectors in the OpenCV camera frame (x right, y down, z forward) facing the
  camera (n . z < 0), laid out channel-first: :math:`(*, 3, H, W)`.
- Angles are measured counter-clockwise on screen, from image +x towards image up.
- Orthographic azimuth: alpha = atan2(-n_y, n_x). Perspective phase angle (PPA, Chen et al.
  ECCV 2022): with the pixel ray v = K^-1 (u + 0.5, v + 0.5, 1),
  alpha = atan2(v_y n_z - v_z n_y, v_z n_x - v_x n_z), the direction in which the plane of
  incidence (spanned by v and n) cuts the image plane; it equals the orthographic formula at
  the principal point.
- Diffuse AoLP = alpha + DIFFUSE_AOLP_OFFSET (mod pi), specular AoLP = alpha +
  SPECULAR_AOLP_OFFSET (mod pi).
- ``K`` is (3, 3) or (*, 3, 3) intrinsics with pixel centres at +0.5 (docs/conventions.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from polargs_plugin.optics.stokes import wrap_angle

__all__ = [
    "DIFFUSE_AOLP_OFFSET",
    "SPECULAR_AOLP_OFFSET",
    "AZIMUTH_MODELS",
    "pixel_rays",
    "normal_azimuth",
    "aolp_from_normals",
    "azimuth_candidates",
    "zenith_from_normals",
    "normals_from_azimuth",
    "dolp_weight",
    "wrap_aolp",
    "aolp_to_clockwise",
]

#: Diffuse light is polarized parallel to the plane of incidence: AoLP = azimuth (mod pi).
DIFFUSE_AOLP_OFFSET = 0.0
#: Specular light is polarized perpendicular to it: AoLP = azimuth + pi/2 (mod pi).
SPECULAR_AOLP_OFFSET = math.pi / 2
AZIMUTH_MODELS = ("orthographic", "perspective")
_AOLP_OFFSETS = {"diffuse": DIFFUSE_AOLP_OFFSET, "specular": SPECULAR_AOLP_OFFSET}


def _check_normals(normals: Tensor) -> None:
    if not isinstance(normals, Tensor):
        raise TypeError(f"normals must be a torch.Tensor, got {type(normals).__name__}")
    if normals.ndim < 3 or normals.shape[-3] != 3:
        raise ValueError(f"normals must have shape (..., 3, H, W), got {tuple(normals.shape)}")


def _check_model(model: str, K: Tensor | None) -> None:
    if model not in AZIMUTH_MODELS:
        raise ValueError(f"unknown azimuth model {model!r}, expected one of {AZIMUTH_MODELS}")
    if model == "perspective" and K is None:
        raise ValueError("the perspective (PPA) model needs the intrinsics K")


def pixel_rays(K: Tensor, height: int, width: int, *, dtype: torch.dtype | None = None,
               device: torch.device | str | None = None) -> Tensor:
    """Un-normalised camera rays K^-1 (u + 0.5, v + 0.5, 1) through every pixel centre.

    Args:
        K: :math:`(3, 3)` or :math:`(*, 3, 3)` intrinsics.
        height: image height H.
        width: image width W.
        dtype: result dtype (default: K's floating dtype).
        device: result device (default: K's device).

    Returns:
        :math:`(*, 3, H, W)` rays with z = 1.

    Example:
        >>> K = torch.tensor([[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]])
        >>> pixel_rays(K, 2, 2)[:, 0, 0]
        tensor([-0.2500, -0.2500,  1.0000])
    """
    K = torch.as_tensor(K)
    dtype = dtype or (K.dtype if K.is_floating_point() else torch.get_default_dtype())
    device = device if device is not None else K.device
    K = K.to(device=device, dtype=torch.float64)
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape (..., 3, 3), got {tuple(K.shape)}")
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64, device=device) + 0.5,
        torch.arange(width, dtype=torch.float64, device=device) + 0.5,
        indexing="ij",
    )
    pixels = torch.stack([u, v, torch.ones_like(u)], dim=0).reshape(3, -1)  # (3, H*W)
    rays = torch.linalg.solve(K, pixels.expand(*K.shape[:-2], 3, height * width))
    return rays.reshape(*K.shape[:-2], 3, height, width).to(dtype)


def normal_azimuth(normals: Tensor, K: Tensor | None = None, model: str = "orthographic") -> Tensor:
    """Image-plane azimuth of camera-frame normals.

    Args:
        normals: :math:`(*, 3, H, W)` camera-frame normals (need not be unit length).
        K: intrinsics, required for ``model="perspective"``.
        model: ``"orthographic"`` (alpha = atan2(-n_y, n_x)) or ``"perspective"`` (PPA).

    Returns:
        :math:`(*, 1, H, W)` azimuth in radians over the full circle, wrapped into [0, 2 pi).

    Example:
        >>> n = torch.tensor([0.0, -0.6, -0.8]).reshape(3, 1, 1)  # tilted towards image up
        >>> round(float(normal_azimuth(n)), 4)  # pi / 2
        1.5708
    """
    _check_normals(normals)
    _check_model(model, K)
    nx, ny, nz = normals.unbind(dim=-3)
    if model == "orthographic":
        alpha = torch.atan2(-ny, nx)
    else:
        rays = pixel_rays(K, normals.shape[-2], normals.shape[-1], dtype=normals.dtype, device=normals.device)
        vx, vy, vz = rays.unbind(dim=-3)
        alpha = torch.atan2(vy * nz - vz * ny, vz * nx - vx * nz)
    return wrap_angle(alpha, 2 * math.pi).unsqueeze(-3)


def aolp_from_normals(normals: Tensor, kind: str = "diffuse", K: Tensor | None = None,
                      model: str = "orthographic") -> Tensor:
    """The AoLP a surface with these normals produces (forward model of the convention).

    Args:
        normals: :math:`(*, 3, H, W)` camera-frame normals.
        kind: ``"diffuse"`` (AoLP = azimuth) or ``"specular"`` (AoLP = azimuth + pi/2).
        K: intrinsics, required for ``model="perspective"``.
        model: ``"orthographic"`` or ``"perspective"`` (PPA).

    Returns:
        :math:`(*, 1, H, W)` AoLP in [0, pi).

    Example:
        >>> n = torch.tensor([0.6, 0.0, -0.8]).reshape(3, 1, 1)  # tilted towards image +x
        >>> float(aolp_from_normals(n, "diffuse")), round(float(aolp_from_normals(n, "specular")), 4)
        (0.0, 1.5708)
    """
    if kind not in _AOLP_OFFSETS:
        raise ValueError(f"unknown reflection kind {kind!r}, expected 'diffuse' or 'specular'")
    return wrap_aolp(normal_azimuth(normals, K, model) + _AOLP_OFFSETS[kind])


def azimuth_candidates(aolp: Tensor) -> Tensor:
    """The four normal azimuths compatible with an AoLP (pi and pi/2 ambiguities).

    Args:
        aolp: :math:`(*, 1, H, W)` AoLP phi in radians.

    Returns:
        :math:`(*, 4, H, W)` azimuths {phi - pi/2, phi, phi + pi/2, phi + pi} wrapped into
        [0, 2 pi), in that order along dim -3.

    Example:
        >>> azimuth_candidates(torch.zeros(1, 1, 1)).flatten()
        tensor([4.7124, 0.0000, 1.5708, 3.1416])
    """
    if aolp.ndim < 3 or aolp.shape[-3] != 1:
        raise ValueError(f"aolp must have shape (..., 1, H, W), got {tuple(aolp.shape)}")
    offsets = torch.tensor([-0.5, 0.0, 0.5, 1.0], dtype=aolp.dtype, device=aolp.device) * math.pi
    return wrap_angle(aolp + offsets.reshape(4, 1, 1), 2 * math.pi)


def _towards_camera(height: int, width: int, K: Tensor | None, model: str, like: Tensor) -> Tensor:
    """Unit direction from the surface to the camera: (3, 1, 1) orthographic, (*, 3, H, W) PPA."""
    if model == "orthographic":
        return torch.tensor([0.0, 0.0, -1.0], dtype=like.dtype, device=like.device).reshape(3, 1, 1)
    rays = pixel_rays(K, height, width, dtype=like.dtype, device=like.device)
    return -rays / torch.linalg.vector_norm(rays, dim=-3, keepdim=True)


def zenith_from_normals(normals: Tensor, K: Tensor | None = None, model: str = "orthographic") -> Tensor:
    """Zenith angle between each normal and the direction towards the camera.

    Orthographic: the camera direction is -z; perspective: minus the normalised pixel ray.

    Args:
        normals: :math:`(*, 3, H, W)` unit camera-frame normals.
        K: intrinsics, required for ``model="perspective"``.
        model: ``"orthographic"`` or ``"perspective"``.

    Returns:
        :math:`(*, 1, H, W)` zenith in [0, pi] radians (< pi/2 for normals facing the camera).

    Example:
        >>> n = torch.tensor([0.6, 0.0, -0.8]).reshape(3, 1, 1)
        >>> round(float(zenith_from_normals(n)), 4)  # acos(0.8)
        0.6435
    """
    _check_normals(normals)
    _check_model(model, K)
    towards = _towards_camera(normals.shape[-2], normals.shape[-1], K, model, normals)
    cos_theta = (normals * towards).sum(dim=-3, keepdim=True)
    return torch.acos(torch.clamp(cos_theta, -1.0, 1.0))


def normals_from_azimuth(azimuth: Tensor, zenith: Tensor, K: Tensor | None = None,
                         model: str = "orthographic") -> Tensor:
    """Unit normals with a given image-plane azimuth and zenith (inverse of the two above).

    The normal lies in the plane spanned by the camera direction w and the image-plane
    direction d = (cos alpha, -sin alpha, 0): n = cos(theta) w + sin(theta) t, t the unit part of
    d orthogonal to w. Orthographically this is (sin th cos a, -sin th sin a, -cos th).

    Args:
        azimuth: :math:`(*, A, H, W)` azimuths (e.g. from :func:`azimuth_candidates`).
        zenith: :math:`(*, 1, H, W)` zenith angles in [0, pi/2].
        K: intrinsics, required for ``model="perspective"``.
        model: ``"orthographic"`` or ``"perspective"`` (PPA).

    Returns:
        :math:`(*, A, 3, H, W)` unit camera-frame normals facing the camera along the
        pixel ray (n . v < 0; with PPA, n_z can be slightly positive near the image border).

    Example:
        >>> n = normals_from_azimuth(torch.full((1, 1, 1), math.pi / 2), torch.full((1, 1, 1), 0.6435))
        >>> torch.allclose(n.flatten(), torch.tensor([0.0, -0.6, -0.8]), atol=1e-4)
        True
    """
    if azimuth.ndim < 3 or zenith.ndim < 3 or zenith.shape[-3] != 1:
        raise ValueError(
            f"azimuth must be (..., A, H, W) and zenith (..., 1, H, W), got {tuple(azimuth.shape)} "
            f"and {tuple(zenith.shape)}"
        )
    _check_model(model, K)
    alpha = azimuth.unsqueeze(-3)  # (*, A, 1, H, W)
    theta = zenith.unsqueeze(-3)  # (*, 1, 1, H, W)
    direction = torch.cat([torch.cos(alpha), -torch.sin(alpha), torch.zeros_like(alpha)], dim=-3)
    # (3, 1, 1) or (*, 1, 3, H, W): one camera direction shared by the A candidates.
    w = _towards_camera(azimuth.shape[-2], azimuth.shape[-1], K, model, azimuth)
    if model == "perspective":
        w = w.unsqueeze(-4)
    tangent = direction - (direction * w).sum(dim=-3, keepdim=True) * w
    tangent = tangent / torch.linalg.vector_norm(tangent, dim=-3, keepdim=True)
    return torch.cos(theta) * w + torch.sin(theta) * tangent


def dolp_weight(dolp: Tensor, sigma: float = 0.5) -> Tensor:
    r"""PolarGS confidence of the azimuth term from DoLP.

    .. math:: \omega = \exp\left(-\frac{(1-\rho)^2}{2\sigma^2}\right) + \exp\left(-\frac{\rho^2}{2\sigma^2}\right)

    Args:
        dolp: :math:`(*)` DoLP rho in [0, 1].
        sigma: width (paper default 0.5).

    Returns:
        :math:`(*)` weight omega.

    Example:
        >>> dolp_weight(torch.tensor([0.0, 1.0])).round(decimals=4)
        tensor([1.1353, 1.1353])
    """
    return torch.exp(-((1 - dolp) ** 2) / (2 * sigma**2)) + torch.exp(-(dolp**2) / (2 * sigma**2))


def wrap_aolp(angle: Tensor) -> Tensor:
    """Wrap angles into the AoLP range [0, pi) (modulo; never clip).

    Args:
        angle: :math:`(*)` radians, any range (e.g. PISR's [-pi/2, pi/2]).

    Returns:
        :math:`(*)` in [0, pi).

    Example:
        >>> wrap_aolp(torch.tensor([-math.pi / 4])).round(decimals=4)
        tensor([2.3562])
    """
    return wrap_angle(angle, math.pi)


def aolp_to_clockwise(aolp: Tensor) -> Tensor:
    """Convert between our ccw AoLP and the clockwise-with-y-down convention (MVAS); an involution.

    Args:
        aolp: :math:`(*)` AoLP in radians.

    Returns:
        :math:`(*)` (pi - aolp) mod pi, in [0, pi).

    Example:
        >>> aolp_to_clockwise(torch.tensor([0.0, math.pi / 4])).round(decimals=4)
        tensor([0.0000, 2.3562])
    """
    return wrap_angle(math.pi - aolp, math.pi)
