"""Fresnel DoLP closed forms against the Fresnel equations written independently here."""

import math

import pytest
import torch

from polargs_plugin.optics import (
    dolp_diffuse,
    dolp_diffuse_max,
    dolp_specular,
    dolp_specular_conductor,
    fresnel_reflectance,
    fresnel_reflectance_conductor,
    zenith_from_dolp_diffuse,
)

THETA = torch.linspace(1e-4, math.pi / 2 - 1e-4, 2001, dtype=torch.float64)


@pytest.mark.parametrize("n", [1.3, 1.5, 1.8, 2.5])
def test_reflectance_matches_angle_form_of_fresnel_equations(n):
    # Snell's law, then R_s = sin^2(ti - tt) / sin^2(ti + tt), R_p = tan^2(ti - tt) / tan^2(ti + tt).
    theta_t = torch.asin(torch.sin(THETA) / n)
    rs_ref = (torch.sin(THETA - theta_t) / torch.sin(THETA + theta_t)) ** 2
    rp_ref = (torch.tan(THETA - theta_t) / torch.tan(THETA + theta_t)) ** 2
    rs, rp = fresnel_reflectance(THETA, n)
    torch.testing.assert_close(rs, rs_ref, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(rp, rp_ref, rtol=1e-9, atol=1e-12)


def test_reflectance_at_normal_incidence():
    rs, rp = fresnel_reflectance(torch.zeros(3, dtype=torch.float64), 1.5)
    expected = torch.full((3,), ((1.5 - 1) / (1.5 + 1)) ** 2, dtype=torch.float64)
    torch.testing.assert_close(rs, expected)
    torch.testing.assert_close(rp, expected)


@pytest.mark.parametrize("n", [1.3, 1.5, 1.8, 2.5])
def test_closed_forms_equal_fresnel_ratios(n):
    rs, rp = fresnel_reflectance(THETA, n)
    ts, tp = 1 - rs, 1 - rp
    torch.testing.assert_close(dolp_specular(THETA, n), (rs - rp) / (rs + rp), rtol=0, atol=1e-12)
    torch.testing.assert_close(dolp_diffuse(THETA, n), (tp - ts) / (tp + ts), rtol=0, atol=1e-12)


def test_specular_dolp_is_one_at_brewster_and_two_valued():
    n = 1.5
    brewster = torch.tensor(math.atan(n), dtype=torch.float64)
    assert float(dolp_specular(brewster, n)) == pytest.approx(1.0, abs=1e-12)
    rho = dolp_specular(THETA, n)
    assert float(rho.max()) <= 1 + 1e-12 and float(rho.min()) >= 0
    peak = int(rho.argmax())
    assert abs(float(THETA[peak]) - math.atan(n)) < 1e-3
    assert bool((rho[1 : peak + 1] > rho[:peak]).all()) and bool((rho[peak + 1 :] < rho[peak:-1]).all())


def test_diffuse_dolp_reference_values_and_monotonic():
    # Published values of the diffuse DoLP for n = 1.5 (Atkinson & Hancock 2006, Fig. 3), to 3 %.
    theta = torch.deg2rad(torch.tensor([10.0, 30.0, 60.0, 80.0], dtype=torch.float64))
    expected = torch.tensor([0.0017, 0.017, 0.096, 0.25], dtype=torch.float64)
    torch.testing.assert_close(dolp_diffuse(theta, 1.5), expected, rtol=0.03, atol=2e-4)
    rho = dolp_diffuse(THETA, 1.5)
    assert bool((rho[1:] > rho[:-1]).all())
    assert float(dolp_diffuse(torch.tensor(math.pi / 2, dtype=torch.float64), 1.5)) == pytest.approx(
        float(dolp_diffuse_max(torch.tensor(1.5, dtype=torch.float64))), abs=1e-12
    )


@pytest.mark.parametrize("n", [1.3, 1.5, 2.5])
def test_zenith_from_diffuse_dolp_inverts(n):
    theta = torch.linspace(0.0, math.pi / 2, 501, dtype=torch.float64)
    torch.testing.assert_close(zenith_from_dolp_diffuse(dolp_diffuse(theta, n), n), theta, rtol=0, atol=1e-6)


def test_zenith_from_diffuse_dolp_clamps_out_of_range():
    rho = torch.tensor([-0.1, 0.0, 0.9], dtype=torch.float64)
    theta = zenith_from_dolp_diffuse(rho, 1.5)
    torch.testing.assert_close(theta, torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))


def test_float32_and_tensor_index_broadcast():
    theta = torch.tensor([[0.2], [1.0]], dtype=torch.float32)
    n = torch.tensor([1.4, 1.6], dtype=torch.float32)
    rho = dolp_diffuse(theta, n)
    assert rho.shape == (2, 2) and rho.dtype == torch.float32
    expected = torch.stack([dolp_diffuse(theta[:, 0].double(), float(k)) for k in n], dim=1).float()
    torch.testing.assert_close(rho, expected)
    torch.testing.assert_close(zenith_from_dolp_diffuse(rho, n), theta.expand(2, 2), rtol=0, atol=1e-3)


@pytest.mark.parametrize("n, k", [(0.43, 2.46), (1.02, 2.58), (0.96, 6.69), (2.9, 3.0)])
def test_conductor_reflectance_at_normal_incidence_and_grazing(n, k):
    # R(0) = ((n - 1)^2 + k^2) / ((n + 1)^2 + k^2) for both polarizations; R -> 1 at grazing
    rs, rp = fresnel_reflectance_conductor(torch.tensor([0.0, math.pi / 2], dtype=torch.float64), n, k)
    expected = ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)
    torch.testing.assert_close(rs[0], torch.tensor(expected, dtype=torch.float64))
    torch.testing.assert_close(rp[0], torch.tensor(expected, dtype=torch.float64))
    torch.testing.assert_close(rs[1], torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(rp[1], torch.tensor(1.0, dtype=torch.float64))


@pytest.mark.parametrize("n, k", [(0.43, 2.46), (1.02, 2.58), (0.96, 6.69), (2.9, 3.0)])
def test_conductor_reflectance_matches_the_explicit_complex_formulas(n, k):
    # the reflection coefficients written with Python complex numbers, one angle at a time
    index = complex(n, k)
    for theta in THETA[::200].tolist():
        cos_i, sin_i = math.cos(theta), math.sin(theta)
        cos_t = (1 - sin_i**2 / index**2) ** 0.5
        r_s = (cos_i - index * cos_t) / (cos_i + index * cos_t)
        r_p = (index * cos_i - cos_t) / (index * cos_i + cos_t)
        rs, rp = fresnel_reflectance_conductor(torch.tensor(theta, dtype=torch.float64), n, k)
        assert float(rs) == pytest.approx(abs(r_s) ** 2, rel=1e-10)
        assert float(rp) == pytest.approx(abs(r_p) ** 2, rel=1e-10)
    # s is reflected more than p at every oblique angle: the DoLP is positive (AoLP = azimuth + pi/2)
    rho = dolp_specular_conductor(THETA, n, k)
    assert bool((rho > 0).all()) and float(rho.max()) < 1


@pytest.mark.parametrize("n", [1.3, 1.5, 1.8])
def test_conductor_formulas_without_extinction_are_the_dielectric_ones(n):
    rs, rp = fresnel_reflectance_conductor(THETA, n, 0.0)
    rs_ref, rp_ref = fresnel_reflectance(THETA, n)
    torch.testing.assert_close(rs, rs_ref, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(rp, rp_ref, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(dolp_specular_conductor(THETA, n, 0.0), dolp_specular(THETA, n), rtol=0, atol=1e-9)
