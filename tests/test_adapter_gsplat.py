"""gsplat adapter (polargs_adapters.gsplat) with the real gsplat package.

gsplat's ``rasterization()`` needs CUDA, so the tests render through :func:`rasterization`
below: a CPU stand-in with gsplat's signature and outputs (channel-last colours [1, H, W, D],
alphas [1, H, W, 1], a ``meta`` dict with ``means2d`` [1, N, 2], ``radii`` [1, N, 2], ``width``,
``height``, ``n_cameras``, ``gaussian_ids``) built from the bundled reference rasterizer's
pieces. Like gsplat it projects once and composites every channel from that one projection
(groups of 3 channels), so ``meta["means2d"].grad`` gathers the gradient of all channels, which
is what gsplat's strategies read. Strategies, ops and the SH / projection reference code are
gsplat's own.
"""

from __future__ import annotations

import math

import pytest
import torch

gsplat = pytest.importorskip("gsplat")

from gsplat.strategy import DefaultStrategy, MCMCStrategy  # noqa: E402

from polargs_adapters.gsplat import (  # noqa: E402
    NOT_PER_GAUSSIAN,
    PolarDefaultStrategy,
    PolarMCMCStrategy,
    PolarStrategy,
    nearest_rows,
    polar_strategy,
    gaussian_state,
    gsplat_cameras,
    make_render_fn,
    polar_backgrounds,
    polar_colors,
    polar_loss,
    render_out_from_gsplat,
    rows_from_new,
    sh_colors,
    view_from_gsplat,
)
from polargs_plugin import PolarHooks  # noqa: E402
from polargs_plugin.backends.reference.binning import bin_gaussians  # noqa: E402
from polargs_plugin.backends.reference.composite_torch import composite_torch  # noqa: E402
from polargs_plugin.backends.reference.projection import project_gaussians  # noqa: E402
from polargs_plugin.geometry import eval_sh  # noqa: E402
from polargs_plugin.backends.reference.rasterizer import rasterize, resolve_backend  # noqa: E402
from polargs_plugin.kit import logit, rgb_to_sh  # noqa: E402
from polargs_plugin.losses import photometric_loss  # noqa: E402
from polargs_plugin.io import PolarInputError  # noqa: E402
from polargs_plugin.types import NewGaussians, View  # noqa: E402
from adapter_config import rough_model_config  # noqa: E402

SIZE = 40
SH_DEGREE = 1


# ----------------------------------------------------------------------------- CPU stand-in
def rasterization(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height,
    near_plane=0.01, far_plane=1e10, eps2d=0.3, sh_degree=None, packed=False, tile_size=16,
    backgrounds=None, render_mode="RGB", absgrad=False, rasterize_mode="classic", **unused,
):
    """gsplat.rasterization's contract for one camera, unpacked, on CPU (reference rasterizer)."""
    assert not packed and not absgrad and not unused, "the stand-in renders unpacked, without absgrad"
    assert rasterize_mode == "classic", "the stand-in has no antialiased mode"
    assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
    K, w2c = Ks[0], viewmats[0]
    if sh_degree is not None:
        campos = torch.inverse(w2c)[:3, 3]
        colors = eval_sh(colors[:, : (sh_degree + 1) ** 2], means - campos)
    proj = project_gaussians(means, quats, scales, opacities, K, w2c, width, height, near_plane, min(far_plane, 1e6), eps2d)
    means2d = proj.means2d[None]  # info["means2d"]: every channel's gradient goes through it
    proj = proj._replace(means2d=means2d[0])
    bins = bin_gaussians(means2d[0].detach(), proj.extents, proj.depths.detach(), width, height, tile_size)
    if render_mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat([colors, proj.depths[:, None]], dim=-1)
    d = colors.shape[-1]
    padded = torch.cat([colors, colors.new_zeros(colors.shape[0], (-d) % 3)], dim=-1)
    if resolve_backend("auto", means.device) == "numba":
        from polargs_plugin.backends.reference.composite_numba import composite_numba as composite
    else:
        composite = composite_torch
    images, alpha = [], None
    for start in range(0, padded.shape[-1], 3):
        comp = composite(proj, opacities, padded[:, start : start + 3].contiguous(), bins, width, height)
        images.append(comp.color)
        alpha = comp.alpha
    image = torch.cat(images, dim=0)[:d].permute(1, 2, 0)[None]  # [1, H, W, D]
    alphas = alpha.permute(1, 2, 0)[None]  # [1, H, W, 1]
    if render_mode == "RGB+ED":
        image = torch.cat([image[..., :-1], image[..., -1:] / alphas.clamp_min(1e-10)], dim=-1)
    if backgrounds is not None:
        image = image + (1 - alphas) * backgrounds[:, None, None, :]
    radius = torch.ceil(proj.extents).to(torch.int32)
    radii = torch.where(bins.visible[:, None], radius, torch.zeros_like(radius))[None]
    meta = {
        "means2d": means2d, "radii": radii, "depths": proj.depths[None], "gaussian_ids": None,
        "camera_ids": None, "width": width, "height": height, "n_cameras": 1, "tile_size": tile_size,
    }
    return image, alphas, meta


# ---------------------------------------------------------------------------------- set-up
@pytest.fixture
def mcmc_on_cpu(monkeypatch):
    """MCMCStrategy's ops call two CUDA kernels: swap in torch versions (the covariance is
    gsplat's own ``_torch_impl``; the relocation formula is the one of its RelocationCUDA.cu)."""
    import gsplat.strategy.ops as ops
    from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

    def compute_relocation(opacities, scales, ratios, binoms):
        n_max = binoms.shape[0]
        n = ratios.clamp(1, n_max).int()
        new_opacities = 1.0 - torch.pow(1.0 - opacities, 1.0 / n)
        denom = torch.zeros_like(opacities)
        for i in range(1, n_max + 1):
            for k in range(i):
                term = binoms[i - 1, k] * (-1.0) ** k / math.sqrt(k + 1) * new_opacities ** (k + 1)
                denom = denom + torch.where(i <= n, term, torch.zeros_like(term))
        return new_opacities, (opacities / denom)[:, None] * scales

    monkeypatch.setattr(ops, "quat_scale_to_covar_preci", _quat_scale_to_covar_preci)
    monkeypatch.setattr(ops, "compute_relocation", compute_relocation)


@pytest.fixture(scope="module")
def scene():
    import scene_cache

    return scene_cache.scene("glossy_plane_sphere", num_views=5, width=SIZE, height=SIZE)


def _splats(views: list[View], n: int = 300, seed: int = 0):
    """simple_trainer-shaped parameters (on the masks' visual hull) and one Adam per name."""
    from polargs_plugin.backends.reference.model import init_points_from_masks

    g = torch.Generator().manual_seed(seed)
    points, rgb = init_points_from_masks(views, n, 24, generator=g)
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(points.float()),
        "scales": torch.nn.Parameter(torch.full((n, 3), math.log(0.05))),
        "quats": torch.nn.Parameter(torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)),
        "opacities": torch.nn.Parameter(torch.full((n,), float(logit(torch.tensor(0.5))))),
        "sh0": torch.nn.Parameter(rgb_to_sh(rgb.float())[:, None, :]),
        "shN": torch.nn.Parameter(torch.zeros(n, (SH_DEGREE + 1) ** 2 - 1, 3)),
    })
    lrs = {"means": 2e-3, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 1e-2, "shN": 1e-3}
    optimizers = {
        name: torch.optim.Adam([{"params": params[name], "lr": lr, "name": name}], eps=1e-15)
        for name, lr in lrs.items()
    }
    return params, optimizers


def _hooks(views: list[View]) -> PolarHooks:
    cfg = rough_model_config()
    cfg.densify.patchmatch.iterations = 2
    hooks = PolarHooks(cfg)
    hooks.preprocess(views)
    return hooks


def _target(view: View) -> torch.Tensor:
    return (view.image.clamp(0, 1) * view.mask.float()).contiguous()  # black background


def _check_aligned(params, optimizers, state) -> int:
    """Every parameter, its Adam moments and every per-Gaussian strategy state tensor share N."""
    n = len(params["means"])
    for name, p in params.items():
        assert p.shape[0] == n, name
        opt = optimizers[name]
        assert opt.param_groups[0]["params"][0] is p, name
        for key in ("exp_avg", "exp_avg_sq"):
            if p in opt.state:
                assert opt.state[p][key].shape == p.shape, (name, key)
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and key not in NOT_PER_GAUSSIAN:
            assert value.shape[0] == n, key
    return n


def _train(views, params, optimizers, strategy, state, hooks, steps, *, lr_means=None, on_step=None):
    """A gsplat simple_trainer-shaped loop; returns the per-step colour losses."""
    render_fn = make_render_fn(params, rasterization, sh_degree=SH_DEGREE, packed=False)
    strategy.render_fn = render_fn
    losses = []
    for step in range(steps):
        view = views[step % len(views)]
        viewmats, Ks = gsplat_cameras(view)
        colors = polar_colors(sh_colors(params, viewmats, SH_DEGREE), params, viewmats)
        render_colors, render_alphas, info = rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            colors, viewmats, Ks, view.width, view.height, sh_degree=None, packed=False,
            backgrounds=polar_backgrounds(torch.zeros(1, 3)),
        )
        assert render_colors.shape == (1, SIZE, SIZE, 3 + 6) and render_alphas.shape == (1, SIZE, SIZE, 1)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = photometric_loss(render_colors[0, ..., :3].permute(2, 0, 1), _target(view))
        extra, logs = polar_loss(hooks, step, view, render_colors, render_alphas, info, params)
        (loss + extra).backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        before = {name: int(opt.state[opt.param_groups[0]["params"][0]]["step"]) for name, opt in optimizers.items()}
        kwargs = {"lr": lr_means} if lr_means is not None else {"packed": False}
        strategy.step_post_backward(params, optimizers, state, step, info, **kwargs)
        if on_step is not None:
            on_step(step, before, logs)
        losses.append(float(loss.detach()))
    return losses


class _Spy:
    """Records what ``hooks.densify`` returned (and with which iteration)."""

    def __init__(self, hooks):
        self.hooks, self.calls = hooks, []
        self._densify = hooks.densify

    def __call__(self, iteration, view, render_fn, gaussians, **kwargs):
        new = self._densify(iteration, view, render_fn, gaussians, **kwargs)
        self.calls.append((iteration, len(gaussians.means), None if new is None else
                           NewGaussians(*(t.clone() for t in (new.means, new.quats, new.scales, new.colors, new.opacities)))))
        return new


# ------------------------------------------------------------------------------ the loops
@pytest.mark.slow
def test_default_strategy_training_with_dense(scene):
    views = scene.views
    params, optimizers = _splats(views)
    hooks = _hooks(views)
    spy = _Spy(hooks)
    hooks.densify = spy
    inner = DefaultStrategy(grow_grad2d=1e-3, refine_start_iter=14, refine_every=10, refine_stop_iter=45,
                            reset_every=10_000, refine_scale2d_stop_iter=1000, verbose=False)
    strategy = PolarStrategy(hooks=hooks, inner=inner)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    assert {"grad2d", "count", "radii", "scene_scale", "polar"} <= set(state)
    appends = []
    logged = set()

    def on_step(step, steps_before, logs):
        logged.update(logs)
        n = _check_aligned(params, optimizers, state)
        if spy.calls and spy.calls[-1][0] == step + 1 and spy.calls[-1][2] is not None:
            _, n_before, new = spy.calls[-1]
            m = len(new)
            assert n == n_before + m
            appends.append(m)
            # the appended rows decode to the NewGaussians values
            tail = {name: p[-m:].detach() for name, p in params.items()}
            torch.testing.assert_close(tail["means"], new.means.float())
            torch.testing.assert_close(torch.exp(tail["scales"]), new.scales.float(), rtol=1e-5, atol=1e-7)
            torch.testing.assert_close(torch.sigmoid(tail["opacities"]), new.opacities.float(), rtol=1e-5, atol=1e-6)
            q = torch.nn.functional.normalize(new.quats.float(), dim=-1)
            torch.testing.assert_close(tail["quats"], q, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(tail["sh0"][:, 0] * 0.28209479177387814 + 0.5, new.colors.float().clamp(0, 1),
                                       rtol=1e-5, atol=1e-6)
            assert (tail["shN"] == 0).all()
            # zero moments for the new rows, the old rows' moments and step counters kept
            for name, opt in optimizers.items():
                st = opt.state[params[name]]
                assert int(st["step"]) == steps_before[name]
                assert (st["exp_avg"][-m:] == 0).all() and (st["exp_avg_sq"][-m:] == 0).all()
                assert st["exp_avg_sq"][:-m].abs().sum() > 0
            assert (state["grad2d"][-m:] == 0).all() and (state["count"][-m:] == 0).all()
            assert state["polar"]["last_step"] == step

    losses = _train(views, params, optimizers, strategy, state, hooks, 50, on_step=on_step)

    # Dense was asked at hook iterations 10, 20, 30, 40 (gsplat steps 9, 19, 29, 39) and appended
    assert [it for it, _, _ in spy.calls if it % 10 == 0 and 10 <= it <= 40] == [10, 20, 30, 40]
    assert appends and sum(appends) == state["polar"]["appended"] > 0
    # the next Adam steps ran on the grown parameters: 50 steps, appends did not reset counters
    for name, opt in optimizers.items():
        st = opt.state[params[name]]
        assert int(st["step"]) == 50 and st["exp_avg"].shape == params[name].shape
        assert torch.isfinite(params[name]).all()
    _check_aligned(params, optimizers, state)
    assert {"l_scale", "l_n", "l_dn"} <= logged  # L_n after the first PatchMatch, L_dn from 20
    # the colour loss goes down (same views: first and last cycle)
    first, last = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert last < 0.8 * first, (first, last)


@pytest.mark.slow
def test_mcmc_composition_pads_nothing_and_respects_cap(scene, mcmc_on_cpu):
    views = scene.views
    params, optimizers = _splats(views, n=120, seed=1)
    hooks = _hooks(views)
    spy = _Spy(hooks)
    hooks.densify = spy
    cap = 120 + 8
    inner = MCMCStrategy(cap_max=cap, refine_start_iter=4, refine_every=10, refine_stop_iter=100, noise_lr=5e3)
    strategy = PolarStrategy(hooks=hooks, inner=inner)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)  # MCMC's takes no scene_scale: dropped
    assert set(state) == {"binoms", "polar"}
    counts = []

    def on_step(step, steps_before, logs):
        counts.append(_check_aligned(params, optimizers, state))
        assert state["binoms"].shape == (51, 51)

    with pytest.raises(ValueError, match="needs lr"):
        strategy.step_post_backward(params, optimizers, state, 0, {})
    _train(views, params, optimizers, strategy, state, hooks, 22, lr_means=2e-3, on_step=on_step)
    assert max(counts) <= cap
    offered = sum(len(new) for _, _, new in spy.calls if new is not None)
    assert offered > 0
    assert state["polar"]["appended"] + state["polar"]["dropped_cap"] == offered
    # Dense's Gaussians partly fitted under cap_max (MCMC grew to 126 at step 10): the rest dropped
    assert state["polar"]["appended"] > 0 and state["polar"]["dropped_cap"] > 0 and counts[-1] == cap


# --------------------------------------------------------------------- unit-level pieces
class _StubHooks:
    """Duck-typed hooks: densify returns a fixed NewGaussians at one iteration."""

    def __init__(self, new: NewGaussians, at: int, not_due: tuple[int, ...] = ()):
        self.new, self.at, self.seen, self.not_due = new, at, [], not_due

    def densify_due(self, iteration):
        return iteration not in self.not_due

    def densify(self, iteration, view, render_fn, gaussians, render=None):
        self.seen.append((iteration, gaussians.num, render))
        return self.new if iteration == self.at else None


def _new(m: int, seed: int = 0) -> NewGaussians:
    g = torch.Generator().manual_seed(seed)
    return NewGaussians(
        means=torch.randn(m, 3, generator=g), quats=torch.randn(m, 4, generator=g),
        scales=0.01 + torch.rand(m, 3, generator=g) * 0.1, colors=torch.rand(m, 3, generator=g),
        opacities=0.05 + 0.9 * torch.rand(m, generator=g),
    )


def _tiny_params(n: int):
    g = torch.Generator().manual_seed(3)
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        "scales": torch.nn.Parameter(torch.randn(n, 3, generator=g) - 3),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
        "opacities": torch.nn.Parameter(torch.randn(n, generator=g)),
        "sh0": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g)),
        "shN": torch.nn.Parameter(torch.randn(n, 3, 3, generator=g)),
    })
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": 1e-3, "name": k}]) for k in params}
    # one real Adam step so that the moments exist
    sum((p ** 2).sum() for p in params.values()).backward()
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    return params, optimizers


def test_mcmc_binoms_not_padded_when_n_is_51_and_cap_subsamples_evenly(mcmc_on_cpu):
    params, optimizers = _tiny_params(51)  # N == binoms.shape[0]
    new = _new(20)
    inner = MCMCStrategy(cap_max=51 + 8, refine_start_iter=10_000)
    strategy = PolarStrategy(hooks=_StubHooks(new, at=7), inner=inner, render_fn=lambda v: None)
    state = strategy.initialize_state()
    binoms = state["binoms"].clone()
    view = object()
    strategy.step_post_backward(params, optimizers, state, 5, {"polar_view": view}, lr=1e-3)
    assert len(params["means"]) == 51
    appended = strategy.step_post_backward(params, optimizers, state, 6, {"polar_view": view}, lr=1e-3)
    assert len(params["means"]) == 59 and len(appended) == 8
    torch.testing.assert_close(state["binoms"], binoms)  # untouched
    assert state["polar"] == {"calls": 1, "appended": 8, "dropped_cap": 12, "last_step": 6}
    # evenly spread subset (first and last kept), not a prefix
    torch.testing.assert_close(params["means"][-8:].detach(), new.means[torch.linspace(0, 19, 8).round().long()])
    assert strategy.hooks.seen[0][0] == 6 and strategy.hooks.seen[1][0] == 7  # step + 1
    # full: nothing more is appended
    strategy.hooks.at = 9
    assert strategy.step_post_backward(params, optimizers, state, 8, {"polar_view": view}, lr=1e-3) is None
    assert len(params["means"]) == 59 and state["polar"]["dropped_cap"] == 32


def test_append_keeps_frozen_params_and_extra_rows_and_passes_render():
    params, optimizers = _tiny_params(10)
    params["frozen"] = torch.nn.Parameter(torch.ones(10, 2), requires_grad=False)
    params["features"] = torch.nn.Parameter(torch.ones(10, 4))
    optimizers["features"] = torch.optim.Adam([params["features"]])
    new = _new(3)
    hooks = _StubHooks(new, at=1)
    strategy = PolarStrategy(hooks=hooks, inner=DefaultStrategy(), render_fn=lambda v: None,
                             extra_rows={"features": lambda new, p: torch.full((len(new), 4), 7.0)})
    state = {"grad2d": torch.ones(10), "count": torch.ones(10), "scene_scale": 1.0, "polar": {"calls": 0, "appended": 0, "dropped_cap": 0, "last_step": -1}}
    marker = object()
    strategy._append(params, optimizers, state, 0, new)
    assert params["frozen"].shape == (13, 2) and not params["frozen"].requires_grad
    assert (params["frozen"][-3:] == 0).all()
    assert (params["features"][-3:] == 7).all() and params["features"].shape == (13, 4)
    assert state["grad2d"].shape == (13,) and (state["grad2d"][-3:] == 0).all()
    # render and view come from info (as polar_loss leaves them); the inner step is a no-op here
    strategy.inner.refine_stop_iter = 0
    strategy.step_post_backward(params, optimizers, state, 0, {"polar_view": marker, "polar_render": "R"})
    assert hooks.seen[-1][2] == "R"
    strategy.step_post_backward(params, optimizers, state, 1, {}, view=marker, render="S")
    assert hooks.seen[-1][0] == 2 and hooks.seen[-1][2] == "S"
    hooks.not_due, hooks.at, count = (3,), 3, len(params["means"])  # 3 would append, but is not due
    assert strategy.step_post_backward(params, optimizers, state, 2, {}, view=marker, render="S") is None
    assert hooks.seen[-1][0] == 2 and len(params["means"]) == count


def test_rows_from_new_simple_trainer_appearance_colors():
    params = {"means": torch.zeros(2, 3), "scales": torch.zeros(2, 3), "quats": torch.zeros(2, 4),
              "opacities": torch.zeros(2), "colors": torch.zeros(2, 3), "features": torch.zeros(2, 5)}
    new = _new(4)
    rows = rows_from_new(new, params)
    torch.testing.assert_close(torch.sigmoid(rows["colors"]), new.colors, rtol=1e-5, atol=1e-6)
    assert rows["features"].shape == (4, 5) and (rows["features"] == 0).all()
    assert rows["opacities"].shape == (4,)


# ----------------------------------------------------------------------- render / cameras
def test_render_out_from_gsplat_splits_the_aux_channels(scene):
    view = scene.views[0]
    params, _ = _splats(scene.views, n=200)
    viewmats, Ks = gsplat_cameras(view)
    rgb = sh_colors(params, viewmats, SH_DEGREE)
    render_colors, render_alphas, info = rasterization(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
        polar_colors(rgb, params, viewmats), viewmats, Ks, SIZE, SIZE, packed=False, render_mode="RGB+ED",
    )
    assert render_colors.shape[-1] == 3 + 6 + 1
    out = render_out_from_gsplat(render_colors, render_alphas, K=view.K)
    ref = rasterize(params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
                    rgb, view.K.float(), view.world_to_camera.float(), SIZE, SIZE)
    torch.testing.assert_close(out.color, ref.color, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(out.alpha, ref.alpha, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(out.alpha, render_alphas[0].permute(2, 0, 1), atol=1e-5, rtol=1e-4)
    # normals: the contract's camera-frame shortest axes, composited like the reference's
    torch.testing.assert_close(out.normal, ref.normal, atol=1e-4, rtol=1e-3)
    # depth = sum w z / alpha with z the mean's camera z: gsplat's own "ED" (last channel)
    covered = out.alpha[0] > 1e-3
    torch.testing.assert_close(out.depth[0][covered], render_colors[0, ..., -1][covered], atol=1e-4, rtol=1e-4)
    # the plane depth of the blended plane distance and normal: the reference's own
    torch.testing.assert_close(out.plane_depth[0][covered], ref.plane_depth[0][covered], atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="aux"):
        render_out_from_gsplat(render_colors[..., :3], render_alphas)


def test_sh_colors_match_gsplat_reference_sh():
    from gsplat.cuda._torch_impl import _spherical_harmonics

    g = torch.Generator().manual_seed(0)
    n = 50
    params = {"means": torch.randn(n, 3, generator=g), "sh0": torch.randn(n, 1, 3, generator=g),
              "shN": torch.randn(n, 15, 3, generator=g)}
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 4.0])
    campos = torch.inverse(viewmat)[:3, 3]
    coeffs = torch.cat([params["sh0"], params["shN"]], 1)
    for degree in range(4):
        expected = torch.clamp_min(_spherical_harmonics(degree, params["means"] - campos, coeffs) + 0.5, 0.0)
        torch.testing.assert_close(sh_colors(params, viewmat[None], degree), expected, atol=1e-5, rtol=1e-5)


def test_view_from_gsplat_projects_like_gsplat():
    """Sign / pixel-centre test: the View built from gsplat's viewmat and K projects a 3D point
    to the pixel gsplat's convention gives, analytically and through gsplat's own projection."""
    from gsplat.cuda._torch_impl import _fully_fused_projection

    # camera at (1, 2, -3) looking along +z of a rotated frame; K with an off-centre principal point
    angle = 0.3
    R = torch.tensor([[math.cos(angle), 0.0, -math.sin(angle)], [0.0, 1.0, 0.0], [math.sin(angle), 0.0, math.cos(angle)]])
    c2w = torch.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = torch.tensor([1.0, 2.0, -3.0])
    viewmats = torch.linalg.inv(c2w)[None]  # simple_trainer: viewmats = inv(camtoworlds)
    W, H = 64, 48
    Ks = torch.tensor([[[50.0, 0.0, 30.25], [0.0, 55.0, 25.5], [0.0, 0.0, 1.0]]])
    view = view_from_gsplat(viewmats, Ks, torch.zeros(3, 3, H, W), name="cam")
    assert view.K.dtype == torch.float64 and torch.equal(view.K.float(), Ks[0])

    point = torch.tensor([1.3, 2.4, 1.0])
    x_cam = viewmats[0, :3, :3] @ point + viewmats[0, :3, 3]
    assert x_cam[2] > 0
    # gsplat: means2d = K x / z; pixel (j, i) is evaluated at (j + 0.5, i + 0.5), so the point lies in pixel floor(u)
    u = Ks[0, 0, 0] * x_cam[0] / x_cam[2] + Ks[0, 0, 2]
    v = Ks[0, 1, 1] * x_cam[1] / x_cam[2] + Ks[0, 1, 2]
    _, means2d, depths, _, _ = _fully_fused_projection(point[None], 1e-4 * torch.eye(3)[None], viewmats, Ks, W, H)
    torch.testing.assert_close(means2d[0, 0], torch.stack([u, v]))
    torch.testing.assert_close(depths[0, 0], x_cam[2])
    # the project's convention through the View (float64)
    p_cam = view.R @ point.double() + view.t
    uv = (view.K @ (p_cam / p_cam[2]))[:2]
    torch.testing.assert_close(uv.float(), torch.stack([u, v]), atol=1e-4, rtol=0)
    torch.testing.assert_close(view.camera_center.float(), c2w[:3, 3], atol=1e-5, rtol=0)
    # and a small bright Gaussian there lights exactly that pixel in the project's rasterizer
    out = rasterize(point[None], torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 1e-3), torch.tensor([0.9]),
                    torch.ones(1, 3), view.K.float(), view.world_to_camera.float(), W, H)
    row, col = divmod(int(out.alpha[0].argmax()), W)
    assert (col, row) == (int(u.floor()), int(v.floor()))
    # round trip
    vm2, K2 = gsplat_cameras(view)
    torch.testing.assert_close(vm2, viewmats)
    torch.testing.assert_close(K2, Ks)
    with pytest.raises(ValueError, match="last row"):
        bad = viewmats.clone()
        bad[0, 3, 0] = 1.0
        view_from_gsplat(bad, Ks, torch.zeros(3, 3, H, W), name="bad")


def test_gaussian_state_activates_gsplat_params():
    params, _ = _tiny_params(5)
    state = gaussian_state(params)
    torch.testing.assert_close(state.scales, torch.exp(params["scales"]))
    torch.testing.assert_close(state.opacities, torch.sigmoid(params["opacities"]))
    torch.testing.assert_close(state.quats.norm(dim=-1), torch.ones(5))
    assert state.means is params["means"]


# ------------------------------------------------- gsplat main: scene=, SH signature, subclasses
class _RecordingScene:
    """gsplat main's ``Scene`` topology hooks, recording their calls (the defaults are no-ops)."""

    def __init__(self):
        self.calls = []

    def on_duplicate(self, sel):
        self.calls.append(("on_duplicate", sel.clone()))


class _MainDefault(DefaultStrategy):
    """DefaultStrategy with gsplat main's signature: ``step_post_backward(..., packed, scene)``."""

    def step_post_backward(self, params, optimizers, state, step, info, packed=False, scene=None):
        self.seen_scene = scene
        super().step_post_backward(params, optimizers, state, step, info, packed=packed)


class _MainMCMC(MCMCStrategy):
    """MCMCStrategy with gsplat main's signature: ``step_post_backward(..., lr, scene)``."""

    def step_post_backward(self, params, optimizers, state, step, info, lr, scene=None):
        self.seen_scene = scene
        super().step_post_backward(params, optimizers, state, step, info, lr=lr)


class _PolarOnMainDefault(PolarDefaultStrategy, _MainDefault):
    """PolarDefaultStrategy as it is on gsplat main (its parent step takes scene=)."""


class _PolarOnMainMCMC(PolarMCMCStrategy, _MainMCMC):
    """PolarMCMCStrategy as it is on gsplat main."""


def _nearest_brute_force(points, queries):
    return torch.tensor([min(range(len(points)), key=lambda j: float(((points[j] - q) ** 2).sum())) for q in queries])


def test_nearest_rows_in_chunks_equals_brute_force():
    g = torch.Generator().manual_seed(5)
    points, queries = torch.randn(40, 3, generator=g), torch.randn(17, 3, generator=g)
    truth = _nearest_brute_force(points, queries)
    for max_pairs in (1, 40, 41 * 3, 1 << 24):  # one query per chunk ... all at once
        assert torch.equal(nearest_rows(points, queries, max_pairs=max_pairs), truth)


@pytest.mark.parametrize("kind", ["default", "mcmc", "composed"])
def test_scene_is_forwarded_and_told_about_appended_rows(kind, mcmc_on_cpu):
    params, optimizers = _tiny_params(12)
    old_means = params["means"].detach().clone()
    new = _new(5)
    hooks = _StubHooks(new, at=4)
    scene = _RecordingScene()
    if kind == "default":
        strategy = _PolarOnMainDefault(hooks=hooks, render_fn=lambda v: None, refine_stop_iter=0)
        state, kwargs = strategy.initialize_state(), {"packed": False}
        inner = strategy
    elif kind == "mcmc":
        strategy = _PolarOnMainMCMC(hooks=hooks, render_fn=lambda v: None, refine_start_iter=10_000)
        state, kwargs = strategy.initialize_state(), {"lr": 1e-3}
        inner = strategy
    else:
        inner = _MainDefault(refine_stop_iter=0)
        strategy = PolarStrategy(hooks=hooks, inner=inner, render_fn=lambda v: None)
        state, kwargs = strategy.initialize_state(), {"packed": False}
    if kind == "mcmc":  # MCMC's noise moves the means: the parents are the nearest after it
        strategy.step_post_backward(params, optimizers, state, 2, {}, scene=scene, **kwargs)
        old_means = params["means"].detach().clone()
    appended = strategy.step_post_backward(params, optimizers, state, 3, {"polar_view": object()}, scene=scene,
                                           **kwargs)
    assert inner.seen_scene is scene  # passed to gsplat's own step
    assert len(appended) == 5 and len(params["means"]) == 17
    assert [name for name, _ in scene.calls] == ["on_duplicate"]
    assert torch.equal(scene.calls[0][1], _nearest_brute_force(old_means, new.means))


def test_scene_with_a_gsplat_without_scenes_is_an_error():
    params, optimizers = _tiny_params(8)
    strategy = PolarDefaultStrategy(hooks=_StubHooks(_new(2), at=99), render_fn=lambda v: None, refine_stop_iter=0)
    state = strategy.initialize_state()
    with pytest.raises(TypeError, match="takes no scene="):
        strategy.step_post_backward(params, optimizers, state, 0, {}, scene=_RecordingScene())
    strategy.step_post_backward(params, optimizers, state, 0, {})  # gsplat 1.5.3's own call works
    mcmc = PolarMCMCStrategy(hooks=_StubHooks(_new(2), at=99), render_fn=lambda v: None)
    with pytest.raises(ValueError, match="needs lr"):
        mcmc.step_post_backward(params, optimizers, mcmc.initialize_state(), 0, {})


def test_polar_strategy_keeps_the_settings_and_passes_simple_trainers_dispatch():
    import pickle

    yaml = pytest.importorskip("yaml")
    default = polar_strategy(DefaultStrategy(verbose=True, refine_every=7, absgrad=True), hooks="H")
    assert isinstance(default, PolarDefaultStrategy) and isinstance(default, DefaultStrategy)
    assert (default.refine_every, default.verbose, default.absgrad, default.hooks) == (7, True, True, "H")
    mcmc = polar_strategy(MCMCStrategy(cap_max=1234))
    assert isinstance(mcmc, MCMCStrategy) and mcmc.cap_max == 1234 and mcmc._polar_cap() == 1234
    assert polar_strategy(default, render_fn="R") is default and default.render_fn == "R"
    with pytest.raises(TypeError, match="neither"):
        polar_strategy(PolarStrategy())
    # simple_trainer.py dumps its config with yaml; the run's hooks are not settings and stay out
    dumped = yaml.dump({"strategy": default})
    assert "refine_every: 7" in dumped and "hooks: null" in dumped
    assert pickle.loads(pickle.dumps(default)).hooks is None


def _sh_1_5(degrees_to_use, dirs, coeffs, masks=None):
    """gsplat 1.5's signature, computed by gsplat's own torch reference."""
    from gsplat.cuda._torch_impl import _spherical_harmonics

    return _spherical_harmonics(degrees_to_use, dirs, coeffs)


def _sh_main(degrees_to_use, means, viewmats, coeffs, masks=None, batch_ids=None, camera_ids=None,
             gaussian_ids=None, viewmats_rs=None):
    """gsplat main's signature: camera centres from the view matrices, [C, N, D] out."""
    from gsplat.cuda._torch_impl import _spherical_harmonics

    centers = torch.linalg.inv(viewmats)[:, :3, 3]
    return torch.stack([_spherical_harmonics(degrees_to_use, means - c, coeffs) for c in centers])


@pytest.mark.parametrize("sh_fn", [_sh_1_5, _sh_main], ids=["gsplat-1.5", "gsplat-main"])
def test_sh_colors_through_either_spherical_harmonics_signature(sh_fn):
    params, _ = _tiny_params(30)
    with torch.no_grad():
        params["shN"] = torch.nn.Parameter(torch.randn(30, 15, 3) * 0.3)
    g = torch.Generator().manual_seed(2)
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=g))[0]
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, torch.tensor([0.2, -0.1, 4.0])
    for degree in range(4):
        expected = sh_colors(params, w2c[None], degree)  # CPU: polargs_plugin.geometry.eval_sh
        torch.testing.assert_close(sh_colors(params, w2c[None], degree, sh_fn=sh_fn), expected, atol=1e-6, rtol=1e-5)
    with pytest.raises(TypeError, match="gsplat 1.6"):
        sh_colors(params, w2c, 1, sh_fn=lambda degree, directions, coefficients: None)


# ------------------------------------------------------------- simple_trainer.py's Runner, attached
class _Parser:
    """simple_trainer's COLMAP parser: what ``trainer_views`` reads of it."""

    def __init__(self, views):
        self.image_names = [f"{view.name}.JPG" for view in views]  # matched to the dataset by stem
        self.camera_ids = list(range(len(views)))
        self.camtoworlds = [torch.linalg.inv(view.world_to_camera).numpy() for view in views]
        self.Ks_dict = {i: view.K.numpy() for i, view in enumerate(views)}
        self.imsize_dict = {i: (view.width, view.height) for i, view in enumerate(views)}


def _runner(views, strategy):
    from types import SimpleNamespace

    params, optimizers = _splats(views)
    cfg = SimpleNamespace(strategy=strategy, batch_size=1, packed=False, near_plane=0.01, far_plane=1e10,
                          antialiased=False, patch_size=None)
    # image 1 is a test view, as simple_trainer's split leaves every test_every-th image out
    return SimpleNamespace(cfg=cfg, parser=_Parser(views), trainset=_Trainset([0, 2, 3, 4]), splats=params,
                           optimizers=optimizers, world_size=1)


class _Trainset:
    def __init__(self, indices):
        self.indices = indices

    def __len__(self):
        return len(self.indices)


def test_attach_to_simple_trainers_runner(scene):
    from polargs_adapters.gsplat import SimpleTrainerPolar

    views = scene.views
    config = _hooks(views).config
    config.correction.enabled = False  # geometry terms only: their gradient path is under test
    config.losses.use_scale = False
    inner = DefaultStrategy(refine_every=7, refine_stop_iter=0, verbose=False)
    runner = _runner(views, inner)
    polar = SimpleTrainerPolar(runner, views, config, "fake", rasterize=rasterization)

    strategy = runner.cfg.strategy
    assert isinstance(strategy, PolarDefaultStrategy) and strategy.refine_every == 7 and strategy.hooks is polar.hooks
    assert [view.name for view in polar.views] == [f"{views[i].name}.JPG" for i in (0, 2, 3, 4)]
    for view, index in zip(polar.views, (0, 2, 3, 4)):
        torch.testing.assert_close(view.world_to_camera, views[index].world_to_camera.double(), atol=1e-6, rtol=0)
        torch.testing.assert_close(view.K, views[index].K.double(), atol=0, rtol=0)
        assert torch.equal(view.stokes, views[index].stokes)

    # one simple_trainer step on training item 1 (parser image 2), past depth_normal_from_iter
    step, item = 30, 1
    params = runner.splats
    camtoworlds = torch.linalg.inv(views[2].world_to_camera.float())[None]
    Ks = views[2].K.float()[None]
    renders, alphas, info = rasterization(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
        torch.cat([params["sh0"], params["shN"]], 1), torch.linalg.inv(camtoworlds), Ks, SIZE, SIZE,
        sh_degree=SH_DEGREE,
    )
    strategy.step_pre_backward(params, runner.optimizers, strategy.initialize_state(), step, info)
    extra = polar.loss(step, torch.tensor([item]), camtoworlds, Ks, renders, alphas, info)
    assert {"l_dn"} <= set(polar.logs) and extra.requires_grad and torch.isfinite(extra)
    extra.backward()
    # the geometric terms came through the second render: the strategy's means2d saw none of it
    assert info["means2d"].grad is None or not info["means2d"].grad.any()
    assert params["means"].grad is not None and params["means"].grad.abs().sum() > 0
    assert info["polar_view"] is polar.views[item] and not info["polar_render"].normal.requires_grad

    batched = _runner(views, DefaultStrategy())
    batched.cfg.batch_size = 4
    with pytest.raises(PolarInputError, match="batch_size 1"):
        SimpleTrainerPolar(batched, views, config, rasterize=rasterization)
