"""Module PC: masks, PRI, CRMs against hand-computed small cases and brute-force references."""

import math

import numpy as np
import pytest
import torch

from polargs_plugin.config import CorrectionConfig
from polargs_plugin.correction import (
    chromaticity_map,
    compute_polar_maps,
    diffuse_map,
    peak_intensity,
    polarimetric_reference_intensity,
    propagate,
    reflective_masks,
    whiten_features,
)
from polargs_plugin.optics.stokes import intensities_from_stokes


def _stokes(s0, s1, s2):
    """(3, C, 1, N) Stokes from per-pixel lists of per-channel values (each (N, C))."""
    t = torch.tensor([s0, s1, s2], dtype=torch.float32)  # (3, N, C)
    return t.permute(0, 2, 1)[:, :, None, :]


def test_masks_hand_cases():
    # Mono pixels, s2 = 0 so DoLP = |s1| / s0 and the brightest angle is I0 = (s0 + |s1|) / 2.
    s0 = [1.4, 1.6, 1.4, 0.8, 320 / 255]
    s1 = [0.56, 0.08, 0.28, 0.4, 0.0]
    stokes = _stokes([[v] for v in s0], [[v] for v in s1], [[0.0]] * 5)
    peak = peak_intensity(stokes)
    assert torch.allclose(peak.flatten(), torch.tensor([0.98, 0.84, 0.84, 0.6, 160 / 255]), atol=1e-6)
    dolp = torch.tensor([0.4, 0.05, 0.2, 0.5, 0.0]).reshape(1, 1, 5)
    spec, over = reflective_masks(dolp, peak, (0.3, 1.0), (0.0, 0.1), (160 / 255, 1.0), intermediate="none")
    # specular: strong DoLP + bright; overexposed: weak DoLP + bright (160/255 inclusive);
    # DoLP 0.2 is neither (the paper read literally); DoLP 0.5 at peak 0.6 < 160/255 is too dark.
    assert spec.flatten().tolist() == [True, False, False, False, False]
    assert over.flatten().tolist() == [False, True, False, False, True]
    # The default gap rule: the unsaturated DoLP-0.2 pixel (peak 0.84 < 1) is specular.
    spec, over = reflective_masks(dolp, peak, (0.3, 1.0), (0.0, 0.1), (160 / 255, 1.0))
    assert spec.flatten().tolist() == [True, False, True, False, False]
    assert over.flatten().tolist() == [False, True, False, False, True]


def test_masks_white_level_and_gap_choices():
    # Peaks 0.5, 2.0 (HDR, above white), 0.9; DoLP 0.2 (between the rules) everywhere.
    peak = torch.tensor([0.5, 2.0, 0.9]).reshape(1, 1, 3)
    dolp = torch.full_like(peak, 0.2)
    rules = dict(specular_dolp=(0.3, 1.0), overexposed_dolp=(0.0, 0.1), intensity_range=(160 / 255, 1.0))
    expect = {
        "none": ([False, False, False], [False, False, False]),
        "specular": ([False, True, True], [False, False, False]),
        "overexposed": ([False, False, False], [False, True, True]),
        "by_saturation": ([False, False, True], [False, True, False]),  # above white = saturated
    }
    for choice, (spec_ok, over_ok) in expect.items():
        spec, over = reflective_masks(dolp, peak, **rules, intermediate=choice)
        assert (spec.flatten().tolist(), over.flatten().tolist()) == (spec_ok, over_ok), choice
    # A value above the white level is bright (it counts as 255), not excluded from both masks.
    spec, over = reflective_masks(torch.tensor([0.5, 0.05]), torch.tensor([3.0, 3.0]), **rules, intermediate="none")
    assert spec.tolist() == [True, False] and over.tolist() == [False, True]
    # A white level of 4 moves the thresholds: peak 2.0 is 2/4 = 128/255 < 160/255, too dark.
    spec, over = reflective_masks(torch.tensor([0.5]), torch.tensor([2.0]), **rules, white_level=4.0)
    assert not spec.any() and not over.any()
    with pytest.raises(ValueError, match="intermediate"):
        reflective_masks(dolp, peak, **rules, intermediate="maybe")


def test_peak_uses_channel_mean_of_brightest_angle():
    # Red channel bright (I0 = 0.95) but the channel mean is dark: not bright.
    stokes = _stokes([[1.9, 0.2, 0.2]], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    assert math.isclose(float(peak_intensity(stokes)), (0.95 + 0.1 + 0.1) / 3, rel_tol=1e-6)
    # s2 dominates: the brightest angle is 45 deg, I45 = (s0 + s2) / 2.
    stokes = _stokes([[1.0]], [[0.1]], [[-0.4]])
    assert math.isclose(float(peak_intensity(stokes)), 0.7, rel_tol=1e-6)  # I135 = (1 + 0.4) / 2


def test_pri_hand_case_drops_clipped_angle():
    angles = torch.tensor(
        [[1.0, 0.7, 0.5], [0.9, 0.5, 0.3], [0.8, 0.5, 0.4], [0.9, 0.6, 0.3]]
    ).reshape(4, 3, 1, 1)
    # angle 0 clips (spread 0.5 ignored); the others spread 0.6, 0.4, 0.6.
    pri = polarimetric_reference_intensity(angles, saturation=254 / 255)
    assert math.isclose(float(pri), (0.6 + 0.4 + 0.6) / 3, rel_tol=1e-6)
    # Every angle clips: uniform mean of the four spreads.
    clipped = torch.tensor([[1.0, 1.0, 0.9], [1.0, 0.8, 0.8], [1.0, 1.0, 1.0], [1.0, 0.9, 0.7]]).reshape(4, 3, 1, 1)
    assert math.isclose(float(polarimetric_reference_intensity(clipped)), (0.1 + 0.2 + 0.0 + 0.3) / 4, rel_tol=1e-6)


def test_pri_invariant_to_white_specular_and_cancels_diffuse_modulation():
    # Diffuse colour d with weak polarization rho, phi, plus a polarized white specular term.
    d = torch.tensor([0.5, 0.3, 0.1])
    rho, phi = 0.08, 0.7
    beta = torch.tensor([0.0, 45.0, 90.0, 135.0]) * math.pi / 180
    diffuse = d[None, :] * (1 + rho * torch.cos(2 * beta - 2 * phi))[:, None] / 2
    specular = (0.2 * (1 - 0.6 * torch.cos(2 * beta - 2 * phi)))[:, None].expand(4, 3)
    angles = (diffuse + specular).reshape(4, 3, 1, 1)
    # The uniform mean over 0/45/90/135 of cos(2 beta - 2 phi) is 0: PRI = (max d - min d) / 2.
    assert math.isclose(float(polarimetric_reference_intensity(angles)), 0.2, rel_tol=1e-5)


def test_diffuse_map_hand_cases():
    stokes = _stokes([[1.0], [0.2]], [[0.3], [0.3]], [[0.4], [0.0]])
    # (1 - 0.5) / 2 = 0.25; a non-physical |s1| > s0 clamps at 0.
    assert torch.allclose(diffuse_map(stokes).flatten(), torch.tensor([0.25, 0.0]))


def test_whiten_features_gives_mahalanobis_distance():
    rng = np.random.default_rng(1)
    raw = rng.normal(size=(2, 6, 7)) * np.array([0.3, 0.05])[:, None, None]
    raw[1] += 0.5 * raw[0]  # correlated features
    features = torch.tensor(raw, dtype=torch.float64)
    mask = torch.ones(1, 6, 7, dtype=torch.bool)
    mask[0, 0, :3] = False
    ridge = 1e-4
    white = whiten_features(features, mask, ridge=ridge)
    samples = raw.reshape(2, -1)[:, mask.reshape(-1).numpy()]
    cov_inv = np.linalg.inv(np.cov(samples) + ridge * np.eye(2))
    delta = raw[:, 2, 3] - raw[:, 5, 1]
    expected = math.sqrt(delta @ cov_inv @ delta)
    got = float(torch.linalg.vector_norm(white[:, 2, 3] - white[:, 5, 1]))
    assert math.isclose(got, expected, rel_tol=1e-9)


def test_propagate_hand_case():
    values = torch.tensor([0.2, 0.4, 0.0, 0.8, 0.6]).reshape(1, 1, 5)
    features = torch.tensor([0.0, 0.5, 0.0, 2.0, 0.3]).reshape(1, 1, 5)
    target = torch.tensor([False, False, True, False, False]).reshape(1, 1, 5)
    donors = ~target
    filled, valid = propagate(values, features, target, donors, radius=2, threshold=0.8)
    # Donor 3 is 2.0 away (rejected); weights exp(-d^2 / 2) for d = 0, 0.5, 0.3.
    w = [1.0, math.exp(-0.125), math.exp(-0.045)]
    expected = (0.2 * w[0] + 0.4 * w[1] + 0.6 * w[2]) / sum(w)
    assert math.isclose(float(filled[0, 0, 2]), expected, rel_tol=1e-6)
    assert valid.flatten().tolist() == [False, False, True, False, False]
    assert float(filled[0, 0, [0, 1, 3, 4]].abs().sum()) == 0
    # Radius 1 reaches donors 1 and 3 only, 3 is rejected.
    filled, _ = propagate(values, features, target, donors, radius=1, threshold=0.8)
    assert math.isclose(float(filled[0, 0, 2]), 0.4, rel_tol=1e-6)
    # No accepted donor: invalid, 0.
    filled, valid = propagate(values, features, target, donors, radius=1, threshold=0.3)
    assert not valid.any() and float(filled.abs().sum()) == 0
    # A target comparing on no component accepts every donor in reach with weight 1.
    filled, _ = propagate(values, features, target, donors, 1, 0.8, components=torch.zeros(1, 1, 5, dtype=torch.bool))
    assert math.isclose(float(filled[0, 0, 2]), (0.4 + 0.8) / 2, rel_tol=1e-6)


@pytest.mark.parametrize("step,confined", [(1, False), (2, False), (1, True)])
def test_propagate_matches_brute_force_loop(step, confined):
    gen = torch.Generator().manual_seed(3)
    C, F, H, W, r, thr = 3, 2, 9, 11, 3, 0.8
    values = torch.rand(C, H, W, generator=gen, dtype=torch.float64)
    features = torch.rand(F, H, W, generator=gen, dtype=torch.float64) * 1.5
    target = torch.rand(1, H, W, generator=gen) < 0.3
    if confined:  # targets in a corner region: exercises the cropped path
        target[:, :, :] = False
        target[:, 5:8, 6:9] = torch.rand(1, 3, 3, generator=gen) < 0.6
    donors = (torch.rand(1, H, W, generator=gen) < 0.6) & ~target
    components = torch.rand(F, H, W, generator=gen) < 0.8
    filled, valid = propagate(values, features, target, donors, r, thr, components, step)
    for y in range(H):
        for x in range(W):
            if not target[0, y, x]:
                continue
            num, den = torch.zeros(C, dtype=torch.float64), 0.0
            # Offsets are the multiples of `step` within the radius (centre included).
            offsets = [o for o in range(-r, r + 1) if o % step == 0]
            for yy in (y + o for o in offsets):
                for xx in (x + o for o in offsets):
                    if not (0 <= yy < H and 0 <= xx < W):
                        continue
                    delta = (features[:, yy, xx] - features[:, y, x]) * components[:, y, x]
                    d = float(torch.linalg.vector_norm(delta))
                    if donors[0, yy, xx] and d < thr:
                        num += math.exp(-d * d / 2) * values[:, yy, xx]
                        den += math.exp(-d * d / 2)
            assert bool(valid[0, y, x]) == (den > 0)
            if den > 0:
                assert torch.allclose(filled[:, y, x], num / den, atol=1e-12)


def test_chromaticity_map_hand_cases():
    i_prop = torch.tensor([0.4, 0.2, 0.2]).reshape(3, 1, 1)
    i_diff = torch.full((3, 1, 1), 0.6)
    # rho_d 0.9: 0.9 * I_prop / (0.8 + 0.6).
    got = chromaticity_map(i_prop, i_diff, rho_d=0.9).flatten()
    assert torch.allclose(got, torch.tensor([0.36, 0.18, 0.18]) / 1.4)
    assert torch.allclose(chromaticity_map(i_prop, i_diff), i_prop)  # brightness-preserving default
    zero = torch.zeros(3, 1, 1)
    assert float(chromaticity_map(zero, zero, rho_d=1.0).abs().sum()) == 0


def _scene_stokes():
    """5x5 RGB view: diffuse colour (0.6, 0.4, 0.2) per angle, unpolarized; a specular pixel at
    (1, 1); an overexposed (clipped white, unpolarized) pixel at (3, 3); a dark background column 0."""
    colour = torch.tensor([0.6, 0.4, 0.2])
    s0 = (2 * colour)[:, None, None].expand(3, 5, 5).clone()
    s1 = torch.zeros(3, 5, 5)
    s2 = torch.zeros(3, 5, 5)
    # Specular: white polarized light 0.5 with DoLP 1 along s1 on top of the diffuse colour.
    s0[:, 1, 1] += 0.5
    s1[:, 1, 1] += 0.5
    s0[:, 3, 3] = 2.0  # every angle at 1.0
    s0[:, :, 0] = 0.0
    return torch.stack([s0, s1, s2])


def test_compute_polar_maps_small_scene():
    stokes = _scene_stokes()
    mask = torch.ones(1, 5, 5, dtype=torch.bool)
    mask[:, :, 0] = False
    # The paper's rules: the specular pixel's red angle image exceeds 1 here, which the default
    # rule (overexposed = clipped) would call overexposed.
    maps = compute_polar_maps(stokes, mask, CorrectionConfig(overexposed_rule="paper"))
    spec = torch.zeros(1, 5, 5, dtype=torch.bool)
    spec[0, 1, 1] = True
    over = torch.zeros(1, 5, 5, dtype=torch.bool)
    over[0, 3, 3] = True
    # Specular pixel: DoLP of the channel-mean Stokes 0.5 / (0.8 + 0.5) and peak (1.3 + 0.5) / 2.
    assert math.isclose(float(maps.dolp[0, 1, 1]), 0.5 / 1.3, rel_tol=1e-5)
    assert torch.equal(maps.specular_mask, spec)
    assert torch.equal(maps.overexposed_mask, over)
    # I_diff at the specular pixel removes the polarized white light: (s0 - 0.5) / 2 = colour.
    assert torch.allclose(maps.i_diff[:, 1, 1], torch.tensor([0.6, 0.4, 0.2]), atol=1e-6)
    # Diffuse pixels: PRI = 0.6 - 0.2 = 0.4 per angle; the clipped pixel has spread 0 (compares on
    # DoLP only) and takes its donors' colour.
    assert math.isclose(float(maps.pri[0, 2, 2]), 0.4, rel_tol=1e-5)
    assert float(maps.pri[0, 3, 3]) == 0
    assert bool(maps.extras["i_chro_valid"][0, 3, 3])
    assert torch.allclose(maps.i_chro[:, 3, 3], torch.tensor([0.6, 0.4, 0.2]), atol=1e-6)
    assert torch.allclose(maps.intensity, stokes[0] / 2)


def test_by_default_overexposed_means_clipped_whatever_the_dolp_and_bright_matte_is_not():
    # Column 0: clipped (some channel of some angle at 1), DoLP 0.2 (a partly clipped highlight);
    # column 1: a light matte surface, bright (peak 0.85 > 160/255) and unpolarized, not clipped;
    # column 2: an unclipped polarized highlight (DoLP 0.5, peak 0.9); column 3: dim diffuse.
    half_s0 = torch.tensor([0.95, 0.85, 0.6, 0.3])[None, None, :].expand(3, 1, 4).clone()
    dolp = torch.tensor([0.2, 0.0, 0.5, 0.02])[None, None, :]
    s0 = 2 * half_s0
    stokes = torch.stack([s0, s0 * dolp, torch.zeros_like(s0)])
    angles = intensities_from_stokes(stokes)
    assert float(angles[:, :, 0, 0].max()) >= 1.0 and float(angles[:, :, 0, 1:].max()) < 254 / 255
    maps = compute_polar_maps(stokes, None, CorrectionConfig())
    assert maps.overexposed_mask[0, 0].tolist() == [True, False, False, False]
    assert maps.specular_mask[0, 0].tolist() == [False, False, True, False]
    paper = compute_polar_maps(stokes, None, CorrectionConfig(overexposed_rule="paper"))
    # The paper's rule: the bright matte pixel is "overexposed" (DoLP <= 0.1, bright); the
    # partly clipped one falls between the DoLP rules and goes by saturation.
    assert paper.overexposed_mask[0, 0].tolist() == [True, True, False, False]


def test_compute_polar_maps_disabled_and_bad_shape():
    maps = compute_polar_maps(_scene_stokes(), None, CorrectionConfig(enabled=False))
    assert maps.specular_mask is None and maps.i_chro is None and maps.dolp.shape == (1, 5, 5)
    with pytest.raises(ValueError, match=r"\(3, C, H, W\)"):
        compute_polar_maps(torch.zeros(2, 3, 4, 4))
