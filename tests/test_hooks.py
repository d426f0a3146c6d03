"""PolarHooks end to end on a tiny hand-built scene with a fake render (no trainer, no densify)."""

import dataclasses
import re
import sys
import types

import pytest
import torch

from polargs_plugin.config import PolarConfig
from polargs_plugin.hooks import PolarHooks, maps_cache_key
from polargs_plugin.losses import photometric_loss, reflective_loss
from polargs_plugin.types import GaussianState, RenderOut, View

H, W = 16, 20


def _view(name="v0", seed=0):
    """Diffuse colour field, a polarized white highlight (specular) and a clipped patch (overexposed)."""
    gen = torch.Generator().manual_seed(seed)
    colour = torch.tensor([0.55, 0.35, 0.2])[:, None, None] * (0.8 + 0.2 * torch.rand(1, H, W, generator=gen))
    s0 = 2 * colour
    s1 = torch.zeros(3, H, W)
    s2 = 0.02 * colour
    s0[:, 3:6, 4:8] += 0.4  # bright (peak about 0.73), DoLP about 0.38, no angle image clipped
    s1[:, 3:6, 4:8] += 0.4
    s0[:, 10:12, 12:15] = 2.0
    s2[:, 10:12, 12:15] = 0.0
    K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    return View(name=name, K=K, world_to_camera=torch.eye(4, dtype=torch.float64), stokes=torch.stack([s0, s1, s2]))


def _config(**loss_kwargs):
    cfg = PolarConfig.synthetic()
    cfg.densify.enabled = False
    for key, value in loss_kwargs.items():
        setattr(cfg.losses, key, value)
    return cfg


def _render(seed=1):
    gen = torch.Generator().manual_seed(seed)
    color = torch.rand(3, H, W, generator=gen).requires_grad_()
    depth = (2.0 + 0.1 * torch.rand(1, H, W, generator=gen)).requires_grad_()
    normal = torch.randn(3, H, W, generator=gen).requires_grad_()
    alpha = torch.rand(1, H, W, generator=gen)
    return RenderOut(color=color, depth=depth, normal=normal, alpha=alpha)


def _gaussians():
    scales = (torch.rand(7, 3) * 0.1 + 0.01).requires_grad_()
    return GaussianState(means=torch.zeros(7, 3), quats=torch.tensor([[1.0, 0, 0, 0]] * 7), scales=scales,
                         opacities=torch.full((7,), 0.5))


def test_end_to_end_finite_loss_and_gradients():
    view = _view()
    hooks = PolarHooks(_config())
    (maps,) = hooks.preprocess([view])
    assert maps.specular_mask[0, 3:6, 4:8].all() and maps.overexposed_mask[0, 10:12, 12:15].all()
    render, gaussians = _render(), _gaussians()
    extra, logs = hooks.loss(10_000, view, render, gaussians)
    assert set(logs) == {"l_s", "l_o", "l_plain_reflective", "l_dn", "l_scale"}
    assert all(value.ndim == 0 and not value.requires_grad for value in logs.values())  # cheap logs
    extra.backward()
    assert torch.isfinite(extra)
    for tensor in (render.color, render.depth, render.normal, gaussians.scales):
        assert tensor.grad is not None and torch.isfinite(tensor.grad).all()


def test_pc_replaces_plain_colour_loss_on_reflective_pixels():
    view = _view()
    cfg = _config(use_depth_normal=False, use_scale=False, lambda_ref=0.7)
    hooks = PolarHooks(cfg)
    (maps,) = hooks.preprocess([view])
    render = _render()
    extra, _ = hooks.loss(1, view, render, _gaussians())
    trainer = photometric_loss(render.color, view.image)  # the trainer's own colour loss
    over = maps.overexposed_mask & maps.extras["i_chro_valid"]
    reflective = maps.specular_mask | over
    l_s, l_o = reflective_loss(render.color, view.image, maps.specular_mask, maps.i_diff, over, maps.i_chro)
    expected = photometric_loss(render.color, view.image, ~reflective) + 0.7 * (l_s + l_o)
    assert torch.allclose(trainer + extra, expected, atol=1e-6)

    # Without SSIM the per-pixel gradient is analytic: sign(C - target) / (3 H W), target swapped
    # to I_diff (weighted by lambda_ref) on specular pixels and left alone elsewhere.
    cfg.losses.ssim_weight = 0.0
    render = _render()
    extra, _ = hooks.loss(1, view, render, _gaussians())
    (photometric_loss(render.color, view.image, ssim_weight=0.0) + extra).backward()
    grad = render.color.grad * (3 * H * W)
    spec = maps.specular_mask.expand(3, H, W)
    plain = ~reflective.expand(3, H, W)
    assert torch.allclose(grad[spec], 0.7 * torch.sign(render.color - maps.i_diff).detach()[spec], atol=1e-5)
    assert torch.allclose(grad[plain], torch.sign(render.color - view.image).detach()[plain], atol=1e-5)


def test_ablation_switches_and_schedule():
    view = _view()
    cfg = _config()
    cfg.correction.enabled = False
    hooks = PolarHooks(cfg)
    (maps,) = hooks.preprocess([view])
    assert maps.specular_mask is None
    _, logs = hooks.loss(1, view, _render(), _gaussians())
    assert set(logs) == {"l_scale"}  # no PC; L_dn waits for its iteration; no PatchMatch normal
    _, logs = hooks.loss(cfg.losses.depth_normal_from_iter, view, _render(), _gaussians())
    assert "l_dn" in logs
    cfg.losses.use_scale = False
    cfg.losses.use_depth_normal = False
    extra, logs = hooks.loss(10_000, view, _render(), _gaussians())
    assert logs == {} and float(extra) == 0
    assert hooks.densify(1000, view, lambda v: _render(), _gaussians()) is None
    assert hooks.normal_target(view.name) is None
    with pytest.raises(KeyError, match="preprocess"):
        PolarHooks(_config()).loss(1, view, _render(), _gaussians())


@pytest.mark.parametrize("iteration", [0, -3, 1.0, True])
def test_loss_and_densify_refuse_iterations_that_are_not_1_based_integers(iteration):
    """Iterations count from 1 (the first optimisation step); a 0-based or fractional count is a
    trainer-side mistake that would shift every schedule by one, so it is refused in one line."""
    view = _view()
    hooks = PolarHooks(_config())
    hooks.preprocess([view])
    for call, where in ((lambda: hooks.loss(iteration, view, _render(), _gaussians()), "hooks.loss"),
                        (lambda: hooks.densify(iteration, view, lambda v: _render(), _gaussians()), "hooks.densify")):
        with pytest.raises(ValueError) as err:
            call()
        assert str(err.value) == f"{where}: iteration must be an integer >= 1 (iterations are 1-based), got {iteration!r}"
    hooks.loss(1, view, _render(), _gaussians())  # the first iteration is fine
    assert hooks.densify(1, view, lambda v: _render(), _gaussians()) is None  # Dense off in _config


def test_depth_normal_term_takes_the_plane_depth_when_the_render_has_one():
    """L_dn on a fronto-parallel plane with normals facing the camera is 0 with ``depth``; a render
    that also carries a tilted ``plane_depth`` gets L_dn of that plane (1 - cos(tilt)), its
    gradient goes to ``plane_depth`` and none to ``depth``; a mis-shaped one is named."""
    import math

    view = _view()
    hooks = PolarHooks(_config(use_ref=False, use_scale=False))
    hooks.preprocess([view])
    iteration = hooks.config.losses.depth_normal_from_iter
    K = view.K
    flat = torch.full((1, H, W), 2.0, requires_grad=True)
    facing = torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1).expand(3, H, W).clone()
    alpha = torch.ones(1, H, W)
    _, logs = hooks.loss(iteration, view, RenderOut(color=torch.rand(3, H, W), depth=flat, normal=facing, alpha=alpha),
                         _gaussians())
    assert float(logs["l_dn"]) == pytest.approx(0.0, abs=1e-7)
    # The plane z = 2 + tan(tilt) * x_cam: along the ray (rx, ry, 1), z = 2 / (1 - tan(tilt) rx).
    tilt = 0.25
    rx = ((torch.arange(W) + 0.5 - K[0, 2]) / K[0, 0]).float().view(1, 1, W).expand(1, H, W)
    tilted = (2.0 / (1.0 - math.tan(tilt) * rx)).requires_grad_()
    render = RenderOut(color=torch.rand(3, H, W), depth=flat, normal=facing, alpha=alpha, plane_depth=tilted)
    extra, logs = hooks.loss(iteration, view, render, _gaussians())
    assert float(logs["l_dn"]) == pytest.approx(1.0 - math.cos(tilt), rel=1e-4)
    extra.backward()
    assert tilted.grad is not None and tilted.grad.abs().sum() > 0 and flat.grad is None
    render.plane_depth = torch.ones(1, H + 1, W)
    with pytest.raises(ValueError, match="render.plane_depth"):
        hooks.loss(iteration, view, render, _gaussians())


def test_cache_keyed_by_content(tmp_path, monkeypatch):
    cfg = _config()
    cfg.cache_dir = str(tmp_path)
    view = _view()
    (first,) = PolarHooks(cfg).preprocess([view])
    files = sorted(tmp_path.glob("*.pt"))
    assert len(files) == 1 and maps_cache_key(view, cfg)[:24] in files[0].name

    import polargs_plugin.hooks as hooks_module

    def fail(*args, **kwargs):
        raise AssertionError("recomputed despite a cache hit")

    monkeypatch.setattr(hooks_module, "compute_polar_maps", fail)
    (cached,) = PolarHooks(cfg).preprocess([view])
    assert torch.equal(cached.i_chro, first.i_chro) and torch.equal(cached.specular_mask, first.specular_mask)
    assert torch.equal(cached.extras["i_chro_valid"], first.extras["i_chro_valid"])
    monkeypatch.undo()

    changed = _view(seed=5)
    assert maps_cache_key(changed, cfg) != maps_cache_key(view, cfg)
    cfg2 = _config()
    cfg2.cache_dir = str(tmp_path)
    cfg2.correction.mahalanobis_threshold = 0.5
    assert maps_cache_key(view, cfg2) != maps_cache_key(view, cfg)
    PolarHooks(cfg).preprocess([changed])
    assert len(list(tmp_path.glob("*.pt"))) == 2
    # A corrupt entry is recomputed and replaced, not trusted.
    files[0].write_bytes(b"garbage")
    (again,) = PolarHooks(cfg).preprocess([view])
    assert torch.equal(again.i_chro, first.i_chro)
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


class _FakeDensifier:
    def __init__(self, config, views, maps):
        self.maps = maps
        self.calls = 0
        self.normals = {}

    def __call__(self, iteration, view, render_fn, gaussians, render=None):
        self.calls += 1
        assert not torch.is_grad_enabled()
        normal = torch.zeros(3, H, W)
        normal[2] = -1
        self.normals[view.name] = (normal, torch.ones(1, H, W, dtype=torch.bool))
        return None

    def normal_target(self, view_name):
        return self.normals.get(view_name)

    def state_dict(self):
        return {"calls": self.calls}

    def load_state_dict(self, state):
        self.calls = state["calls"]


def test_densify_delegation_normal_loss_and_state(monkeypatch):
    fake = types.ModuleType("polargs_plugin.densify.densifier")
    fake.PolarDensifier = _FakeDensifier
    monkeypatch.setitem(sys.modules, "polargs_plugin.densify.densifier", fake)
    cfg = _config(use_ref=False, use_depth_normal=False, use_scale=False)
    cfg.densify.enabled = True
    view = _view()
    hooks = PolarHooks(cfg)
    hooks.preprocess([view])
    _, logs = hooks.loss(1, view, _render(), _gaussians())
    assert "l_n" not in logs  # no PatchMatch normal yet
    hooks.densify(1000, view, lambda v: _render(), _gaussians())
    render = _render()
    extra, logs = hooks.loss(1001, view, render, _gaussians())
    # L_n = mean |N/|N| - (0, 0, -1)|_1 (all pixels valid here), weighted by alpha_normal.
    unit = render.normal / render.normal.norm(dim=0, keepdim=True)
    expected = (unit - torch.tensor([0.0, 0, -1])[:, None, None]).abs().sum(0).mean().detach()
    assert abs(logs["l_n"] - float(expected)) < 1e-5
    assert torch.allclose(extra, cfg.losses.alpha_normal * expected, atol=1e-6)
    # The targets are refreshed only inside the Dense window: L_n covers every target pixel until
    # normal_until_after_dense iterations after it, then only the pixels whose rendered normal
    # lies within normal_hold_deg of the target (None: L_n stops there).
    tilt = torch.full((H, W), 4.0)  # degrees from the target (0, 0, -1)
    tilt[:, W // 2 :] = 25.0
    tilt_rad = torch.deg2rad(tilt)
    normal = 0.7 * torch.stack([torch.sin(tilt_rad), torch.zeros(H, W), -torch.cos(tilt_rad)])
    tilted = dataclasses.replace(render, normal=normal.requires_grad_())
    per_pixel = (normal / 0.7 - torch.tensor([0.0, 0, -1])[:, None, None]).abs().sum(0)
    last = cfg.densify.end_iter + cfg.losses.normal_until_after_dense
    assert cfg.losses.normal_hold_deg == 10.0
    fresh = hooks.loss(last, view, tilted, _gaussians())[1]["l_n"]
    assert abs(fresh - float(per_pixel.mean())) < 1e-5
    held = hooks.loss(last + 1, view, tilted, _gaussians())[1]["l_n"]
    assert abs(held - float(per_pixel[:, : W // 2].sum() / (H * W))) < 1e-5
    cfg.losses.normal_hold_deg = None
    assert "l_n" not in hooks.loss(last + 1, view, tilted, _gaussians())[1]
    for bad in (0.0, -5.0, 200.0):
        cfg.losses.normal_hold_deg = bad
        with pytest.raises(ValueError, match=re.escape(
                f"config.losses.normal_hold_deg: must be in (0, 180] degrees or null, got {bad}")):
            PolarHooks(cfg)
    cfg.losses.normal_hold_deg = None
    cfg.losses.normal_until_after_dense = None
    assert abs(hooks.loss(last + 1, view, tilted, _gaussians())[1]["l_n"] - fresh) < 1e-6

    state = hooks.state_dict()
    assert state == {"densifier": {"calls": 1}}
    resumed = PolarHooks(cfg)
    resumed.load_state_dict(state)  # before preprocess: applied when the densifier is built
    resumed.preprocess([view])
    assert resumed.state_dict() == state


def test_densify_due_follows_the_dense_schedule(synthetic_views):
    views = synthetic_views("glossy_plane_sphere", num_views=3, width=24, height=24)
    cfg = _config()
    cfg.densify.enabled = True
    cfg.densify.start_iter, cfg.densify.end_iter, cfg.densify.interval = 10, 30, 10
    hooks = PolarHooks(cfg)
    assert not hooks.densify_due(10)  # no densifier before preprocess
    hooks.preprocess(views)
    assert [it for it in range(1, 41) if hooks.densify_due(it)] == [10, 20, 30]
    assert hooks.densify(15, views[0], lambda v: _render(), _gaussians()) is None
    cfg.densify.enabled = False
    off = PolarHooks(cfg)
    off.preprocess(views)
    assert not any(off.densify_due(it) for it in range(1, 41))


def test_consistency_filter_uses_config_and_maps(synthetic_views):
    from polargs_plugin.densify.filters import consistency_filter

    # surface masks: GT depth on the floor as well, so the filter has much to keep or drop
    views = synthetic_views("glossy_plane_sphere", num_views=3, width=24, height=24, mask="surface")
    cfg = _config()
    cfg.densify.filters.max_relative_depth = 0.005
    hooks = PolarHooks(cfg)
    maps = hooks.preprocess(views)
    depths = [view.depth_gt * (1 + 0.01 * i) for i, view in enumerate(views)]
    normals = [view.normal_gt for view in views]
    expected = consistency_filter(
        depths, normals, views, config=cfg.densify.filters,
        aolps=[m.aolp for m in maps], dolps=[m.dolp for m in maps],
    )
    assert torch.equal(hooks.consistency_filter(depths, normals, views), expected)
    default = consistency_filter(depths, normals, views)
    assert not torch.equal(default, expected)  # the config really reached the filter


def test_package_exports_polar_hooks_lazily():
    import subprocess

    import polargs_plugin

    assert "PolarHooks" in polargs_plugin.__all__ and polargs_plugin.PolarHooks is PolarHooks
    # The package import itself stays light: no numba / open3d until PolarHooks is used.
    code = "import sys, polargs_plugin; print(sorted(m for m in ('numba', 'open3d') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_polar_config_from_dict_checks_each_value_against_its_field():
    """Wrong kinds fail when the config is built, naming the setting, not later inside training."""
    data = PolarConfig.synthetic().to_dict()
    data["losses"]["alpha_normal"] = 1  # an int in a float field is a number
    data["correction"]["specular_dolp"] = [0.2, 0.9]  # JSON lists become the field's tuples
    data["densify"]["seed_max_plane_deviation"] = None
    config = PolarConfig.from_dict(data)
    assert config.losses.alpha_normal == 1.0 and isinstance(config.losses.alpha_normal, float)
    assert config.correction.specular_dolp == (0.2, 0.9) and config.densify.seed_max_plane_deviation is None
    for path, value, message in (
        ("losses.alpha_normal", "0.1", "losses.alpha_normal: expected a number, got '0.1'"),
        ("losses.alpha_normal", float("nan"), "losses.alpha_normal: expected a number"),
        ("densify.enabled", 1, "densify.enabled: expected true or false, got 1"),
        ("densify.patchmatch.propagation_distances", [1, 2.5],
         "densify.patchmatch.propagation_distances: expected a list of integers"),
    ):
        bad = PolarConfig.synthetic().to_dict()
        *sections, key = path.split(".")
        node = bad
        for section in sections:
            node = node[section]
        node[key] = value
        with pytest.raises(ValueError, match=re.escape(message)):
            PolarConfig.from_dict(bad)
    with pytest.raises(ValueError, match="^losses: expected a dict"):
        PolarConfig.synthetic().update({"losses": 0.5})
