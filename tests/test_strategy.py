"""DensityControl: vanilla clone / split / prune / reset on hand-made statistics."""

import math
from dataclasses import replace

import pytest
import torch

from polargs_plugin.backends.reference.model import PARAM_NAMES, GaussianModel
from polargs_plugin.backends.reference.strategy import DensityConfig, DensityControl
from polargs_plugin.types import RenderOut

EXTENT = 2.0


def _model(log_scales, logits, means=None, quats=None) -> GaussianModel:
    n = len(logits)
    params = {
        "means": torch.arange(n * 3, dtype=torch.float32).reshape(n, 3) if means is None else means,
        "sh_dc": torch.arange(n, dtype=torch.float32)[:, None, None].expand(n, 1, 3).clone(),
        "sh_rest": torch.zeros(n, 3, 3),
        "opacity_logits": torch.tensor(logits, dtype=torch.float32),
        "log_scales": torch.tensor(log_scales, dtype=torch.float32),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * n) if quats is None else quats,
    }
    return GaussianModel(params, sh_degree=1, extent=EXTENT)


def _warm_adam(model: GaussianModel) -> None:
    model.optimizer.zero_grad()
    sum((getattr(model, k) ** 2).sum() for k in PARAM_NAMES).backward()
    model.optimizer.step()


def _stats(grads, counts=None, radii=None):
    n = len(grads)
    return {
        "grad2d": torch.tensor(grads, dtype=torch.float32),
        "count": torch.ones(n) if counts is None else torch.tensor(counts, dtype=torch.float32),
        "max_radii": torch.zeros(n) if radii is None else torch.tensor(radii, dtype=torch.float32),
    }


def test_clone_split_prune_on_hand_made_stats():
    small = math.log(0.01 * EXTENT * 0.5)  # below percent_dense * extent -> clone
    large = math.log(0.01 * EXTENT * 3.0)  # above -> split
    # A: small, high grad (clone); B: large, high grad (split); C: low grad (kept); D: transparent (pruned)
    model = _model(
        log_scales=[[small] * 3, [large, large - 1, large - 2], [small] * 3, [small] * 3],
        logits=[2.0, 2.0, 2.0, -8.0],
    )
    _warm_adam(model)
    before = {k: getattr(model, k).detach().clone() for k in PARAM_NAMES}
    moments_c = model.optimizer.state[model.means]["exp_avg"][2].clone()
    ctrl = DensityControl(DensityConfig(), EXTENT)
    # averaged grads: A 3e-4 (count 2), B 4e-4, C 1e-4, D 0 -> threshold 2e-4
    ctrl.load_state_dict(_stats([6e-4, 4e-4, 1e-4, 0.0], counts=[2, 1, 1, 1]))
    out = ctrl.refine(model, prune_large=False)
    assert out == {"cloned": 1, "split": 1, "pruned": 1}
    assert model.num == 4 + 1 + 2 - 1 - 1
    means = model.means.detach()
    # A twice (original + exact clone), C once, B gone, two children of B, D gone
    assert int((means == before["means"][0]).all(1).sum()) == 2
    assert int((means == before["means"][2]).all(1).sum()) == 1
    assert not bool((means == before["means"][1]).all(1).any())
    assert not bool((means == before["means"][3]).all(1).any())
    children = (model.sh_dc.detach() == before["sh_dc"][1]).all(-1).all(-1)  # B's colour marks its children
    assert int(children.sum()) == 2
    assert torch.allclose(model.log_scales[children], (before["log_scales"][1] - math.log(1.6)).expand(2, 3))
    assert torch.allclose(model.opacity_logits[children], before["opacity_logits"][1].expand(2))
    # survivors keep their moments; new rows start from zero moments
    state = model.optimizer.state[model.means]
    c_row = int(torch.nonzero((means == before["means"][2]).all(1))[0])
    assert torch.equal(state["exp_avg"][c_row], moments_c)
    assert bool((state["exp_avg"][children] == 0).all())
    assert state["exp_avg"].shape == model.means.shape
    # statistics follow the rows and are reset to zero
    assert all(v.shape == (model.num,) and bool((v == 0).all()) for v in ctrl.state.values())


def test_split_samples_follow_the_gaussian():
    """Children of a split are drawn from N(mean, R diag(s^2) R^T)."""
    n = 4000
    s = torch.tensor([0.3, 0.1, 0.05])
    q = torch.tensor([math.cos(0.4), 0.0, 0.0, math.sin(0.4)])  # rotation of 0.8 rad about z
    model = _model(
        log_scales=torch.log(s).expand(n, 3).tolist(),
        logits=[1.0] * n,
        means=torch.tensor([1.0, -2.0, 0.5]).expand(n, 3).clone(),
        quats=q.expand(n, 4).clone(),
    )
    ctrl = DensityControl(DensityConfig(), EXTENT)
    ctrl.load_state_dict(_stats([1.0] * n))
    torch.manual_seed(1)
    ctrl.refine(model, prune_large=False)
    assert model.num == 2 * n
    d = (model.means.detach() - torch.tensor([1.0, -2.0, 0.5])).double()
    c, sn = math.cos(0.8), math.sin(0.8)
    R = torch.tensor([[c, -sn, 0], [sn, c, 0], [0, 0, 1]], dtype=torch.float64)
    truth = R @ torch.diag(s.double() ** 2) @ R.T
    assert torch.allclose(d.mean(0), torch.zeros(3, dtype=torch.float64), atol=0.01)
    assert torch.allclose(d.T @ d / d.shape[0], truth, atol=0.004)


def test_prune_large_only_after_first_reset():
    big = math.log(0.1 * EXTENT * 1.5)
    model = _model(log_scales=[[big] * 3, [-6.0] * 3, [-6.0] * 3], logits=[2.0, 2.0, 2.0])
    ctrl = DensityControl(DensityConfig(grow_grad2d=1.0), EXTENT)
    ctrl.load_state_dict(_stats([0.0, 0.0, 0.0], radii=[1, 25, 5]))
    assert ctrl.refine(model, prune_large=False)["pruned"] == 0
    ctrl.load_state_dict(_stats([0.0, 0.0, 0.0], radii=[1, 25, 5]))
    assert ctrl.refine(model, prune_large=True)["pruned"] == 2  # world-too-big and screen-too-big
    assert model.num == 1 and float(model.log_scales.detach()[0, 0]) == -6.0


@pytest.mark.parametrize(("width", "kept"), [(128, [True, False, True]), (612, [True, True, True]),
                                             (1224, [True, True, True])])
def test_screen_limit_as_a_share_of_the_image_width(width, kept):
    """prune_screen_fraction = 20 / 128: 20 px at 128 px (vanilla's limit there), 95.6 px at 612;
    radii 1, 25 and 5 px: only the 25-px splat of a 128-px image is too big."""
    model = _model(log_scales=[[-6.0] * 3] * 3, logits=[2.0, 2.0, 2.0])
    ctrl = DensityControl(DensityConfig(grow_grad2d=1.0, prune_screen_fraction=20 / 128), EXTENT, image_width=width)
    assert ctrl.screen_limit_px == pytest.approx(20 * width / 128)
    ctrl.load_state_dict(_stats([0.0, 0.0, 0.0], radii=[1, 25, 5]))
    ctrl.refine(model, prune_large=True)
    assert model.num == sum(kept)


def test_screen_fraction_needs_the_image_width():
    with pytest.raises(ValueError, match="image width"):
        DensityControl(DensityConfig(prune_screen_fraction=0.2), EXTENT)


def test_schedule_scaled_by_one_factor():
    cfg = DensityConfig().scaled(0.1)
    assert (cfg.refine_start, cfg.refine_stop, cfg.refine_every, cfg.reset_every) == (50, 1500, 10, 300)
    model = _model(log_scales=[[-6.0] * 3] * 2, logits=[2.0, 2.0])
    ctrl = DensityControl(cfg, EXTENT)
    refines, resets = [], []
    for it in range(1, 2001):
        ctrl.load_state_dict(_stats([0.0, 0.0]))
        out = ctrl.step(model, it)
        if out["refined"]:
            assert bool((ctrl.state["count"] == 0).all())  # statistics consumed
            refines.append(it)
        if out["reset"]:
            resets.append(it)
    assert refines == list(range(60, 1500, 10))  # iteration > start, every 10, before stop
    assert resets == [300, 600, 900, 1200]
    assert torch.allclose(model.opacities, torch.full((2,), 0.01), atol=1e-6)
    quiet = DensityControl(replace(cfg, opacity_reset=False), EXTENT)
    fresh = _model(log_scales=[[-6.0] * 3] * 2, logits=[2.0, 2.0])
    assert not any(quiet.step(fresh, it)["reset"] for it in range(1, 2001))
    assert torch.allclose(fresh.opacities, torch.sigmoid(torch.tensor([2.0, 2.0])))


def test_update_accumulates_ndc_gradient_norms_of_visible():
    ctrl = DensityControl(DensityConfig(), EXTENT)
    means2d = torch.zeros(3, 2, requires_grad=True)
    means2d.grad = torch.tensor([[3e-4, 4e-4], [1.0, 1.0], [0.0, 2e-4]])
    radii = torch.tensor([2, 0, 7])
    render = RenderOut(color=None, depth=None, normal=None, alpha=None, means2d=means2d, radii=radii)
    W, H = 100, 50
    ctrl.update(render, W, H, iteration=1)
    ctrl.update(render, W, H, iteration=2)
    g0 = math.hypot(3e-4 * W / 2, 4e-4 * H / 2)
    assert torch.allclose(ctrl.state["grad2d"], torch.tensor([2 * g0, 0.0, 2 * 2e-4 * H / 2]))
    assert torch.equal(ctrl.state["count"], torch.tensor([2.0, 0.0, 2.0]))
    assert torch.equal(ctrl.state["max_radii"], torch.tensor([2.0, 0.0, 7.0]))
    ctrl.pad(2)
    assert ctrl.state["count"].shape == (5,)
    ctrl.update(render, W, H, iteration=DensityConfig().refine_stop)  # past the window: ignored
    assert ctrl.state["count"].shape == (5,)


def test_state_dict_round_trip_gives_identical_refinement():
    def fresh():
        return _model(log_scales=[[-6.0] * 3, [-1.0] * 3, [-6.0] * 3], logits=[2.0, 2.0, -9.0])

    a, b = fresh(), fresh()
    ca = DensityControl(DensityConfig(), EXTENT)
    ca.load_state_dict(_stats([5e-4, 5e-4, 0.0], radii=[1, 2, 3]))
    cb = DensityControl(DensityConfig(), EXTENT)
    cb.load_state_dict(ca.state_dict())
    torch.manual_seed(3)
    ca.refine(a, prune_large=True)
    torch.manual_seed(3)
    cb.refine(b, prune_large=True)
    for k in PARAM_NAMES:
        assert torch.equal(getattr(a, k), getattr(b, k))
    with pytest.raises(KeyError):
        ca.load_state_dict({"bogus": None})


def test_max_gaussians_caps_growth_by_gradient():
    model = _model(log_scales=[[-6.0] * 3] * 4, logits=[2.0] * 4)
    ctrl = DensityControl(DensityConfig(max_gaussians=6), EXTENT)
    ctrl.load_state_dict(_stats([3e-4, 9e-4, 5e-4, 1e-3]))
    out = ctrl.refine(model, prune_large=False)
    assert out["cloned"] == 2 and model.num == 6
    dc = model.sh_dc.detach()[:, 0, 0]
    assert int((dc == 3.0).sum()) == 2 and int((dc == 1.0).sum()) == 2  # the two highest gradients


def _indexed_update(state, grad, radii, width, height):
    """DensityControl.update written with boolean indexing, the plain form to compare against."""
    visible = radii > 0
    norms = (grad[visible] * grad.new_tensor([width / 2.0, height / 2.0])).norm(dim=-1)
    state["grad2d"][visible] += norms
    state["count"][visible] += 1
    state["max_radii"][visible] = torch.maximum(state["max_radii"][visible], radii[visible].to(state["max_radii"]))


def test_update_without_indexing_equals_the_indexed_update_bit_for_bit():
    gen = torch.Generator().manual_seed(3)
    n = 500
    ctrl = DensityControl(DensityConfig(), EXTENT)
    state = {k: torch.zeros(n) for k in ("grad2d", "count", "max_radii")}
    for it, (w, h) in enumerate([(128, 128), (128, 128), (96, 64), (128, 128)], start=1):
        means2d = torch.zeros(n, 2, requires_grad=True)
        means2d.grad = torch.randn(n, 2, generator=gen) * 1e-3
        radii = torch.randint(0, 12, (n,), generator=gen) * (torch.rand(n, generator=gen) > 0.3)
        render = RenderOut(color=None, depth=None, normal=None, alpha=None, means2d=means2d, radii=radii)
        ctrl.update(render, w, h, iteration=it)
        _indexed_update(state, means2d.grad, radii, w, h)
        assert all(torch.equal(ctrl.state[k], state[k]) for k in state)
