"""PatchMatch recovers analytic geometry from corrupted starts; the AoLP term helps on textureless
surfaces; the cost terms match their definitions."""

import math

import pytest
import torch
import torch.nn.functional as F

from polargs_plugin.config import PatchMatchConfig
from polargs_plugin.densify.homography import pixel_rays
from polargs_plugin.densify.ncc import numba_available
from polargs_plugin.densify.patchmatch import azimuth_cost, depth_gradient_normal, patchmatch
from polargs_plugin.optics.azimuth import aolp_from_normals, dolp_weight, zenith_from_normals
from polargs_plugin.optics.fresnel import dolp_diffuse
from test_patchmatch_scenes import make_scene


def _eroded(mask, radius):
    """(H, W) pixels of the (1, H, W) mask whose (2r+1)^2 window lies on the object and in the image."""
    padded = F.pad(mask.float()[None], (radius,) * 4)
    return (-F.max_pool2d(-padded, 2 * radius + 1, 1, 0))[0, 0] > 0.5


def _corrupt(depth, normal, seed=1):
    g = torch.Generator().manual_seed(seed)
    h, w = depth.shape[-2:]
    smooth = F.interpolate(torch.randn(1, 1, 4, 4, generator=g), size=(h, w), mode="bilinear")[0]
    d = depth * (1 + 0.05 * smooth + 0.01 * torch.randn(depth.shape, generator=g))
    n = F.normalize(normal + 0.3 * torch.randn(normal.shape, generator=g), dim=0)
    return d, torch.where(n[2:] > 0, -n, n)


def _run(views, renders, d0, n0, **kwargs):
    src = torch.stack([r[0] for r in renders[1:]])
    return patchmatch(renders[0][0], views[0].K, views[0].world_to_camera, src,
                      torch.stack([v.K for v in views[1:]]), torch.stack([v.world_to_camera for v in views[1:]]),
                      d0, n0, mask=renders[0][3], **kwargs)


def _errors(res, depth, normal, sel):
    rel = ((res.depth - depth).abs() / depth.clamp_min(1e-6))[0][sel]
    ang = torch.rad2deg(torch.arccos((res.normal * normal).sum(0).clamp(-1, 1)))[sel]
    return rel, ang


@pytest.mark.parametrize(
    "kind, scene_kwargs, min_depth_frac, min_normal_frac",
    [
        ("plane", dict(), 0.97, 0.9),
        ("sphere", dict(distance=3.5, focal_ratio=1.6, texture_scale=0.7), 0.9, 0.8),
    ],
)
def test_recovers_depth_within_1pct_and_normals_within_5deg(kind, scene_kwargs, min_depth_frac, min_normal_frac):
    views, renders = make_scene(kind, size=64, **scene_kwargs)
    _, depth, normal, mask = renders[0]
    d0, n0 = _corrupt(depth, normal)
    # evaluated where the 11x11 window lies on the object and in the image
    sel = _eroded(mask, 5)
    rel0, ang0 = _errors(type("R", (), {"depth": d0, "normal": n0}), depth, normal, sel)
    assert (rel0 < 0.01).float().mean() < 0.3 and (ang0 < 5).float().mean() < 0.1
    res = _run(views, renders, d0, n0, config=PatchMatchConfig(iterations=6))
    rel, ang = _errors(res, depth, normal, sel)
    assert (rel < 0.01).float().mean() >= min_depth_frac
    assert (ang < 5).float().mean() >= min_normal_frac
    assert res.evaluations > 0
    assert torch.isfinite(res.cost[mask]).all()
    assert (res.depth[~mask] == 0).all()


def test_aolp_term_lowers_normal_error_on_a_textureless_sphere():
    views, renders = make_scene("sphere", size=48, textured=False, distance=3.5, focal_ratio=1.6)
    _, depth, normal, mask = renders[0]
    aolp = aolp_from_normals(normal)
    dolp = dolp_diffuse(zenith_from_normals(normal))
    g = torch.Generator().manual_seed(1)
    d0 = depth * (1 + 0.01 * torch.randn(depth.shape, generator=g))
    n0 = F.normalize(normal + 0.5 * torch.randn(normal.shape, generator=g), dim=0)
    n0 = torch.where(n0[2:] > 0, -n0, n0)
    sel = _eroded(mask, 2)
    errors = {}
    for lam in (0.0, 0.02):
        res = _run(views, renders, d0, n0, aolp=aolp, dolp=dolp,
                   config=PatchMatchConfig(iterations=2, lambda_aolp=lam))
        errors[lam] = _errors(res, depth, normal, sel)[1].mean().item()
    assert errors[0.02] < 0.85 * errors[0.0]


def test_azimuth_cost_is_pi_half_periodic_and_grows_with_the_difference():
    phi = torch.full((1, 1, 1), 0.4)
    dolp = torch.full((1, 1, 1), 0.3)
    tau = 0.1
    omega = dolp_weight(dolp)[0, 0, 0]
    deltas = torch.tensor([0.0, 0.1, 0.3, 0.5, math.pi / 2, math.pi, 3 * math.pi / 2])
    alpha = phi.flatten() + deltas  # orthographic normals with these azimuths, zenith 40 deg
    th = math.radians(40)
    normals = torch.stack([math.sin(th) * torch.cos(alpha), -math.sin(th) * torch.sin(alpha),
                           torch.full_like(alpha, -math.cos(th))], -1).reshape(-1, 3, 1, 1)
    cost = azimuth_cost(normals, phi, dolp, tau=tau, sigma=0.5)[:, 0, 0]
    expected = omega * torch.exp(torch.tensor([0.0, 0.01, 0.09, 0.25, 0, 0, 0]) / tau)
    assert torch.allclose(cost, expected, rtol=1e-4)


def test_depth_gradient_normal_of_a_tilted_plane():
    views, renders = make_scene("plane", size=24, num_sources=1)
    _, depth, normal, mask = renders[0]
    rays = pixel_rays(views[0].K, 24, 24).float()
    n_dg, ok = depth_gradient_normal(depth[0], rays, mask[0])
    assert ok[1:-1, 1:-1].all() and not ok[0].any()
    assert torch.allclose(n_dg[:, ok], normal[:, ok], atol=1e-3)


def test_holes_are_filled_by_propagation():
    views, renders = make_scene("plane", size=48)
    _, depth, normal, mask = renders[0]
    d0 = depth.clone()
    d0[:, 18:30, 18:30] = 0.0  # a hole in the rendered depth
    res = _run(views, renders, d0, normal, config=PatchMatchConfig(iterations=4))
    rel = ((res.depth - depth).abs() / depth)[0, 18:30, 18:30]
    assert (rel < 0.01).float().mean() > 0.9


def test_rejects_missing_sources_and_empty_depth():
    views, renders = make_scene("plane", size=16, num_sources=1)
    img, depth, normal, _ = renders[0]
    K, w2c = views[0].K, views[0].world_to_camera
    with pytest.raises(ValueError, match="source"):
        patchmatch(img, K, w2c, img[None][:0], K[None][:0], w2c[None][:0], depth, normal)
    with pytest.raises(ValueError, match="depth"):
        patchmatch(img, K, w2c, img[None], K[None], w2c[None], torch.zeros_like(depth), normal)


@pytest.mark.skipif(not numba_available(), reason="numba missing")
def test_numba_search_matches_the_torch_reference():
    """Same random draws, same hypotheses: the fused numba search reproduces the torch reference."""
    views, renders = make_scene("sphere", size=40, distance=3.5, focal_ratio=1.6, texture_scale=0.7)
    _, depth, normal, mask = renders[0]
    d0, n0 = _corrupt(depth, normal)
    d0[:, 12:16, 12:16] = 0.0  # a hole: random initial depths
    polar = dict(aolp=aolp_from_normals(normal), dolp=dolp_diffuse(zenith_from_normals(normal)))
    rays = pixel_rays(views[0].K, 40, 40).float()
    sel = _eroded(mask, 5)
    for model, iterations in (("perspective", 0), ("orthographic", 2)):
        ref, fast = (_run(views, renders, d0, n0, **polar, config=PatchMatchConfig(
            iterations=iterations, ncc_backend=backend, azimuth_model=model)) for backend in ("torch", "numba"))
        # the azimuth of a normal along the viewing ray is undefined: both answers are arbitrary there
        defined = torch.linalg.cross(rays, ref.normal, dim=0).norm(dim=0) > 1e-3 * rays.norm(dim=0)
        close = (ref.cost - fast.cost).abs()[0][mask[0] & defined] < 1e-4
        if iterations == 0:  # one scoring of identical hypotheses: the minimum agrees everywhere
            assert close.all()
            assert ref.evaluations == fast.evaluations > 0
        else:  # near-ties may pick different planes, which then propagate a little differently
            assert close.float().mean() > 0.98
        rel_ref, ang_ref = _errors(ref, depth, normal, sel)
        rel_fast, ang_fast = _errors(fast, depth, normal, sel)
        assert abs((rel_ref < 0.01).float().mean() - (rel_fast < 0.01).float().mean()) < 0.03
        assert abs((ang_ref < 5).float().mean() - (ang_fast < 5).float().mean()) < 0.03


def test_grey_sources_give_the_colour_sources_result():
    """PatchMatch reads the sources' mean over the channels: passing that grey gives the same planes
    bit for bit (the densifier hands over grey sources, a fourth of the colour images' memory)."""
    views, renders = make_scene("sphere", size=32, distance=3.5, focal_ratio=1.6, texture_scale=0.7)
    _, depth, normal, mask = renders[0]
    d0, n0 = _corrupt(depth, normal)
    colour = [(r[0].expand(3, -1, -1) * torch.tensor([0.9, 1.0, 1.1])[:, None, None],) + tuple(r[1:]) for r in renders]
    grey = [(c[0].mean(-3, keepdim=True),) + tuple(c[1:]) for c in colour]
    config = PatchMatchConfig(iterations=1)
    from_colour, from_grey = (_run(views, r, d0, n0, config=config) for r in (colour, grey))
    assert from_colour.depth.count_nonzero() > 0
    for name in ("depth", "normal", "cost", "photometric_cost"):
        assert torch.equal(getattr(from_colour, name), getattr(from_grey, name)), name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu_torch_backend():
    views, renders = make_scene("plane", size=32)
    _, depth, normal, _ = renders[0]
    d0, n0 = _corrupt(depth, normal)
    cfg = PatchMatchConfig(iterations=1, ncc_backend="torch")
    cpu = _run(views, renders, d0, n0, config=cfg)
    dev = [tuple(t.cuda() for t in r) for r in renders]
    gpu = _run([v.to("cuda") for v in views], dev, d0.cuda(), n0.cuda(), config=cfg)
    sel = _eroded(renders[0][3], 5)
    rel_cpu, _ = _errors(cpu, depth, normal, sel)
    rel_gpu, _ = _errors(type("R", (), {"depth": gpu.depth.cpu(), "normal": gpu.normal.cpu()}), depth, normal, sel)
    # different random streams: compare accuracy, not bits
    assert abs((rel_cpu < 0.01).float().mean() - (rel_gpu < 0.01).float().mean()) < 0.1
