"""Single-view polarimetric normals (optics.single_view_normals), their loss and their use by the
hooks where PatchMatch confirmed nothing.

The truth is built here without the optics module: a plane seen by a pinhole camera, its AoLP as
the image direction in which a point moving along the normal projects (the trace of the plane
of incidence on the sensor, what the perspective model describes), its zenith from the ray, its
DoLP from Fresnel's transmittances (diffuse) or reflectances (specular)."""

from __future__ import annotations

import math
import sys
import types

import pytest
import torch

from polargs_plugin.config import PolarConfig
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.losses import polar_normal_loss
from polargs_plugin.optics import aolp_from_stokes, dolp_from_stokes, single_view_normals
from polargs_plugin.types import GaussianState, RenderOut, View

N = 1.5


def _intrinsics(width, height, focal):
    return torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64)


def _unit(v):
    v = torch.as_tensor(v, dtype=torch.float64)
    return v / v.norm()


def _tilted(zenith_deg, azimuth_deg):
    """Camera-frame unit normal tilted ``zenith_deg`` from -z towards the on-screen direction
    ``azimuth_deg`` (ccw from image +x towards image up, y down)."""
    t, a = math.radians(zenith_deg), math.radians(azimuth_deg)
    return torch.tensor([math.sin(t) * math.cos(a), -math.sin(t) * math.sin(a), -math.cos(t)], dtype=torch.float64)


def _rotate(v, axis, deg):
    """Rodrigues rotation of the 3-vector ``v`` about ``axis``."""
    k = _unit(axis)
    a = math.radians(deg)
    return v * math.cos(a) + torch.linalg.cross(k, v) * math.sin(a) + k * (k @ v) * (1 - math.cos(a))


def _fresnel(cos_i):
    sin2 = 1 - cos_i**2
    cos_t = torch.sqrt(1 - sin2 / N**2)
    r_s = ((cos_i - N * cos_t) / (cos_i + N * cos_t)) ** 2
    r_p = ((N * cos_i - cos_t) / (N * cos_i + cos_t)) ** 2
    return r_s, r_p


def _rays(K, height, width):
    """(3, H, W) pinhole rays through the pixel centres (no skew)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                          torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    return torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)])


def _ray_zenith_deg(normal, K):
    """(H, W) angle between a (3, H, W) normal map and the direction towards the camera."""
    rays = _rays(K, *normal.shape[-2:])
    cos = (normal * -rays).sum(0) / (normal.norm(dim=0) * rays.norm(dim=0))
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1)))


def _plane(normal, K, height, width, kind="diffuse"):
    """Stokes (3, 1, H, W) of a plane with camera-frame unit ``normal`` through (0, 0, 3)."""
    rays = _rays(K, height, width)
    points = rays * (3 * normal[2] / (normal @ rays.reshape(3, -1))).reshape(1, height, width)
    assert (normal @ points.reshape(3, -1) < 0).all(), "the plane must face the camera"

    def pixel(p):
        return K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]

    eps = 1e-4
    (u1, v1), (u0, v0) = pixel(points + eps * normal[:, None, None]), pixel(points - eps * normal[:, None, None])
    aolp = torch.atan2(-(v1 - v0), u1 - u0)  # ccw from image +x towards image up
    cos_zenith = (normal[:, None, None] * -points / points.norm(dim=0, keepdim=True)).sum(0)
    r_s, r_p = _fresnel(cos_zenith)
    if kind == "diffuse":
        dolp = ((1 - r_p) - (1 - r_s)) / ((1 - r_p) + (1 - r_s))
    else:
        dolp, aolp = (r_s - r_p) / (r_s + r_p), aolp + math.pi / 2
    s0 = torch.ones_like(dolp)
    return torch.stack([s0, dolp * torch.cos(2 * aolp), dolp * torch.sin(2 * aolp)])[:, None]


def _angle_deg(a, b):
    """(1, H, W) angle between two (3, H, W) normal maps."""
    cos = (a * b).sum(0, keepdim=True) / (a.norm(dim=0, keepdim=True) * b.norm(dim=0, keepdim=True))
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1)))


H, W = 24, 32
K = _intrinsics(W, H, 60.0)


def _maps(stokes):
    return aolp_from_stokes(stokes), dolp_from_stokes(stokes)


def _guess(true, deg, length=0.6):
    """The true normal rotated by ``deg`` about an axis orthogonal to it, alpha-weighted, as a map."""
    axis = torch.linalg.cross(true, _unit([0.3, 1.0, 0.2]))
    return (length * _rotate(true, axis, deg))[:, None, None].expand(3, H, W)


# ------------------------------------------------------------------------------ (a) analytic
@pytest.mark.parametrize("azimuth_deg", [35.0, 200.0, 290.0])  # 200, 290: true azimuth = AoLP + pi
@pytest.mark.parametrize("perturb_deg", [20.0, 30.0])
def test_a_tilted_plane_gives_back_its_normal_from_a_perturbed_guess(azimuth_deg, perturb_deg):
    true = _tilted(67.0, azimuth_deg)  # zeniths 52-84 degrees over the image
    aolp, dolp = _maps(_plane(true, K, H, W))
    out = single_view_normals(aolp, dolp, _guess(true, perturb_deg), K, "perspective", N)
    assert out.valid.all() and not out.azimuth_only.any().item()
    assert _angle_deg(out.normal, true[:, None, None]).max() < 1e-3
    assert (out.normal.norm(dim=0) - 1).abs().max() < 1e-9
    # float32 maps, as the hooks hold them: still far below a degree
    out32 = single_view_normals(aolp.float(), dolp.float(), _guess(true, perturb_deg).float(), K, "perspective", N)
    assert _angle_deg(out32.normal.double(), true[:, None, None]).max() < 0.1


def test_the_guess_decides_the_pi_ambiguity_and_the_azimuth_model_must_match():
    true = _tilted(67.0, 200.0)
    aolp, dolp = _maps(_plane(true, K, H, W))
    # A guess on the other side of the pi ambiguity (its azimuth 180 degrees off) gets the mirror
    # normal: the AoLP cannot tell them apart, the render decides.
    mirror = _tilted(67.0, 20.0)
    flipped = single_view_normals(aolp, dolp, _guess(mirror, 10.0), K, "perspective", N).normal
    assert _angle_deg(flipped, true[:, None, None]).min() > 90
    # The orthographic model read on a pinhole camera's AoLP is off by degrees away from the centre.
    ortho = single_view_normals(aolp, dolp, _guess(true, 20.0), K, "orthographic", N).normal
    assert _angle_deg(ortho, true[:, None, None]).max() > 2


def test_orthographic_model_inverts_its_own_forward_model():
    from polargs_plugin.optics.fresnel import dolp_diffuse

    true = _tilted(70.0, 130.0)
    aolp = torch.full((1, 2, 2), math.atan2(-float(true[1]), float(true[0])) % math.pi, dtype=torch.float64)
    dolp = dolp_diffuse(torch.full((1, 2, 2), math.radians(70.0), dtype=torch.float64), N)
    out = single_view_normals(aolp, dolp, true[:, None, None].expand(3, 2, 2) * 0.5 + 0.2, None, "orthographic", N)
    assert _angle_deg(out.normal, true[:, None, None]).max() < 1e-4


def test_specular_pixels_constrain_only_the_azimuth():
    true = _tilted(55.0, 300.0)
    aolp, dolp = _maps(_plane(true, K, H, W, kind="specular"))
    guess = _guess(true, 25.0)
    for mask in (torch.ones(1, H, W, dtype=torch.bool), None):  # PC's mask, or the guess calls it specular
        out = single_view_normals(aolp, dolp, guess, K, "perspective", N, specular_mask=mask)
        assert out.valid.all() and out.azimuth_only.all()
        # the true normal lies in the measured plane of incidence; the target keeps the guess's zenith
        assert (true[:, None, None] * out.plane).sum(0).abs().max() < 1e-6
        assert (out.normal * out.plane).sum(0).abs().max() < 1e-9
        # (a guess facing away from the camera, past 90 degrees, gives a grazing target)
        assert (_ray_zenith_deg(out.normal, K) - _ray_zenith_deg(guess, K).clamp(max=90)).abs().max() < 1e-6
        assert float(polar_normal_loss(true[:, None, None].expand(3, H, W), out)) < 1e-6
        assert float(polar_normal_loss(guess, out)) > 0.05
    # Read as diffuse (the diffuse pair only competes when the guess is close to it) it would be
    # 90 degrees off: on PC's specular pixels the diffuse pair never competes.
    near_diffuse = _guess(_tilted(55.0, 30.0), 5.0)
    forced = single_view_normals(aolp, dolp, near_diffuse, K, "perspective", N,
                                 specular_mask=torch.ones(1, H, W, dtype=torch.bool))
    assert (true[:, None, None] * forced.plane).sum(0).abs().max() < 1e-6


def test_low_clipped_or_impossible_dolp_leaves_azimuth_only_or_nothing():
    true = _tilted(67.0, 35.0)
    aolp, dolp = _maps(_plane(true, K, H, W))
    dolp = dolp.clone()
    dolp[:, 0] = 0.01  # below min_dolp: no target
    dolp[:, 1] = 0.03  # zenith ill-conditioned: azimuth only
    dolp[:, 2] = 0.5  # above the diffuse maximum 0.385: no diffuse light
    over = torch.zeros(1, H, W, dtype=torch.bool)
    over[:, 3] = True
    guess = _guess(true, 20.0).clone()
    guess[:, 4] = 0  # nothing rendered
    out = single_view_normals(aolp, dolp, guess, K, "perspective", N, overexposed_mask=over)
    assert not out.valid[:, [0, 4]].any() and (out.normal[:, [0, 4]] == 0).all()
    assert out.azimuth_only[:, 1:4].all() and not out.azimuth_only[:, 5:].any() and out.valid[:, 5:].all()
    assert (true[:, None, None] * out.plane).sum(0)[1:4].abs().max() < 1e-6
    with pytest.raises(ValueError, match="aolp and dolp"):
        single_view_normals(aolp, dolp[0], guess)


# --------------------------------------------------------------------------- (b) gradients
def test_the_loss_gradient_reaches_the_rendered_normal():
    true = _tilted(67.0, 35.0)
    aolp, dolp = _maps(_plane(true, K, H, W))
    dolp[:, :, : W // 2] = 0.03  # left half azimuth only
    target = single_view_normals(aolp, dolp, _guess(true, 20.0), K, "perspective", N)
    assert target.azimuth_only[:, :, : W // 2].all() and not target.azimuth_only[:, :, W // 2:].any()
    small = type(target)(*(t[..., 10:13, 14:18] for t in target))  # a 3 x 4 patch across both kinds
    normal = (_guess(true, 20.0)[..., 10:13, 14:18] + 0.05 * torch.randn(3, 3, 4, dtype=torch.float64,
              generator=torch.Generator().manual_seed(0))).requires_grad_()
    assert torch.autograd.gradcheck(lambda n: polar_normal_loss(n, small), (normal,))
    # Descending it moves the rendered normal onto the target: onto the true normal where the
    # zenith is measured, into the measured azimuth plane where it is not.
    normal = _guess(true, 20.0).clone().requires_grad_()
    optimizer = torch.optim.Adam([normal], lr=0.01)
    for _ in range(300):
        optimizer.zero_grad()
        polar_normal_loss(normal, target).backward()
        optimizer.step()
    final = normal.detach()
    assert _angle_deg(final, true[:, None, None])[:, :, W // 2:].max() < 1.5
    off_plane = ((final / final.norm(dim=0)) * target.plane).sum(0).abs()
    assert off_plane[:, : W // 2].max() < math.sin(math.radians(1.5))
    where = torch.zeros(1, H, W, dtype=torch.bool)
    assert float(polar_normal_loss(final, target, where)) == 0


# ------------------------------------------------------------------------------- (c) hooks
HH, HW = 16, 20
HK = _intrinsics(HW, HH, 40.0)
TRUE = _tilted(60.0, 35.0)


def _hooks_view():
    stokes = _plane(TRUE, HK, HH, HW).float().expand(3, 3, HH, HW) * 0.8  # grey, s0 / 2 = 0.4
    return View(name="plane", K=HK, world_to_camera=torch.eye(4, dtype=torch.float64), stokes=stokes.contiguous())


class _HalfConfirmed:
    """A densifier whose N_opt (0, 0, -1) is valid on the left half of the view only."""

    def __init__(self, config, views, maps):
        self.normals = {}

    def __call__(self, iteration, view, render_fn, gaussians, render=None):
        normal = torch.zeros(3, HH, HW)
        normal[2] = -1
        valid = torch.zeros(1, HH, HW, dtype=torch.bool)
        valid[:, :, : HW // 2] = True
        self.normals[view.name] = (normal, valid)

    def normal_target(self, view_name):
        return self.normals.get(view_name)

    def state_dict(self):
        return {}

    def load_state_dict(self, state):
        pass


def _hooks_config(use_polar_normal, dense=True):
    cfg = PolarConfig.synthetic()  # perspective azimuth model
    cfg.losses.use_ref = cfg.losses.use_depth_normal = cfg.losses.use_scale = False
    cfg.losses.use_polar_normal = use_polar_normal
    cfg.densify.enabled = dense
    return cfg


def _hooks_render():
    normal = (0.8 * _rotate(TRUE, [0.0, 1.0, 0.3], 20.0)).float()[:, None, None].expand(3, HH, HW).contiguous()
    alpha = torch.ones(1, HH, HW)
    alpha[:, :, -2:] = 0.2  # below densify.alpha_threshold: no render to guide or to correct
    return RenderOut(color=torch.rand(3, HH, HW), depth=torch.full((1, HH, HW), 3.0),
                     normal=normal.requires_grad_(), alpha=alpha)


def _gaussians():
    return GaussianState(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]),
                         scales=torch.full((1, 3), 0.1), opacities=torch.full((1,), 0.5))


def _step(hooks, view, iteration=1001):
    render = _hooks_render()
    extra, logs = hooks.loss(iteration, view, render, _gaussians())
    if extra.requires_grad:
        extra.backward()
    return render, logs


def test_hooks_use_the_polar_normal_only_where_n_opt_is_invalid_and_only_when_enabled(monkeypatch):
    fake = types.ModuleType("polargs_plugin.densify.densifier")
    fake.PolarDensifier = _HalfConfirmed
    monkeypatch.setitem(sys.modules, "polargs_plugin.densify.densifier", fake)
    view = _hooks_view()
    runs = {}
    for enabled in (False, True):
        hooks = PolarHooks(_hooks_config(enabled))
        (maps,) = hooks.preprocess([view])
        assert "l_pn" not in _step(hooks, view, 1)[1] and "l_n" not in _step(hooks, view, 1)[1]  # no N_opt yet
        hooks.densify(1000, view, lambda v: _hooks_render(), _gaussians())
        runs[enabled] = _step(hooks, view)
    (off, off_logs), (on, on_logs) = runs[False], runs[True]
    assert "l_pn" not in off_logs and "l_pn" in on_logs
    assert torch.equal(on_logs["l_n"], off_logs["l_n"])
    # the value: the polar loss on the unconfirmed (right-half), opaque pixels
    render = _hooks_render()
    target = single_view_normals(maps.aolp, maps.dolp, render.normal, view.K, "perspective", 1.5)
    where = torch.zeros(1, HH, HW, dtype=torch.bool)
    where[:, :, HW // 2: -2] = True
    assert target.valid[where].all()
    assert torch.allclose(on_logs["l_pn"], polar_normal_loss(render.normal, target, where).detach())
    # the gradient: unchanged on confirmed pixels and transparent ones, added on the others
    extra = on.normal.grad - off.normal.grad
    assert torch.equal(on.normal.grad[:, :, : HW // 2], off.normal.grad[:, :, : HW // 2])
    assert (extra[:, :, -2:] == 0).all() and (off.normal.grad[:, :, HW // 2:] == 0).all()
    assert (extra[:, :, HW // 2: -2].abs().sum(0) > 0).all()
    # with Dense off there is no N_opt, so neither L_n nor its single-view complement
    dense_off = PolarHooks(_hooks_config(True, dense=False))
    dense_off.preprocess([view])
    assert _step(dense_off, view)[1] == {}
