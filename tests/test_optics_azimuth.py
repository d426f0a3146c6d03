"""AoLP / azimuth conventions pinned on an analytically rendered sphere and by projection geometry."""

import math

import pytest
import torch

from polargs_plugin.optics import (
    DIFFUSE_AOLP_OFFSET,
    SPECULAR_AOLP_OFFSET,
    aolp_from_normals,
    aolp_from_stokes,
    aolp_to_clockwise,
    azimuth_candidates,
    dolp_weight,
    normal_azimuth,
    normals_from_azimuth,
    pixel_rays,
    stokes_from_intensities,
    wrap_aolp,
    zenith_from_normals,
)

SIZE = 65  # odd, so that one pixel centre sits exactly on the sphere centre


def _sphere(size=SIZE, radius_px=28.0):
    """Orthographic unit sphere centred in the image: camera-frame normals, mask, pixel offsets."""
    coords = torch.arange(size, dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(coords, coords, indexing="ij")
    du, dv = u - size / 2, v - size / 2  # offset from the centre, image y down
    x, y = du / radius_px, dv / radius_px
    r2 = x**2 + y**2
    mask = (r2 < 0.98) & (r2 > 1e-6)
    z = -torch.sqrt(torch.clamp(1 - r2, min=0))  # facing the camera: n_z < 0
    normals = torch.stack([x, y, z]) * mask
    return normals, mask, du, dv


def _circular_diff(a, b, period=math.pi):
    d = torch.remainder(a - b, period)
    return torch.minimum(d, period - d)


def _random_normals(count, seed, dtype=torch.float64, max_zenith=1.4):
    g = torch.Generator().manual_seed(seed)
    az = torch.rand(count, generator=g, dtype=dtype) * 2 * math.pi
    ze = torch.rand(count, generator=g, dtype=dtype) * max_zenith
    return torch.stack([torch.sin(ze) * torch.cos(az), torch.sin(ze) * torch.sin(az), -torch.cos(ze)])


def test_offsets_constants():
    assert DIFFUSE_AOLP_OFFSET == 0.0
    assert SPECULAR_AOLP_OFFSET == pytest.approx(math.pi / 2)


def test_sphere_diffuse_aolp_is_radial_and_specular_tangential():
    normals, mask, du, dv = _sphere()
    radial = torch.remainder(torch.atan2(-dv, du), math.pi)  # ccw angle, image y flipped
    diffuse = aolp_from_normals(normals, "diffuse")[0]
    specular = aolp_from_normals(normals, "specular")[0]
    assert float(_circular_diff(diffuse, radial)[mask].max()) < 1e-9
    # Tangential: the specular polarization direction (cos, -sin) in image coords is orthogonal
    # to the radial pixel offset.
    dot = torch.cos(specular) * du - torch.sin(specular) * dv
    assert float((dot[mask] / torch.hypot(du, dv)[mask]).abs().max()) < 1e-9
    # The pixel directly above the centre (one row up, same column) gives pi/2.
    centre = SIZE // 2
    assert float(diffuse[centre - 5, centre]) == pytest.approx(math.pi / 2, abs=1e-12)
    assert float(diffuse[centre, centre + 5]) == pytest.approx(0.0, abs=1e-12)


def test_sphere_through_malus_and_stokes_gives_radial_aolp():
    # Diffuse light is brightest behind a polarizer aligned with the radial direction;
    # images are synthesised with Malus' law, then Stokes -> AoLP must give back that direction.
    normals, mask, du, dv = _sphere()
    radial = torch.atan2(-dv, du)
    zenith = zenith_from_normals(normals)[0]
    rho = torch.sin(zenith) ** 2 * 0.3
    images = torch.stack(
        [0.5 * (1 + rho * torch.cos(2 * (math.radians(b) - radial))) for b in (0, 45, 90, 135)]
    ).unsqueeze(1)
    aolp = aolp_from_stokes(stokes_from_intensities(images))[0]
    assert float(_circular_diff(aolp, aolp_from_normals(normals)[0])[mask].max()) < 1e-9


def test_sphere_zenith_matches_geometry():
    normals, mask, du, dv = _sphere()
    expected = torch.asin(torch.clamp(torch.hypot(du, dv) / 28.0, max=1.0))
    torch.testing.assert_close(zenith_from_normals(normals)[0][mask], expected[mask])


def _intrinsics(f=80.0, cx=32.5, cy=24.5):
    return torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=torch.float64)


def test_pixel_rays_use_half_pixel_centres():
    K = _intrinsics()
    rays = pixel_rays(K, 48, 64)
    assert rays.shape == (3, 48, 64)
    # Pixel (u=32, v=24) has its centre at (32.5, 24.5): the principal point.
    torch.testing.assert_close(rays[:, 24, 32], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(rays[:, 0, 0], torch.tensor([-32 / 80, -24 / 80, 1.0], dtype=torch.float64))


def test_perspective_equals_orthographic_at_principal_point():
    K = _intrinsics()
    n = _random_normals(48 * 64, seed=1).reshape(3, 48, 64)
    ppa = normal_azimuth(n, K, "perspective")[0, 24, 32]
    ortho = normal_azimuth(n, model="orthographic")[0, 24, 32]
    assert float(_circular_diff(ppa, ortho, 2 * math.pi)) < 1e-12
    away = _circular_diff(normal_azimuth(n, K, "perspective"), normal_azimuth(n), 2 * math.pi)
    assert float(away.max()) > 0.1  # the models do differ off-axis


def test_perspective_azimuth_is_direction_of_projected_normal():
    # Independent geometry: project a surface point P on each pixel ray and P + eps * n; the image
    # displacement points along the PPA azimuth (full circle, ccw with image y flipped).
    K = _intrinsics()
    n = _random_normals(48 * 64, seed=2).reshape(3, 48, 64)
    depth = 3.0
    point = pixel_rays(K, 48, 64) * depth
    moved = point + 1e-7 * n
    proj = lambda p: (K @ p.reshape(3, -1)).reshape(3, 48, 64)  # noqa: E731
    a, b = proj(point), proj(moved)
    du = b[0] / b[2] - a[0] / a[2]
    dv = b[1] / b[2] - a[1] / a[2]
    expected = torch.atan2(-dv, du)
    alpha = normal_azimuth(n, K, "perspective")[0]
    assert float(_circular_diff(alpha, expected, 2 * math.pi).max()) < 1e-5


@pytest.mark.parametrize("model", ["orthographic", "perspective"])
def test_normals_from_azimuth_inverts_azimuth_and_zenith(model):
    K = _intrinsics().unsqueeze(0).expand(2, 3, 3)
    g = torch.Generator().manual_seed(3)
    az = torch.rand(2, 4, 48, 64, generator=g, dtype=torch.float64) * 2 * math.pi
    ze = torch.rand(2, 1, 48, 64, generator=g, dtype=torch.float64) * 1.4
    n = normals_from_azimuth(az, ze, K, model)
    assert n.shape == (2, 4, 3, 48, 64)
    torch.testing.assert_close(torch.linalg.vector_norm(n, dim=-3), torch.ones(2, 4, 48, 64, dtype=torch.float64))
    flat = n.transpose(0, 1)  # (4, 2, 3, H, W): the candidates as a batch over K's batch
    alpha = normal_azimuth(flat, K, model).squeeze(-3).transpose(0, 1)
    zen = zenith_from_normals(flat, K, model).squeeze(-3).transpose(0, 1)
    assert float(_circular_diff(alpha, az, 2 * math.pi).max()) < 1e-9
    torch.testing.assert_close(zen, ze.expand(2, 4, 48, 64))
    view = pixel_rays(_intrinsics(), 48, 64) if model == "perspective" else torch.tensor([0.0, 0, 1]).reshape(3, 1, 1)
    assert bool(((n * view.double()).sum(-3) < 0).all())  # facing the camera


@pytest.mark.parametrize("kind", ["diffuse", "specular"])
@pytest.mark.parametrize("model", ["orthographic", "perspective"])
def test_azimuth_candidates_contain_true_azimuth(kind, model):
    K = _intrinsics()
    n = _random_normals(48 * 64, seed=4).reshape(3, 48, 64)
    aolp = aolp_from_normals(n, kind, K, model)
    cands = azimuth_candidates(aolp)
    assert cands.shape == (4, 48, 64)
    assert bool((cands >= 0).all()) and bool((cands < 2 * math.pi).all())
    truth = normal_azimuth(n, K, model)
    assert float(_circular_diff(cands, truth, 2 * math.pi).min(dim=0).values.max()) < 1e-9
    # The candidates are phi - pi/2, phi, phi + pi/2, phi + pi in that order.
    expected = torch.cat([aolp - math.pi / 2, aolp, aolp + math.pi / 2, aolp + math.pi])
    assert float(_circular_diff(cands, expected, 2 * math.pi).max()) < 1e-12


def test_normals_from_candidates_reproduce_aolp():
    n = _random_normals(32, seed=5).reshape(3, 4, 8)
    aolp = aolp_from_normals(n)
    cand_normals = normals_from_azimuth(azimuth_candidates(aolp), zenith_from_normals(n))
    back = aolp_from_normals(cand_normals)
    expected = (aolp + torch.tensor([0.5, 0.0, 0.5, 0.0], dtype=torch.float64).reshape(4, 1, 1, 1) * math.pi)
    assert float(_circular_diff(back, wrap_aolp(expected)).max()) < 1e-9


def test_dolp_weight_formula():
    rho = torch.linspace(0, 1, 11, dtype=torch.float64)
    for sigma in (0.5, 0.2):
        expected = torch.exp(-((1 - rho) ** 2) / (2 * sigma**2)) + torch.exp(-(rho**2) / (2 * sigma**2))
        torch.testing.assert_close(dolp_weight(rho, sigma), expected)
    torch.testing.assert_close(dolp_weight(rho), dolp_weight(1 - rho))
    assert float(dolp_weight(torch.tensor(0.5, dtype=torch.float64))) == pytest.approx(2 * math.exp(-0.5))


def test_wrap_aolp_wraps_and_round_trips_pisr_range():
    x = torch.tensor([-1e-7, 0.0, 1e-7, math.pi - 1e-7, math.pi, math.pi + 1e-7, -math.pi / 2, 7.0])
    w = wrap_aolp(x)
    assert bool((w >= 0).all()) and bool((w < math.pi).all())
    assert float(_circular_diff(w, x).max()) < 1e-6
    near = wrap_aolp(torch.tensor([-1e-3, math.pi + 1e-3]))
    assert float(near[0]) == pytest.approx(math.pi - 1e-3) and float(near[1]) == pytest.approx(1e-3, abs=1e-6)  # not clipped
    pisr = torch.linspace(-math.pi / 2, math.pi / 2 - 1e-3, 101, dtype=torch.float64)
    back = torch.where(wrap_aolp(pisr) >= math.pi / 2, wrap_aolp(pisr) - math.pi, wrap_aolp(pisr))
    torch.testing.assert_close(back, pisr)


def test_clockwise_conversion_is_involution_and_matches_mvas():
    g = torch.Generator().manual_seed(6)
    aolp = torch.rand(1000, generator=g, dtype=torch.float64) * math.pi
    twice = aolp_to_clockwise(aolp_to_clockwise(aolp))
    assert float(_circular_diff(twice, aolp).max()) < 1e-12
    # MVAS: clockwise azimuth with y down, phi = atan2(n_y, n_x) (MVAS's convention).
    n = _random_normals(64, seed=7).reshape(3, 8, 8)
    mvas = torch.remainder(torch.atan2(n[1], n[0]), math.pi)
    assert float(_circular_diff(aolp_to_clockwise(aolp_from_normals(n)[0]), mvas).max()) < 1e-12


def test_float32_in_float32_out():
    n = _random_normals(12, seed=8, dtype=torch.float32).reshape(3, 3, 4)
    K = _intrinsics(cx=2.0, cy=1.5)
    for out in (normal_azimuth(n, K, "perspective"), aolp_from_normals(n), zenith_from_normals(n, K, "perspective")):
        assert out.dtype == torch.float32 and out.shape == (1, 3, 4)
    assert normals_from_azimuth(torch.zeros(2, 3, 4), torch.zeros(1, 3, 4), K, "perspective").dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    K = _intrinsics()
    n = _random_normals(48 * 64, seed=9, dtype=torch.float32).reshape(3, 48, 64)
    for model in ("orthographic", "perspective"):
        cpu = aolp_from_normals(n, "specular", K, model)
        gpu = aolp_from_normals(n.cuda(), "specular", K.cuda(), model)
        assert gpu.is_cuda
        assert float(_circular_diff(gpu.cpu(), cpu).max()) < 1e-4
        back = normals_from_azimuth(azimuth_candidates(gpu), zenith_from_normals(n.cuda(), K, model), K, model)
        assert back.is_cuda and back.shape == (4, 3, 48, 64)


def test_errors():
    n = torch.zeros(3, 4, 4)
    with pytest.raises(ValueError, match="needs the intrinsics"):
        normal_azimuth(n, model="perspective")
    with pytest.raises(ValueError, match="unknown azimuth model"):
        normal_azimuth(n, model="weak")
    with pytest.raises(ValueError, match="unknown reflection kind"):
        aolp_from_normals(n, "glossy")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, H, W\)"):
        normal_azimuth(torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 1, H, W\)"):
        azimuth_candidates(torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match="zenith"):
        normals_from_azimuth(torch.zeros(4, 4, 4), torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        pixel_rays(torch.eye(4), 2, 2)
