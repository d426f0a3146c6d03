"""Stokes, AoLP, DoLP, Imax/Imin against Malus' law written here and against polanalyser."""

import math

import numpy as np
import polanalyser as pa
import pytest
import torch

from polargs_plugin.optics import (
    POLARIZER_ANGLES_DEG,
    aolp_from_stokes,
    dolp_from_stokes,
    imax_imin_from_stokes,
    intensities_from_stokes,
    stokes_from_intensities,
    wrap_angle,
)


def _random_stokes(shape, seed=0, dtype=torch.float64):
    """Physical Stokes (DoLP <= 1) of shape (*, 3, C, H, W) from random s0, rho, phi."""
    g = torch.Generator().manual_seed(seed)
    s0 = torch.rand(shape, generator=g, dtype=dtype) + 0.1
    rho = torch.rand(shape, generator=g, dtype=dtype)
    phi = torch.rand(shape, generator=g, dtype=dtype) * math.pi
    return torch.stack([s0, s0 * rho * torch.cos(2 * phi), s0 * rho * torch.sin(2 * phi)], dim=-4), rho, phi


def _malus(s0, rho, phi, beta):
    """Independent Malus law: I(beta) = s0/2 (1 + rho cos 2(beta - phi))."""
    return 0.5 * s0 * (1 + rho * torch.cos(2 * (beta - phi)))


def _circular_diff(a, b, period=math.pi):
    d = torch.remainder(a - b, period)
    return torch.minimum(d, period - d)


def test_standard_angles_constant():
    assert POLARIZER_ANGLES_DEG == (0, 45, 90, 135)


def test_closed_form_recovers_known_s0_rho_phi():
    stokes, rho, phi = _random_stokes((2, 3, 5, 7))
    s0 = stokes.select(-4, 0)
    images = torch.stack([_malus(s0, rho, phi, math.radians(b)) for b in (0, 45, 90, 135)], dim=-4)
    out = stokes_from_intensities(images)
    assert out.shape == (2, 3, 3, 5, 7)
    torch.testing.assert_close(out, stokes)
    torch.testing.assert_close(dolp_from_stokes(out), rho)
    assert float(_circular_diff(aolp_from_stokes(out), phi).max()) < 1e-9


def test_closed_form_definition():
    g = torch.Generator().manual_seed(1)
    i = torch.rand(4, 3, 6, 6, generator=g)
    s = stokes_from_intensities(i)
    torch.testing.assert_close(s[0], (i[0] + i[1] + i[2] + i[3]) / 2)
    torch.testing.assert_close(s[1], i[0] - i[2])
    torch.testing.assert_close(s[2], i[1] - i[3])


def test_least_squares_equals_closed_form_at_standard_angles():
    g = torch.Generator().manual_seed(2)
    i = torch.rand(3, 4, 2, 5, 5, generator=g, dtype=torch.float64)
    angles = [math.radians(a) for a in POLARIZER_ANGLES_DEG]
    torch.testing.assert_close(stokes_from_intensities(i, angles), stokes_from_intensities(i), rtol=0, atol=1e-13)


@pytest.mark.parametrize("count", [3, 5, 8])
def test_least_squares_arbitrary_angles_round_trip_and_polanalyser(count):
    g = torch.Generator().manual_seed(count)
    angles = torch.sort(torch.rand(count, generator=g, dtype=torch.float64) * math.pi).values
    stokes, rho, phi = _random_stokes((1, 4, 4), seed=count)
    s0 = stokes[0]
    images = torch.stack([_malus(s0, rho, phi, b) for b in angles], dim=0)
    torch.testing.assert_close(intensities_from_stokes(stokes, angles), images)
    torch.testing.assert_close(stokes_from_intensities(images, angles), stokes)
    # Noisy measurements: least squares must agree with polanalyser's pseudo-inverse.
    noisy = images + 0.01 * torch.randn(images.shape, generator=g, dtype=torch.float64)
    ref = pa.calcLinearStokes(noisy.numpy(), angles.numpy())  # (*, 3) with Stokes last
    ours = stokes_from_intensities(noisy, angles.tolist())
    np.testing.assert_allclose(np.moveaxis(ours.numpy(), 0, -1), ref, atol=1e-12)


def test_malus_default_angles_and_imax_imin_against_dense_sweep():
    stokes, rho, phi = _random_stokes((2, 8, 8), seed=3)
    images = intensities_from_stokes(stokes)
    beta = torch.tensor([0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4], dtype=torch.float64)
    for k in range(4):
        torch.testing.assert_close(images[k], _malus(stokes[0], rho, phi, beta[k]))
    sweep = torch.linspace(0, math.pi, 3601, dtype=torch.float64)
    dense = intensities_from_stokes(stokes, sweep)
    imax, imin = imax_imin_from_stokes(stokes)
    torch.testing.assert_close(imax, dense.max(dim=0).values, rtol=0, atol=1e-6)
    torch.testing.assert_close(imin, dense.min(dim=0).values, rtol=0, atol=1e-6)
    s_last = np.moveaxis(stokes.numpy(), 0, -1)
    np.testing.assert_allclose(imax.numpy(), pa.cvtStokesToImax(s_last), atol=1e-12)
    np.testing.assert_allclose(imin.numpy(), pa.cvtStokesToImin(s_last), atol=1e-12)


def test_aolp_dolp_match_polanalyser():
    stokes, _, _ = _random_stokes((3, 16, 16), seed=4)
    s_last = np.moveaxis(stokes.numpy(), 0, -1)
    np.testing.assert_allclose(dolp_from_stokes(stokes).numpy(), pa.cvtStokesToDoLP(s_last), atol=1e-12)
    ours = aolp_from_stokes(stokes)
    ref = torch.from_numpy(pa.cvtStokesToAoLP(s_last))
    assert float(_circular_diff(ours, ref).max()) < 1e-12


def test_aolp_wraps_into_half_open_range():
    # Tiny negative s2 with s1 > 0 gives atan2 -> 0^-; the result must wrap to ~pi, never reach pi.
    for dtype in (torch.float32, torch.float64):
        s = torch.tensor([[1.0, 1.0, 1.0, 1.0], [1.0, -1.0, 1.0, -1.0], [-1e-30, -1e-9, 1e-9, 0.0]], dtype=dtype)
        aolp = aolp_from_stokes(s.reshape(3, 1, 1, 4)).flatten()
        assert bool((aolp >= 0).all()) and bool((aolp < math.pi).all())
        # Expected phi: ~pi (wrapped, not clipped to 0), ~pi/2, ~0, pi/2.
        expected = torch.tensor([math.pi, math.pi / 2, 0.0, math.pi / 2], dtype=dtype)
        assert float(_circular_diff(aolp, expected).max()) < 1e-6
    assert float(wrap_angle(torch.tensor(-1e-9, dtype=torch.float32))) < math.pi


def test_dolp_safe_at_zero_intensity_and_clamped():
    s = torch.tensor([[0.0, 0.0, -0.1, 0.5, 1.0], [0.0, 0.1, 0.1, 0.9, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]])
    s = s.reshape(3, 1, 1, 5).requires_grad_(True)
    dolp = dolp_from_stokes(s)
    assert torch.equal(dolp.detach().flatten(), torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0]))
    dolp.sum().backward()
    assert bool(torch.isfinite(s.grad).all())


def test_batched_equals_per_item_and_dtype_follows_input():
    g = torch.Generator().manual_seed(5)
    i = torch.rand(2, 3, 4, 3, 5, 6, generator=g)
    s = stokes_from_intensities(i)
    assert s.shape == (2, 3, 3, 3, 5, 6) and s.dtype == torch.float32
    torch.testing.assert_close(s[1, 2], stokes_from_intensities(i[1, 2]))
    assert stokes_from_intensities(i.double(), [0, 0.7, 1.4, 2.1]).dtype == torch.float64
    assert aolp_from_stokes(s).shape == (2, 3, 3, 5, 6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    g = torch.Generator().manual_seed(6)
    i = torch.rand(4, 3, 9, 9, generator=g)
    angles = [0.1, 0.9, 1.7, 2.5]
    for args in ((), (angles,)):
        cpu = stokes_from_intensities(i, *args)
        gpu = stokes_from_intensities(i.cuda(), *args)
        assert gpu.is_cuda
        torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(aolp_from_stokes(cpu.cuda()).cpu(), aolp_from_stokes(cpu), rtol=0, atol=1e-5)
    torch.testing.assert_close(dolp_from_stokes(cpu.cuda()).cpu(), dolp_from_stokes(cpu), rtol=0, atol=1e-5)


def test_errors():
    with pytest.raises(ValueError, match="at least 3"):
        stokes_from_intensities(torch.zeros(2, 1, 2, 2), [0.0, 1.0])
    with pytest.raises(ValueError, match="dim -4"):
        stokes_from_intensities(torch.zeros(4, 1, 2, 2), [0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="0/45/90/135"):
        stokes_from_intensities(torch.zeros(3, 1, 2, 2))
    with pytest.raises(ValueError, match="do not determine"):
        stokes_from_intensities(torch.zeros(3, 1, 2, 2), [0.0, math.pi, 2 * math.pi])
    with pytest.raises(ValueError, match=r"\(\.\.\., A, C, H, W\)"):
        stokes_from_intensities(torch.zeros(4, 2, 2))
    with pytest.raises(ValueError, match="3 components"):
        aolp_from_stokes(torch.zeros(4, 1, 2, 2))
    with pytest.raises(TypeError):
        stokes_from_intensities(np.zeros((4, 1, 2, 2)))
