"""Module PC: polar-guided photometric correction (reflective masks, PRI, colour refinement maps).

:func:`compute_polar_maps` turns one view's Stokes images into the :class:`PolarMaps` the losses
and the densifier use. The stateless pieces live in ``masks``, ``pri`` and ``crm``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction.crm import chromaticity_map, diffuse_map, propagate, whiten_features
from polargs_plugin.correction.masks import INTERMEDIATE_CHOICES, peak_intensity, reflective_masks
from polargs_plugin.correction.physics import StokesCheck, input_range, physical_stokes
from polargs_plugin.correction.pri import (
    clipped_angles,
    polarimetric_reference_intensity,
    pri_weights,
    pri_with_clipping,
)
from polargs_plugin.optics.stokes import (
    aolp_from_stokes,
    dolp_from_stokes,
    intensities_from_stokes,
    stokes_from_intensities,
)
from polargs_plugin.types import PolarMaps

__all__ = [
    "compute_polar_maps",
    "peak_intensity",
    "reflective_masks",
    "INTERMEDIATE_CHOICES",
    "physical_stokes",
    "StokesCheck",
    "input_range",
    "sensor_dolp",
    "polarimetric_reference_intensity",
    "pri_weights",
    "clipped_angles",
    "pri_with_clipping",
    "diffuse_map",
    "whiten_features",
    "propagate",
    "chromaticity_map",
]


# Relative slack on the white level for float rounding of Malus re-synthesised angle images.
_WHITE_TOL = 1e-4


def sensor_dolp(angles: Tensor, white_level: float) -> Tensor:
    """DoLP of the channel-mean colour as a sensor clipping at ``white_level`` would record it.

    Args:
        angles: :math:`(4, C, H, W)` 0/45/90/135 deg images.
        white_level: clipping level (the value recorded as full scale).

    Returns:
        :math:`(1, H, W)` DoLP of the clipped images (HDR highlights lose their polarization as
        on an 8-bit sensor, where the paper's thresholds were set).
    """
    clipped = angles.clamp(0.0, white_level).mean(dim=-3, keepdim=True)  # (4, 1, H, W)
    return dolp_from_stokes(stokes_from_intensities(clipped))


def _reflective_regions(
    angles: Tensor, dolp: Tensor, peak: Tensor, inside: Tensor, config: CorrectionConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """(specular, overexposed, saturated) :math:`(1, H, W)` bool masks of one view.

    Where some angle image of some channel exceeds the white level (HDR), the masks use the DoLP
    a sensor clipping there would record. A pixel with some channel of some angle at the clipping
    level (pri_saturation * white) holds clipped colour: saturated, never a donor; with
    ``overexposed_rule="saturated"`` the overexposed mask is those pixels and the specular mask
    leaves them out. Specular and overexposed pixels are restricted to ``inside``.
    """
    white = float(config.white_level)
    brightest = angles.flatten(0, 1).amax(dim=0, keepdim=True)  # (1, H, W)
    above_white = brightest > white * (1 + _WHITE_TOL)
    saturated = brightest >= config.pri_saturation * white
    mask_dolp = dolp
    if bool(above_white.any()):
        mask_dolp = torch.where(above_white, sensor_dolp(angles, white), dolp)
    specular, overexposed = reflective_masks(
        mask_dolp, peak, config.specular_dolp, config.overexposed_dolp, config.intensity_range,
        white_level=white, intermediate=config.intermediate_dolp, saturated=saturated,
    )
    if config.overexposed_rule == "saturated":
        overexposed = saturated.clone()
        specular &= ~saturated
    specular &= inside
    overexposed &= inside
    return specular, overexposed, saturated


def _chromaticity_targets(
    i_diff: Tensor,
    dolp: Tensor,
    pri: Tensor,
    all_clipped: Tensor,
    overexposed: Tensor,
    donors: Tensor,
    config: CorrectionConfig,
) -> tuple[Tensor, Tensor]:
    """(I_chro :math:`(C, H, W)`, valid :math:`(1, H, W)` bool) of the overexposed pixels: I_diff
    propagated from donors of similar whitened (DoLP, PRI), a pixel whose four angles all clip
    comparing on DoLP only; I_chro is 0 where no donor was found."""
    features = whiten_features(torch.cat([dolp, pri]), donors)
    components = torch.cat([torch.ones_like(all_clipped), ~all_clipped])
    i_prop, chro_valid = propagate(
        i_diff,
        features,
        overexposed,
        donors,
        config.propagation_radius,
        config.mahalanobis_threshold,
        components,
        config.propagation_step,
    )
    # I_chro only where propagation succeeded (a small fraction of the image).
    i_chro = torch.zeros_like(i_diff)
    where = chro_valid.reshape(-1).nonzero().squeeze(1)
    columns = (m.reshape(m.shape[0], -1)[:, where, None] for m in (i_prop, i_diff))  # (C, T, 1)
    i_chro.reshape(i_chro.shape[0], -1)[:, where] = chromaticity_map(*columns, config.rho_d)[..., 0]
    return i_chro, chro_valid


def compute_polar_maps(
    stokes: Tensor,
    mask: Tensor | None = None,
    config: CorrectionConfig | None = None,
    intensities: Tensor | None = None,
) -> PolarMaps:
    """All per-view maps of module PC.

    The Stokes are first projected onto the physical cone (s0 >= 0, DoLP <= 1;
    :func:`physical_stokes`). AoLP and DoLP come from the channel-mean Stokes. With
    ``config.enabled`` False only those and the intensity are filled (the densifier still needs
    them). Reflective masks are restricted to ``mask``; donors of the I_chro propagation are the
    non-reflective pixels inside ``mask`` that are not saturated (no channel of any angle image
    at the clipping level ``pri_saturation * white_level``).
    Propagation features (docs/choices.md): (DoLP, PRI), whitened by their covariance over the
    donors; a target pixel whose four angles all clip has no usable PRI and compares on DoLP only.

    Inputs that are not [0, 1] LDR (docs/choices.md "HDR inputs"): brightness is measured against
    ``config.white_level``; the masks use the DoLP a sensor clipping there would record
    (:func:`sensor_dolp`, equal to the plain DoLP where nothing exceeds the white level); PRI's
    clipping level is ``pri_saturation * white_level``; I_diff is clamped to the white level.

    Args:
        stokes: :math:`(3, C, H, W)` Stokes of one view.
        mask: optional :math:`(1, H, W)` bool object mask.
        config: correction settings (defaults: the paper's).
        intensities: optional :math:`(4, C, H, W)` 0/45/90/135 deg images the Stokes came from
            (saves re-deriving them by Malus, e.g. straight after demosaicing).

    Returns:
        :class:`PolarMaps`; ``extras`` holds ``"peak_intensity"`` :math:`(1, H, W)`,
        ``"i_chro_valid"`` :math:`(1, H, W)` bool (overexposed pixels that found a donor) and
        ``"saturated"`` :math:`(1, H, W)` bool (some channel of some angle image at the clipping
        level ``pri_saturation * white_level``: clipped colour).
    """
    config = config or CorrectionConfig()
    if stokes.ndim != 4 or stokes.shape[0] != 3:
        raise ValueError(f"stokes must have shape (3, C, H, W), got {tuple(stokes.shape)}")
    white = float(config.white_level)
    stokes, _ = physical_stokes(stokes, config.stokes_tolerance * white)
    mean_stokes = stokes.mean(dim=-3, keepdim=True)
    aolp = aolp_from_stokes(mean_stokes)
    dolp = dolp_from_stokes(mean_stokes)
    intensity = stokes[0] / 2
    if not config.enabled:
        return PolarMaps(aolp=aolp, dolp=dolp, intensity=intensity)

    inside = torch.ones_like(dolp, dtype=torch.bool) if mask is None else mask.to(torch.bool)
    peak = peak_intensity(mean_stokes)
    angles = intensities_from_stokes(stokes) if intensities is None else intensities  # (4, C, H, W)
    specular, overexposed, saturated = _reflective_regions(angles, dolp, peak, inside, config)
    pri, all_clipped = pri_with_clipping(angles, config.pri_saturation * white)
    i_diff = diffuse_map(stokes).clamp_(max=white)
    donors = inside & ~specular & ~overexposed & ~saturated
    i_chro, chro_valid = _chromaticity_targets(i_diff, dolp, pri, all_clipped, overexposed, donors, config)
    return PolarMaps(
        aolp=aolp,
        dolp=dolp,
        intensity=intensity,
        specular_mask=specular,
        overexposed_mask=overexposed,
        pri=pri,
        i_diff=i_diff,
        i_chro=i_chro,
        extras={"peak_intensity": peak, "i_chro_valid": chro_valid, "saturated": saturated},
    )
