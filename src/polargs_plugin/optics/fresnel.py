"""Fresnel reflection at an air -> dielectric (or air -> conductor) interface and the DoLP it produces.

All functions are elementwise over a zenith-angle tensor ``theta`` (radians, angle between the
surface normal and the viewing direction, cos(theta) = N . V) of any shape ``(*)``; the result
has the same shape, dtype and device. ``n`` is the refractive index of the dielectric, a float
or a tensor broadcastable with ``theta``. Formulas: Atkinson & Hancock 2006, Miyazaki 2003
(Fresnel's equations for a dielectric; e.g. Atkinson and Hancock 2006). A conductor (metal) has
a complex index n + i k; :func:`fresnel_reflectance_conductor` and :func:`dolp_specular_conductor`
take it (Born & Wolf, "Principles of Optics", the Fresnel equations with a complex index). A metal
re-emits no diffuse light, so it has no diffuse DoLP.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "DEFAULT_REFRACTIVE_INDEX",
    "fresnel_reflectance",
    "fresnel_reflectance_conductor",
    "dolp_specular_conductor",
    "dolp_diffuse",
    "dolp_specular",
    "dolp_diffuse_max",
    "zenith_from_dolp_diffuse",
]

#: Refractive index used by PANDORA, NeRSP, PolGS and NeISF when nothing else is known.
DEFAULT_REFRACTIVE_INDEX = 1.5


def _index_like(n: float | Tensor, like: Tensor) -> Tensor:
    return torch.as_tensor(n, dtype=like.dtype, device=like.device)


def _as_float_tensor(x: float | Tensor) -> Tensor:
    x = torch.as_tensor(x)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def fresnel_reflectance(theta: Tensor, n: float | Tensor = DEFAULT_REFRACTIVE_INDEX) -> tuple[Tensor, Tensor]:
    r"""Fresnel power reflectances for light arriving from air at zenith ``theta``.

    .. math::
        \cos\theta_t = \sqrt{1 - \sin^2\theta / n^2},\quad
        r_s = \frac{\cos\theta - n\cos\theta_t}{\cos\theta + n\cos\theta_t},\quad
        r_p = \frac{n\cos\theta - \cos\theta_t}{n\cos\theta + \cos\theta_t},\quad
        R = r^2.

    Transmittances are ``1 - R``.

    Args:
        theta: incidence (zenith) angle in radians, shape :math:`(*)`, in [0, pi/2].
        n: refractive index (> 1), float or tensor broadcastable with ``theta``.

    Returns:
        ``(R_s, R_p)``: s- (perpendicular) and p- (parallel) reflectances, each :math:`(*)`.

    Example:
        >>> rs, rp = fresnel_reflectance(torch.tensor([0.0]))
        >>> torch.allclose(rs, torch.tensor([0.04])) and torch.allclose(rp, torch.tensor([0.04]))
        True
    """
    theta = _as_float_tensor(theta)
    n = _index_like(n, theta)
    cos_i = torch.cos(theta)
    sin2 = torch.sin(theta) ** 2
    cos_t = torch.sqrt(torch.clamp(1.0 - sin2 / n**2, min=0.0))
    r_s = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    r_p = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    return r_s**2, r_p**2


def fresnel_reflectance_conductor(theta: Tensor, n: float | Tensor, k: float | Tensor) -> tuple[Tensor, Tensor]:
    r"""Fresnel power reflectances of a conductor of complex index :math:`\hat n = n + i k`.

    .. math::
        \cos\theta_t = \sqrt{1 - \sin^2\theta / \hat n^2},\quad
        r_s = \frac{\cos\theta - \hat n\cos\theta_t}{\cos\theta + \hat n\cos\theta_t},\quad
        r_p = \frac{\hat n\cos\theta - \cos\theta_t}{\hat n\cos\theta + \cos\theta_t},\quad
        R = |r|^2,

    the dielectric formulas of :func:`fresnel_reflectance` with a complex index (the principal
    square root; for ``k = 0`` and ``n > 1`` they are the same).

    Args:
        theta: incidence angle in radians, shape :math:`(*)`, in [0, pi/2].
        n: real part of the index (> 0).
        k: extinction coefficient (>= 0).

    Returns:
        ``(R_s, R_p)``, each :math:`(*)`, real, in [0, 1].

    Example:
        >>> rs, rp = fresnel_reflectance_conductor(torch.tensor([0.0], dtype=torch.float64), 0.2, 3.0)
        >>> round(float(rs), 4), round(float(rp), 4)  # ((n-1)^2 + k^2) / ((n+1)^2 + k^2)
        (0.9234, 0.9234)
    """
    theta = _as_float_tensor(theta)
    complex_dtype = torch.complex128 if theta.dtype == torch.float64 else torch.complex64
    index = torch.complex(_index_like(n, theta), _index_like(k, theta)).to(complex_dtype)
    cos_i = torch.cos(theta).to(complex_dtype)
    sin2 = (torch.sin(theta) ** 2).to(complex_dtype)
    cos_t = torch.sqrt(1.0 - sin2 / index**2)
    r_s = (cos_i - index * cos_t) / (cos_i + index * cos_t)
    r_p = (index * cos_i - cos_t) / (index * cos_i + cos_t)
    return r_s.abs() ** 2, r_p.abs() ** 2


def dolp_specular_conductor(theta: Tensor, n: float | Tensor, k: float | Tensor) -> Tensor:
    r"""Degree of linear polarization of light reflected by a conductor, :math:`(R_s - R_p) / (R_s + R_p)`.

    A metal reflects the s component more than the p one at every angle between 0 and pi/2, so the
    reflected light is polarized perpendicular to the plane of incidence, as a dielectric's
    specular reflection is (AoLP = azimuth + pi/2), but weakly: its DoLP peaks at the principal
    angle (near grazing), well below 1 for most metals in the visible (aluminium 0.14, gold 0.15,
    copper 0.33, iron 0.67 at 550 nm).

    Args:
        theta: incidence angle in radians, shape :math:`(*)`, in [0, pi/2].
        n: real part of the index (> 0).
        k: extinction coefficient (>= 0).

    Returns:
        :math:`(*)` DoLP in [0, 1].

    Example:
        >>> theta = torch.deg2rad(torch.tensor([0.0, 45.0, 80.0], dtype=torch.float64))
        >>> [round(float(v), 3) for v in dolp_specular_conductor(theta, 0.96, 6.69)]  # aluminium, 550 nm
        [0.0, 0.029, 0.136]
    """
    r_s, r_p = fresnel_reflectance_conductor(theta, n, k)
    return (r_s - r_p) / (r_s + r_p)


def dolp_specular(theta: Tensor, n: float | Tensor = DEFAULT_REFRACTIVE_INDEX) -> Tensor:
    r"""Degree of linear polarization of specularly reflected light, closed form.

    .. math::
        \rho_s = \frac{R_s - R_p}{R_s + R_p}
        = \frac{2\sin^2\theta\cos\theta\sqrt{n^2 - \sin^2\theta}}
               {n^2 - \sin^2\theta - n^2\sin^2\theta + 2\sin^4\theta}

    Equals 1 at Brewster's angle ``atan(n)``; two-valued in ``theta``.

    Args:
        theta: zenith angle in radians, shape :math:`(*)`, in [0, pi/2].
        n: refractive index (> 1).

    Returns:
        :math:`(*)` specular DoLP in [0, 1].

    Example:
        >>> rho = dolp_specular(torch.atan(torch.tensor(1.5)))
        >>> torch.allclose(rho, torch.tensor(1.0))
        True
    """
    theta = _as_float_tensor(theta)
    n = _index_like(n, theta)
    sin2 = torch.sin(theta) ** 2
    num = 2.0 * sin2 * torch.cos(theta) * torch.sqrt(torch.clamp(n**2 - sin2, min=0.0))
    den = n**2 - sin2 - n**2 * sin2 + 2.0 * sin2**2
    return num / den


def dolp_diffuse(theta: Tensor, n: float | Tensor = DEFAULT_REFRACTIVE_INDEX) -> Tensor:
    r"""Degree of linear polarization of diffusely re-emitted light, closed form.

    .. math::
        \rho_d = \frac{T_p - T_s}{T_p + T_s}
        = \frac{(n - 1/n)^2\sin^2\theta}
               {2 + 2n^2 - (n + 1/n)^2\sin^2\theta + 4\cos\theta\sqrt{n^2 - \sin^2\theta}}

    Monotonically increasing in ``theta`` from 0 to :func:`dolp_diffuse_max`.

    Args:
        theta: zenith (emittance) angle in radians, shape :math:`(*)`, in [0, pi/2].
        n: refractive index (> 1).

    Returns:
        :math:`(*)` diffuse DoLP in [0, (n^2-1)/(n^2+1)].

    Example:
        >>> rho = dolp_diffuse(torch.deg2rad(torch.tensor([60.0])))
        >>> round(float(rho), 3)
        0.096
    """
    theta = _as_float_tensor(theta)
    n = _index_like(n, theta)
    sin2 = torch.sin(theta) ** 2
    num = (n - 1.0 / n) ** 2 * sin2
    den = (
        2.0
        + 2.0 * n**2
        - (n + 1.0 / n) ** 2 * sin2
        + 4.0 * torch.cos(theta) * torch.sqrt(torch.clamp(n**2 - sin2, min=0.0))
    )
    return num / den


def dolp_diffuse_max(n: float | Tensor = DEFAULT_REFRACTIVE_INDEX) -> Tensor:
    r"""Largest diffuse DoLP, reached at grazing emission: :math:`(n^2 - 1) / (n^2 + 1)`.

    Args:
        n: refractive index (> 1), float or tensor of shape :math:`(*)`.

    Returns:
        :math:`(*)` (a 0-d tensor for a float ``n``).

    Example:
        >>> round(float(dolp_diffuse_max(1.5)), 4)
        0.3846
    """
    n = _as_float_tensor(n)
    return (n**2 - 1.0) / (n**2 + 1.0)


def zenith_from_dolp_diffuse(rho: Tensor, n: float | Tensor = DEFAULT_REFRACTIVE_INDEX) -> Tensor:
    r"""Invert :func:`dolp_diffuse`: the zenith angle that produces diffuse DoLP ``rho``.

    Closed form: with :math:`x = \sin^2\theta`, :math:`A = (n - 1/n)^2`, :math:`B = (n + 1/n)^2`,
    squaring :math:`4\rho\cos\theta\sqrt{n^2 - x} = (A + \rho B)x - 2\rho(1 + n^2)` gives a
    quadratic in :math:`x` whose larger root is the solution. ``rho`` is clamped to
    [0, :func:`dolp_diffuse_max`] first, so noisy DoLP above the physical maximum maps to pi/2.

    Args:
        rho: diffuse DoLP, shape :math:`(*)`.
        n: refractive index (> 1).

    Returns:
        :math:`(*)` zenith angle in radians, in [0, pi/2].

    Example:
        >>> theta = torch.tensor([0.3, 0.9, 1.4], dtype=torch.float64)
        >>> torch.allclose(zenith_from_dolp_diffuse(dolp_diffuse(theta)), theta)
        True
    """
    rho = _as_float_tensor(rho)
    n = _index_like(n, rho)
    rho = torch.minimum(torch.clamp(rho, min=0.0), dolp_diffuse_max(n))
    a = (n - 1.0 / n) ** 2
    b = (n + 1.0 / n) ** 2
    one_rho = 1.0 + rho
    quad = a + rho * b + 4.0 * rho
    # Common factor 4*rho taken out of the discriminant so that rho -> 0 does not underflow.
    disc = (1.0 + n**2) ** 2 * a**2 * one_rho**2 - a * one_rho * quad * (n**2 - 1.0) ** 2
    x = 2.0 * rho * ((1.0 + n**2) * a * one_rho + torch.sqrt(torch.clamp(disc, min=0.0))) / (a * one_rho * quad)
    return torch.asin(torch.sqrt(torch.clamp(x, 0.0, 1.0)))
