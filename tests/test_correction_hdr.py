"""Module PC on inputs that are not 8-bit LDR (docs/choices.md "HDR inputs", "Between the DoLP
rules"): a rendered metal highlight whose core exceeds the white level and whose DoLP lies
between the paper's specular (>= 0.3) and overexposed (<= 0.1) rules."""

from __future__ import annotations

import math

import torch

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.optics.azimuth import aolp_from_normals
from polargs_plugin.optics.fresnel import dolp_specular

SIZE = 64
METAL_INDEX = 6.0  # a real index this high gives a metal's weak specular DoLP (0.1-0.3 at 35-50 deg)
COPPER = torch.tensor([0.95, 0.64, 0.54])


def render_metal_highlight(peak: float = 4.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """HDR Stokes (3, 3, H, W) of a copper sphere (orthographic view) with one highlight.

    Specular lobe (Gaussian in the angle between the normal and a half vector at zenith 43.5 deg),
    copper-tinted, peak ``peak`` times the tint in s0/2 units; its DoLP is Fresnel's specular DoLP
    of index :data:`METAL_INDEX` (0.12-0.29 over the lobe), its AoLP the specular one. The diffuse
    part is a dim unpolarized copper (s0/2 around 0.1-0.3).

    Returns:
        ``(stokes, mask, lobe)``: Stokes, (1, H, W) sphere mask, (1, H, W) specular s0/2 (channel mean).
    """
    v, u = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    x, y = (u - SIZE / 2) / (0.45 * SIZE), (v - SIZE / 2) / (0.45 * SIZE)
    r2 = x**2 + y**2
    mask = (r2 < 1.0)[None]
    nz = torch.sqrt((1 - r2).clamp_min(0))
    normal = torch.stack([x, y, -nz]) * mask  # camera frame, facing the camera (n . z < 0)
    zenith = torch.arccos(nz.clamp(0, 1))
    half_zenith, half_azimuth = math.radians(43.5), math.radians(30.0)
    half = torch.tensor([math.sin(half_zenith) * math.cos(half_azimuth),
                         math.sin(half_zenith) * math.sin(half_azimuth), -math.cos(half_zenith)])
    cos_angle = (normal * half[:, None, None]).sum(0).clamp(-1, 1)
    lobe = peak * torch.exp(-torch.arccos(cos_angle) ** 2 / (2 * math.radians(6.0) ** 2)) * mask[0]
    dolp = dolp_specular(zenith, METAL_INDEX) * mask[0]
    aolp = aolp_from_normals(normal[None] + (~mask[None]) * torch.tensor([0, 0, -1.0])[None, :, None, None],
                             kind="specular")[0, 0]
    shade = (0.15 + 0.15 * nz) * mask[0]
    specular = COPPER[:, None, None] * lobe  # (3, H, W), s0/2 units
    diffuse = 0.6 * COPPER[:, None, None] * shade + 0.02 * mask[0]
    s0 = 2 * (diffuse + specular)
    s1 = 2 * specular * dolp * torch.cos(2 * aolp)
    s2 = 2 * specular * dolp * torch.sin(2 * aolp)
    return torch.stack([s0, s1, s2]).float(), mask, (specular.mean(0, keepdim=True))


def test_rendered_metal_highlight_has_the_dolp_of_a_copper_pan():
    stokes, mask, lobe = render_metal_highlight()
    core = lobe > 1.0
    s0, s1, s2 = stokes.mean(1).unbind(0)
    dolp = torch.hypot(s1, s2) / s0
    assert core.sum() > 20 and float((stokes[0] / 2).max()) > 3.0
    assert 0.12 <= float(dolp[core[0]].min()) and float(dolp[core[0]].max()) <= 0.3  # a copper pan's highlight: 0.12-0.29


def test_default_assigns_a_metal_highlight_and_paper_literal_misses_its_rim():
    stokes, mask, lobe = render_metal_highlight()
    maps = compute_polar_maps(stokes, mask, CorrectionConfig(overexposed_rule="paper"))
    peak = maps.extras["peak_intensity"]
    highlight = mask & (lobe > 0.1) & (peak >= 160 / 255)  # bright and visibly specular
    assigned = maps.specular_mask | maps.overexposed_mask
    assert float(assigned[highlight].float().mean()) > 0.99
    # The default rule: the same for every saturated or visibly polarized highlight pixel; the
    # few bright, unclipped ones with DoLP <= 0.1 keep their own colour (no mask).
    default = compute_polar_maps(stokes, mask, CorrectionConfig())
    s0, s1, s2 = stokes.mean(1, keepdim=True).unbind(0)
    polarized = torch.hypot(s1, s2) / s0 > 0.1
    kept = highlight & (default.extras["saturated"] | polarized)
    assert bool((default.specular_mask | default.overexposed_mask)[kept].all())
    assert not (default.specular_mask | default.overexposed_mask)[highlight & ~kept].any()
    # Saturated pixels (some angle image above the white level: their colour is clipped) take the
    # donors' colour (overexposed); the unsaturated bright rim takes I_diff (specular).
    saturated = maps.extras["saturated"]
    assert bool(maps.overexposed_mask[saturated & highlight].all())
    s0, s1, s2 = stokes.mean(1, keepdim=True).unbind(0)
    gap = (torch.hypot(s1, s2) / s0 > 0.1) & (torch.hypot(s1, s2) / s0 < 0.3)
    rim = highlight & ~saturated & gap
    assert rim.sum() >= 8
    assert bool(maps.specular_mask[rim].all())

    literal = compute_polar_maps(stokes, mask, CorrectionConfig(intermediate_dolp="none"))
    literal_assigned = literal.specular_mask | literal.overexposed_mask
    assert not literal_assigned[rim].any()  # the paper's rules read literally leave the rim out


def test_hdr_cores_are_never_donors_and_i_chro_stays_below_the_pixel():
    stokes, mask, lobe = render_metal_highlight()
    maps = compute_polar_maps(stokes, mask, CorrectionConfig())
    valid = maps.extras["i_chro_valid"][0]
    assert valid.sum() > 20  # the overexposed core found donors
    i_chro = maps.i_chro[:, valid]
    half_s0 = (stokes[0] / 2)[:, valid]
    # Donors are unsaturated pixels, so I_chro (their colour) is at most the white level and,
    # at these bright targets, far below the observed s0/2: the excluded-core donor bug (I_chro
    # ~1.5 where s0/2 ~ 0.7) cannot happen.
    assert float(i_chro.max()) <= 1.0 + 1e-6
    assert bool((i_chro.mean(0) <= half_s0.mean(0)).all())
    assert torch.isfinite(maps.i_chro).all() and torch.isfinite(maps.i_diff).all()
    # I_diff is clamped to the white level and never above the pixel's s0/2.
    spec = maps.specular_mask[0]
    assert float(maps.i_diff.max()) <= 1.0 + 1e-6
    assert bool((maps.i_diff[:, spec] <= (stokes[0] / 2)[:, spec] + 1e-6).all())


def test_white_level_rescales_the_thresholds():
    stokes, mask, lobe = render_metal_highlight()
    # Exposure scaled by 1000 (e.g. raw counts) with the white level scaled alike: same masks.
    ref = compute_polar_maps(stokes, mask, CorrectionConfig())
    scaled = compute_polar_maps(stokes * 1000, mask, CorrectionConfig(white_level=1000.0))
    assert torch.equal(ref.specular_mask, scaled.specular_mask)
    assert torch.equal(ref.overexposed_mask, scaled.overexposed_mask)
    assert torch.allclose(ref.i_chro * 1000, scaled.i_chro, rtol=1e-4, atol=1e-3)


def test_ldr_input_is_unchanged_by_the_white_level_machinery():
    """For [0, 1] data nothing exceeds the white level: no pixel is 'saturated', and the masks
    use the plain DoLP."""
    stokes, mask, lobe = render_metal_highlight(peak=0.6)
    assert float((stokes[0] / 2).max()) <= 1.0
    maps = compute_polar_maps(stokes, mask, CorrectionConfig())
    assert not maps.extras["saturated"].any()


def test_pixels_above_the_white_level_are_never_i_chro_donors():
    """An overexposed pixel (s0/2 ~ 0.9, DoLP 0.05) next to a highlight core above the white level
    (s0/2 = 3). Read literally, the paper's inclusive range up to 255/255 leaves the core out of
    both masks, so it would donate I_diff ~ 2.9 and I_chro would come out ~2.1 where s0/2 ~ 0.9."""
    size = 15
    g = torch.Generator().manual_seed(0)
    half_s0 = 0.3 + 0.05 * torch.rand(3, size, size, generator=g)  # dim diffuse surroundings
    dolp = 0.08 * torch.rand(size, size, generator=g)
    half_s0[:, 5:10, 5:10] = torch.tensor([3.0, 2.98, 2.97])[:, None, None]  # HDR core
    dolp[5:10, 5:10] = 0.05
    half_s0[:, 7, 11] = torch.tensor([0.92, 0.9, 0.89])  # bright, weakly polarized target
    dolp[7, 11] = 0.05
    s0 = 2 * half_s0
    stokes = torch.stack([s0, s0 * dolp, torch.zeros_like(s0)])
    maps = compute_polar_maps(stokes, None, CorrectionConfig(overexposed_rule="paper"))
    assert bool(maps.overexposed_mask[0, 5:10, 5:10].all())  # the core counts as 255: bright
    assert bool(maps.overexposed_mask[0, 7, 11]) and bool(maps.extras["i_chro_valid"][0, 7, 11])
    i_chro = maps.i_chro[:, 7, 11]
    assert bool((i_chro <= half_s0[:, 7, 11]).all()), i_chro
    assert float(i_chro.max()) < 0.5  # the surroundings' colour, not the core's
