"""Single-view shape from polarization: a normal per pixel from one view's own AoLP and DoLP.

One polarimetric view constrains the surface normal at a pixel (Atkinson & Hancock 2006;
Miyazaki 2003): the AoLP fixes the plane of incidence, i.e. the normal's image-plane azimuth up
to the pi ambiguity (the normal's sign) and the pi/2 one (diffuse light is polarized parallel to
the plane of incidence, specular light perpendicular to it; :func:`azimuth_candidates`), and
for diffuse light the DoLP fixes the zenith through the surface's refractive index
(:func:`zenith_from_dolp_diffuse`). :func:`single_view_normals` resolves both ambiguities with a
guess of the normal (the rendered one) and says where only the azimuth can be trusted.

Conventions as :mod:`polargs_plugin.optics.azimuth` (docs/conventions.md): camera-frame normals
(OpenCV: x right, y down, z forward) facing the camera, channel-first :math:`(*, 3, H, W)`; AoLP
in [0, pi), counter-clockwise on screen from image +x towards image up; the azimuth model
``"orthographic"`` or ``"perspective"`` (PPA, needs ``K``, pixel centres at +0.5), which must be
the one the AoLP was rendered or measured with.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from polargs_plugin.optics.azimuth import azimuth_candidates, normals_from_azimuth, zenith_from_normals
from polargs_plugin.optics.fresnel import DEFAULT_REFRACTIVE_INDEX, dolp_diffuse_max, zenith_from_dolp_diffuse

__all__ = ["SingleViewNormals", "single_view_normals"]

# Of the candidates of azimuth_candidates (phi - pi/2, phi, phi + pi/2, phi + pi), the diffuse ones.
_DIFFUSE_CANDIDATES = (False, True, False, True)


class SingleViewNormals(NamedTuple):
    """What :func:`single_view_normals` returns; every map in the camera frame of the view.

    Attributes:
        normal: :math:`(*, 3, H, W)` unit target normal: the chosen azimuth with the zenith read
            from the diffuse DoLP, or, on ``azimuth_only`` pixels, with the guess's own zenith
            (the guess with its azimuth replaced); 0 where not ``valid``.
        plane: :math:`(*, 3, H, W)` unit normal of the measured plane of incidence (spanned by
            the direction towards the camera and the chosen azimuth): a normal with the measured
            azimuth is orthogonal to it, so ``|N . plane|`` measures how far a normal leaves that
            azimuth whatever its zenith; 0 where not ``valid``.
        valid: :math:`(*, 1, H, W)` bool, pixels with a target (DoLP at least ``min_dolp``,
            finite inputs, a non-zero guess).
        azimuth_only: :math:`(*, 1, H, W)` bool, the valid pixels where only the azimuth is
            measured (see :func:`single_view_normals`).

    Example:
        >>> out = single_view_normals(torch.zeros(1, 1, 2), torch.tensor([[[0.01, 0.03]]]), torch.tensor(
        ...     [0.5, 0.0, -0.8]).reshape(3, 1, 1).expand(3, 1, 2))
        >>> out.valid.flatten().tolist(), out.azimuth_only.flatten().tolist()  # too low; zenith unsure
        ([False, True], [False, True])
        >>> out.plane[:, 0, 1].abs().tolist()  # orthographic, azimuth 0: the plane of incidence is x-z
        [0.0, 1.0, 0.0]
    """

    normal: Tensor
    plane: Tensor
    valid: Tensor
    azimuth_only: Tensor


def _bool_mask(mask: Tensor | None, like: Tensor) -> Tensor:
    if mask is None:
        return torch.zeros_like(like, dtype=torch.bool)
    if mask.shape[-3:] != like.shape[-3:]:
        raise ValueError(f"masks must have shape (..., 1, H, W) like the AoLP {tuple(like.shape)}, got {tuple(mask.shape)}")
    return mask.to(device=like.device, dtype=torch.bool)


def single_view_normals(
    aolp: Tensor,
    dolp: Tensor,
    guess: Tensor,
    K: Tensor | None = None,
    model: str = "orthographic",
    refractive_index: float | Tensor = DEFAULT_REFRACTIVE_INDEX,
    *,
    min_dolp: float = 0.02,
    zenith_min_dolp: float = 0.05,
    specular_mask: Tensor | None = None,
    overexposed_mask: Tensor | None = None,
) -> SingleViewNormals:
    r"""The normal one view's polarization gives at each pixel, its ambiguities resolved by a guess.

    1. Azimuth: of the four candidates compatible with the AoLP (:func:`azimuth_candidates`:
       phi and phi + pi for diffuse light, phi +- pi/2 for specular light), the one whose
       direction in the tangent plane of the viewing direction lies closest to ``guess``
       (largest ``t_k . guess``, ``t_k`` the candidate at zenith pi/2; the same as the
       candidate normal closest to the guess at the guess's zenith). On ``specular_mask``
       pixels only the specular pair phi +- pi/2 competes.
    2. Zenith: where the chosen candidate is a diffuse one, the pixel is neither specular nor
       overexposed, and ``zenith_min_dolp <= dolp < dolp_diffuse_max(n)``, the inversion of
       the diffuse DoLP (:func:`zenith_from_dolp_diffuse`). Elsewhere the pixel is
       ``azimuth_only``: a lower DoLP gives a zenith that a small DoLP error moves a lot (rho
       grows as sin^2 theta), a DoLP at or above the diffuse maximum is no diffuse light, the
       specular DoLP is two-valued in the zenith, and an overexposed pixel's DoLP is clipped.
    3. Valid: ``dolp >= min_dolp`` (below it the AoLP is noise), finite AoLP and DoLP, and a
       non-zero guess.

    The result does not depend differentiably on ``guess`` (the choice is discrete): it is a
    target, computed on the detached guess.

    Args:
        aolp: :math:`(*, 1, H, W)` AoLP phi in radians, [0, pi), e.g. ``PolarMaps.aolp`` or
            :func:`~polargs_plugin.optics.stokes.aolp_from_stokes` of the channel-mean Stokes.
        dolp: :math:`(*, 1, H, W)` DoLP in [0, 1] (``PolarMaps.dolp``,
            :func:`~polargs_plugin.optics.stokes.dolp_from_stokes`).
        guess: :math:`(*, 3, H, W)` camera-frame normal that decides the ambiguities (a rendered
            normal; any length, e.g. alpha-weighted).
        K: :math:`(3, 3)` or :math:`(*, 3, 3)` intrinsics, required for ``model="perspective"``.
        model: the azimuth model of the AoLP, ``"orthographic"`` or ``"perspective"`` (PPA).
        refractive_index: n (> 1) of the diffuse DoLP, float or tensor broadcastable with
            ``dolp``.
        min_dolp: DoLP below which a pixel gets no target.
        zenith_min_dolp: DoLP from which the zenith is read from it.
        specular_mask: optional :math:`(*, 1, H, W)` bool, pixels whose light is specular
            (AoLP = azimuth + pi/2; e.g. ``PolarMaps.specular_mask``): azimuth only.
        overexposed_mask: optional :math:`(*, 1, H, W)` bool, pixels whose DoLP is clipped
            (``PolarMaps.overexposed_mask``): azimuth only, any of the four candidates.

    Returns:
        :class:`SingleViewNormals` ``(normal, plane, valid, azimuth_only)``, in the AoLP's dtype
        and device.

    Example:
        >>> from polargs_plugin.optics.fresnel import dolp_diffuse
        >>> theta = math.radians(60.0)  # a surface tilted towards image +x: AoLP 0
        >>> dolp = dolp_diffuse(torch.full((1, 1, 1), theta))
        >>> guess = torch.tensor([0.5, 0.3, -0.8]).reshape(3, 1, 1)  # about 20 degrees off
        >>> out = single_view_normals(torch.zeros(1, 1, 1), dolp, guess)
        >>> out.normal.flatten().round(decimals=4), bool(out.valid), bool(out.azimuth_only)
        (tensor([ 0.8660,  0.0000, -0.5000]), True, False)
        >>> flipped = single_view_normals(torch.zeros(1, 1, 1), dolp, guess * torch.tensor([-1.0, 1, 1]).reshape(3, 1, 1))
        >>> flipped.normal.flatten().round(decimals=4)  # the other side of the pi ambiguity
        tensor([-0.8660,  0.0000, -0.5000])
    """
    if aolp.ndim < 3 or aolp.shape[-3] != 1 or dolp.shape != aolp.shape:
        raise ValueError(f"aolp and dolp must both have shape (..., 1, H, W), got {tuple(aolp.shape)} and "
                         f"{tuple(dolp.shape)}")
    if guess.shape[-3] != 3 or guess.shape[-2:] != aolp.shape[-2:]:
        raise ValueError(f"guess must have shape (..., 3, H, W) with the AoLP's H, W, got {tuple(guess.shape)}")
    specular = _bool_mask(specular_mask, aolp)
    overexposed = _bool_mask(overexposed_mask, aolp)
    guess = guess.detach().to(aolp.dtype)
    length = torch.linalg.vector_norm(guess, dim=-3, keepdim=True)
    unit = guess / length.clamp_min(torch.finfo(guess.dtype).tiny)

    candidates = azimuth_candidates(aolp)  # (*, 4, H, W)
    tangents = normals_from_azimuth(candidates, torch.full_like(aolp, math.pi / 2), K, model)  # (*, 4, 3, H, W)
    score = (tangents * unit.unsqueeze(-4)).sum(dim=-3)  # (*, 4, H, W)
    diffuse_candidate = torch.tensor(_DIFFUSE_CANDIDATES, device=aolp.device).reshape(4, 1, 1)
    score = torch.where(specular & diffuse_candidate, -torch.inf, score)
    best = score.argmax(dim=-3, keepdim=True)  # (*, 1, H, W)
    azimuth = candidates.gather(-3, best)
    tangent = tangents.gather(-4, best.unsqueeze(-3).expand(*best.shape[:-3], 1, 3, *best.shape[-2:])).squeeze(-4)

    valid = (dolp >= min_dolp) & (length > 0) & torch.isfinite(aolp) & torch.isfinite(dolp) & torch.isfinite(length)
    rho_max = dolp_diffuse_max(refractive_index).to(dolp)
    full = valid & (best % 2 == 1) & ~overexposed & (dolp >= zenith_min_dolp) & (dolp < rho_max)
    guess_zenith = zenith_from_normals(unit, K, model).clamp(max=math.pi / 2)
    zenith = torch.where(full, zenith_from_dolp_diffuse(dolp, refractive_index), guess_zenith)
    normal = normals_from_azimuth(azimuth, zenith, K, model).squeeze(-4)
    towards = normals_from_azimuth(azimuth, torch.zeros_like(aolp), K, model).squeeze(-4)
    plane = torch.linalg.cross(towards, tangent, dim=-3)  # unit: towards is orthogonal to tangent
    return SingleViewNormals(normal * valid, plane * valid, valid, valid & ~full)
