"""Property tests of optics/ (hypothesis): Stokes round trips, AoLP / DoLP ranges, demosaic
linearity, Fresnel DoLP monotonicity in the zenith angle."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polargs_plugin.optics.fresnel import dolp_diffuse, dolp_specular
from polargs_plugin.optics.mosaic import demosaic_polar, mosaic_from_intensities
from polargs_plugin.optics.stokes import (
    aolp_from_stokes,
    dolp_from_stokes,
    intensities_from_stokes,
    stokes_from_intensities,
)

# database=None: no .hypothesis folder in the working tree; derandomize: the same examples every run.
FAST = settings(max_examples=60, deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])

finite = st.floats(min_value=0.0, max_value=1.0, allow_nan=False, width=32)


@st.composite
def valid_stokes(draw, channels: int = 3, size: int = 4) -> torch.Tensor:
    """(3, C, H, W) physically valid Stokes: s0 >= 0, s1^2 + s2^2 <= s0^2 (edge cases included:
    s0 = 0, DoLP exactly 0 or 1, signed zeros)."""
    shape = (channels, size, size)
    s0 = draw(arrays(np.float64, shape, elements=st.floats(0.0, 20.0, allow_nan=False)))
    dolp = draw(arrays(np.float64, shape, elements=st.sampled_from([0.0, 1.0]) | st.floats(0.0, 1.0)))
    angle = draw(arrays(np.float64, shape, elements=st.sampled_from([0.0, -0.0, math.pi, -math.pi / 2])
                        | st.floats(-4 * math.pi, 4 * math.pi)))
    s1 = s0 * dolp * np.cos(2 * angle)
    s2 = s0 * dolp * np.sin(2 * angle)
    signed = draw(st.booleans())
    if signed:  # exercise atan2(+-0, negative) branches
        s2 = np.where(np.abs(s2) < 1e-12, -0.0, s2)
    return torch.from_numpy(np.stack([s0, s1, s2])).to(torch.float32)


@FAST
@given(valid_stokes())
def test_stokes_to_intensities_to_stokes_round_trip(stokes):
    back = stokes_from_intensities(intensities_from_stokes(stokes))
    scale = 1e-5 * (1.0 + stokes.abs().max())
    assert torch.allclose(back, stokes, atol=float(scale), rtol=0)


@FAST
@given(arrays(np.float32, (4, 3, 3, 5), elements=finite))
def test_intensities_to_stokes_to_intensities_is_the_consistent_projection(raw):
    """Four arbitrary angle images are over-determined (I0 + I90 = I45 + I135 for real light): the
    round trip returns the least-squares consistent images, and is the identity on those."""
    intensities = torch.from_numpy(raw)
    once = intensities_from_stokes(stokes_from_intensities(intensities))
    twice = intensities_from_stokes(stokes_from_intensities(once))
    assert torch.allclose(twice, once, atol=1e-5)
    assert torch.allclose(once[0] + once[2], once[1] + once[3], atol=1e-5)
    # Consistent input (from a valid Stokes vector) comes back unchanged.
    assert torch.allclose(intensities_from_stokes(stokes_from_intensities(once)), once, atol=1e-5)


@FAST
@given(valid_stokes())
def test_aolp_in_half_open_range_and_dolp_in_unit_range(stokes):
    aolp = aolp_from_stokes(stokes)
    dolp = dolp_from_stokes(stokes)
    assert torch.isfinite(aolp).all() and torch.isfinite(dolp).all()
    assert bool((aolp >= 0).all()) and bool((aolp < math.pi).all())
    assert bool((dolp >= 0).all()) and bool((dolp <= 1).all())


@FAST
@given(st.floats(-1e-7, 0.0, allow_nan=False), st.floats(-1.0, -1e-3))
def test_aolp_never_reaches_pi_for_tiny_negative_angles(s2, s1):
    """0.5 atan2(s2, s1) just below 0 (or at -pi/2) must wrap to [0, pi), never to pi itself."""
    for dtype in (torch.float32, torch.float64):
        stokes = torch.tensor([1.0, s1, s2], dtype=dtype).reshape(3, 1, 1, 1)
        aolp = float(aolp_from_stokes(stokes))
        assert 0.0 <= aolp < math.pi


@FAST
@given(
    arrays(np.float32, (8, 12), elements=finite),
    arrays(np.float32, (8, 12), elements=finite),
    st.floats(0.0, 1.0),
    st.sampled_from(["mono", "rgb"]),
)
@pytest.mark.slow
def test_demosaic_is_linear(x, y, a, pattern):
    """demosaic(a x + (1 - a) y) = a demosaic(x) + (1 - a) demosaic(y) for float raws in [0, 1]."""
    b = 1.0 - a
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    mixed = (a * xt + b * yt).clamp(0, 1)
    lhs = demosaic_polar(mixed, pattern)
    rhs = a * demosaic_polar(xt, pattern) + b * demosaic_polar(yt, pattern)
    assert torch.allclose(lhs, rhs, atol=1e-5)


@FAST
@given(arrays(np.float32, (4, 1, 8, 8), elements=finite))
def test_demosaic_of_a_uniform_mosaic_returns_its_angles(values):
    """Constant angle images survive mosaic -> demosaic exactly (interpolation of a constant)."""
    intensities = torch.from_numpy(values[:, :, :1, :1]).expand(4, 1, 8, 8).contiguous()
    raw = mosaic_from_intensities(intensities, "mono")  # (H, W)
    assert torch.allclose(demosaic_polar(raw, "mono"), intensities, atol=1e-6)


zenith_pairs = st.tuples(st.floats(0.0, math.pi / 2 - 1e-3), st.floats(0.0, math.pi / 2 - 1e-3)).map(sorted)
indices = st.floats(1.2, 3.0)


@FAST
@given(zenith_pairs, indices)
def test_diffuse_dolp_increases_with_zenith(pair, n):
    lo, hi = pair
    values = dolp_diffuse(torch.tensor([lo, hi], dtype=torch.float64), n)
    assert float(values[1]) >= float(values[0]) - 1e-12
    assert 0.0 <= float(values.min()) and float(values.max()) <= 1.0


@FAST
@given(zenith_pairs, indices)
def test_specular_dolp_rises_to_brewster_then_falls(pair, n):
    lo, hi = pair
    brewster = math.atan(n)
    values = dolp_specular(torch.tensor([lo, hi, brewster], dtype=torch.float64), n)
    if hi <= brewster:
        assert float(values[1]) >= float(values[0]) - 1e-12
    elif lo >= brewster:
        assert float(values[1]) <= float(values[0]) + 1e-12
    assert float(values[2]) == pytest.approx(1.0, abs=1e-9)
    assert float(values[:2].max()) <= 1.0 + 1e-12 and float(values[:2].min()) >= 0.0
