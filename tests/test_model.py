"""GaussianModel: activations, initialisation, row edits with consistent Adam state, persistence."""

import copy
import math

import pytest
import torch

from polargs_plugin.backends.reference.model import (
    PARAM_NAMES,
    GaussianModel,
    LearningRates,
    exponential_lr,
    init_points_from_masks,
    scene_extent,
)
from polargs_plugin.geometry import SH_C0, rgb_to_sh, sh_to_rgb
from polargs_plugin.types import NewGaussians, View


def _random_model(n: int = 6, sh_degree: int = 1, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.randn(n, 3, generator=g),
        "sh_dc": torch.randn(n, 1, 3, generator=g),
        "sh_rest": torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=g),
        "opacity_logits": torch.randn(n, generator=g),
        "log_scales": torch.randn(n, 3, generator=g) - 2,
        "quats": torch.randn(n, 4, generator=g),
    }
    return GaussianModel(params, sh_degree=sh_degree, extent=2.0)


def _fake_loss(model: GaussianModel, seed: int) -> torch.Tensor:
    """A loss touching every raw parameter with fixed random weights per row."""
    g = torch.Generator().manual_seed(seed)
    total = 0.0
    for name in PARAM_NAMES:
        p = getattr(model, name)
        total = total + (p * torch.randn(p.shape, generator=g)).sum()
    return total


def _adam_steps(model: GaussianModel, seeds) -> None:
    for s in seeds:
        model.optimizer.zero_grad(set_to_none=True)
        _fake_loss(model, s).backward()
        model.optimizer.step()


def test_activations_match_definitions():
    m = _random_model()
    assert torch.allclose(m.scales, torch.exp(m.log_scales))
    assert torch.allclose(m.opacities, 1 / (1 + torch.exp(-m.opacity_logits)))
    assert torch.allclose(m.rotations.norm(dim=1), torch.ones(m.num))
    st = m.state()
    assert st.num == m.num and st.opacities.shape == (m.num,)
    st.scales.sum().backward()  # autograd-connected to the raw parameters
    assert torch.allclose(m.log_scales.grad, torch.exp(m.log_scales.detach()))
    # SH DC convention of vanilla 3DGS: RGB2SH(c) = (c - 0.5) / C0
    c = torch.rand(5, 3)
    assert torch.allclose(rgb_to_sh(c), (c - 0.5) / 0.28209479177387814)
    assert torch.allclose(sh_to_rgb(rgb_to_sh(c)), c, atol=1e-6)


def test_sh_truncated_to_active_degree():
    m = _random_model(sh_degree=2)
    assert m.sh.shape == (m.num, 1, 3)
    m.active_sh_degree = 2
    assert m.sh.shape == (m.num, 9, 3)


def test_from_points_vanilla_init():
    h = 0.25  # regular grid spacing: the 3 nearest neighbours of an interior point are at h
    axis = torch.arange(5) * h
    pts = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    cols = torch.rand(pts.shape[0], 3)
    m = GaussianModel.from_points(pts, cols, sh_degree=2, initial_opacity=0.1)
    assert torch.allclose(m.scales, torch.full_like(m.scales, h), atol=1e-5)
    assert torch.allclose(m.opacities, torch.full((m.num,), 0.1), atol=1e-6)
    assert torch.allclose(m.rotations, torch.tensor([1.0, 0, 0, 0]).expand(m.num, 4))
    assert torch.allclose(m.sh_dc[:, 0] * SH_C0 + 0.5, cols, atol=1e-6)
    assert m.sh_rest.shape == (m.num, 8, 3) and bool((m.sh_rest == 0).all())
    with pytest.raises(ValueError):
        GaussianModel.from_points(pts, cols[:-1])


def test_exponential_lr_is_log_linear():
    assert exponential_lr(0, 1e-2, 1e-4, 100) == pytest.approx(1e-2)
    assert exponential_lr(100, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    assert exponential_lr(50, 1e-2, 1e-4, 100) == pytest.approx(1e-3)  # geometric mean
    assert exponential_lr(500, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    m = _random_model()
    m.lrs = LearningRates(means_max_steps=10)
    assert m.update_learning_rate(10) == pytest.approx(2.0 * 1.6e-6)  # scaled by extent 2
    assert m.optimizer.param_groups[0]["name"] == "means"
    assert m.optimizer.param_groups[0]["lr"] == pytest.approx(3.2e-6)


def test_one_adam_group_per_parameter_with_vanilla_rates():
    m = _random_model()
    groups = {g["name"]: g for g in m.optimizer.param_groups}
    assert set(groups) == set(PARAM_NAMES)
    for name in PARAM_NAMES:
        assert groups[name]["params"] == [getattr(m, name)]
    assert groups["sh_dc"]["lr"] == pytest.approx(0.0025)
    assert groups["sh_rest"]["lr"] == pytest.approx(0.0025 / 20)
    assert groups["log_scales"]["lr"] == pytest.approx(0.005)
    assert groups["quats"]["lr"] == pytest.approx(0.001)


def test_extended_rows_do_not_change_old_rows_trajectory():
    """Zero-padded moments: after appending, the old rows evolve exactly as without the append."""
    a = _random_model()
    _adam_steps(a, [1, 2])
    b = copy.deepcopy(a)
    n = a.num
    extra = _random_model(n=3, seed=7)
    b.extend({name: getattr(extra, name).detach() for name in PARAM_NAMES})
    assert b.num == n + 3
    for name in PARAM_NAMES:
        state = b.optimizer.state[getattr(b, name)]
        assert state["exp_avg"].shape == getattr(b, name).shape
        assert bool((state["exp_avg"][n:] == 0).all()) and bool((state["exp_avg_sq"][n:] == 0).all())
        assert torch.equal(state["exp_avg"][:n], a.optimizer.state[getattr(a, name)]["exp_avg"])
    # same per-row loss weights for the first n rows in both models
    for s in (3, 4):
        for model in (a, b):
            model.optimizer.zero_grad(set_to_none=True)
            g = torch.Generator().manual_seed(s)
            loss = 0.0
            for name in PARAM_NAMES:
                p = getattr(model, name)
                w = torch.randn((n, *p.shape[1:]), generator=g)
                loss = loss + (p[:n] * w).sum() + (p[n:] ** 2).sum()
            loss.backward()
            model.optimizer.step()
    for name in PARAM_NAMES:
        assert torch.allclose(getattr(b, name)[:n], getattr(a, name), atol=1e-7, rtol=0)
        # new rows moved too: Adam steps them with their own (zero-started) moments
        assert not torch.equal(getattr(b, name)[n:], getattr(extra, name)) or getattr(b, name).numel() == 0


def test_keep_slices_parameters_and_moments():
    m = _random_model()
    _adam_steps(m, [1])
    before = {name: (getattr(m, name).detach().clone(), m.optimizer.state[getattr(m, name)]["exp_avg_sq"].clone()) for name in PARAM_NAMES}
    mask = torch.tensor([True, False, True, True, False, True])
    m.keep(mask)
    assert m.num == 4
    for name in PARAM_NAMES:
        assert torch.equal(getattr(m, name).detach(), before[name][0][mask])
        assert torch.equal(m.optimizer.state[getattr(m, name)]["exp_avg_sq"], before[name][1][mask])
    with pytest.raises(ValueError):
        m.keep(torch.ones(3, dtype=torch.bool))


def test_append_activated_gaussians():
    m = _random_model(sh_degree=1)
    _adam_steps(m, [1])
    n = m.num
    q = torch.tensor([[2.0, 0, 0, 0], [0, 0, 3.0, 0]])
    new = NewGaussians(
        means=torch.tensor([[0.1, 0.2, 0.3], [1.0, 2.0, 3.0]]),
        quats=q,
        scales=torch.tensor([[0.01, 0.02, 0.001], [0.5, 0.5, 0.5]]),
        colors=torch.tensor([[0.2, 0.4, 0.9], [1.0, 0.0, 0.5]]),
        opacities=torch.tensor([0.5, 0.9]),
    )
    m.append(new)
    assert m.num == n + 2
    assert torch.allclose(m.means[n:], new.means)
    assert torch.allclose(m.scales[n:], new.scales, rtol=1e-6)
    assert torch.allclose(m.opacities[n:], new.opacities, atol=1e-6)
    assert torch.allclose(m.rotations[n:], q / q.norm(dim=1, keepdim=True))
    assert torch.allclose(sh_to_rgb(m.sh_dc[n:, 0]), new.colors, atol=1e-6)
    assert bool((m.sh_rest[n:] == 0).all())
    for name in PARAM_NAMES:
        st = m.optimizer.state[getattr(m, name)]
        assert st["exp_avg_sq"].shape == getattr(m, name).shape
    _adam_steps(m, [2])  # the next step runs on the grown tensors
    assert torch.isfinite(m.means).all()


def test_reset_opacity_caps_and_zeroes_moments():
    m = _random_model(n=4)
    with torch.no_grad():
        m.opacity_logits.copy_(torch.tensor([-6.0, -4.0, 0.0, 3.0]))
    _adam_steps(m, [1])
    low = m.opacities[:1].detach().clone()
    m.reset_opacity(0.01)
    assert torch.allclose(m.opacities[1:], torch.full((3,), 0.01), atol=1e-6)
    assert torch.allclose(m.opacities[:1], low)  # already below the cap (the step moved it a little)
    assert bool((m.optimizer.state[m.opacity_logits]["exp_avg"] == 0).all())


def test_checkpoint_round_trip_continues_identically():
    a = _random_model()
    _adam_steps(a, [1, 2])
    a.active_sh_degree = 1
    b = GaussianModel.from_checkpoint(copy.deepcopy(a.checkpoint()))
    assert b.active_sh_degree == 1
    _adam_steps(a, [3])
    _adam_steps(b, [3])
    for name in PARAM_NAMES:
        assert torch.equal(getattr(a, name), getattr(b, name))


def test_the_model_renders_and_saves_its_own_dilation():
    """eps2d belongs to the model: every render uses it (the footprint's variance grows by it,
    so a Gaussian's 1/e^0.5 radius in pixels is sqrt(s'^2 + eps2d)), a checkpoint keeps it, and a
    checkpoint without it (older ones) was trained at vanilla's 0.3."""
    from polargs_plugin.backends.reference.trainer import CPU_EPS2D, TrainConfig

    view = _look_at_view([0.0, 0.0, 4.0], size=32, f=40.0, radius=0.5)
    params = {
        "means": torch.zeros(1, 3), "sh_dc": torch.full((1, 1, 3), 2.0), "sh_rest": torch.zeros(1, 0, 3),
        "opacity_logits": torch.full((1,), 3.0), "log_scales": torch.full((1, 3), math.log(0.02)),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
    }
    spreads = {}
    for eps2d in (0.3, 2.0):
        model = GaussianModel(params, sh_degree=0, eps2d=eps2d)
        alpha = model.render(view).alpha[0].double()
        u = torch.arange(32, dtype=torch.float64) + 0.5
        row = alpha[16]  # the row through the mean at (16, 16): variance from the second moment
        spreads[eps2d] = float((row * (u - 16) ** 2).sum() / row.sum())
        restored = GaussianModel.from_checkpoint(copy.deepcopy(model.checkpoint()))
        assert restored.eps2d == eps2d and torch.equal(restored.render(view).alpha, model.render(view).alpha)
    screen_variance = (0.02 * 40.0 / 4.0) ** 2  # s f / z, pixels
    for eps2d, spread in spreads.items():
        # exact up to the pixel sampling and the alpha >= 1/255 cut-off of the tails
        assert spread == pytest.approx(screen_variance + eps2d, rel=0.05)
    old = GaussianModel(params, sh_degree=0).checkpoint()
    del old["eps2d"]
    assert GaussianModel.from_checkpoint(old).eps2d == 0.3
    assert TrainConfig.cpu().eps2d == CPU_EPS2D and TrainConfig().eps2d == 0.3
    with pytest.raises(ValueError, match="eps2d"):
        GaussianModel(params, sh_degree=0, eps2d=-1.0)


def _rasterized(model: GaussianModel, view: View, **kwargs):
    """``rasterize`` called directly on the model's Gaussians at its dilation (``kwargs``: the rest)."""
    from polargs_plugin.backends.reference.rasterizer import rasterize

    state = model.state()
    return rasterize(state.means, state.quats, state.scales, state.opacities, model.sh, view.K, view.world_to_camera,
                     view.width, view.height, eps2d=model.eps2d, **kwargs)


def _overlapping_splats(n: int = 40, seed: int = 3) -> dict:
    """Parameters of ``n`` opaque, randomly turned and sized Gaussians around the origin, many
    overlapping, so that the compositing orders differ."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=gen) * 0.3, "sh_dc": torch.rand(n, 1, 3, generator=gen),
        "sh_rest": torch.zeros(n, 0, 3), "opacity_logits": torch.full((n,), 2.0),
        "log_scales": torch.log(torch.rand(n, 3, generator=gen) * 0.2 + 0.01), "quats": torch.randn(n, 4, generator=gen),
    }


def test_the_model_renders_and_saves_its_own_compositing_order():
    """order and tile_size belong to the model as eps2d does: every render uses them (a render
    with them passed explicitly is the same), a checkpoint keeps them, and an older checkpoint
    without them renders as vanilla did ("center", 16-px tiles)."""
    view = _look_at_view([0.0, 0.0, 4.0], size=24, f=30.0, radius=0.5)
    params = _overlapping_splats()
    model = GaussianModel(params, sh_degree=0, order="ray", tile_size=2)
    explicit = _rasterized(model, view, order="ray", tile_size=2)
    assert torch.equal(model.render(view).color, explicit.color)
    assert not torch.equal(GaussianModel(params, sh_degree=0).render(view).color, explicit.color)  # the order shows
    restored = GaussianModel.from_checkpoint(copy.deepcopy(model.checkpoint()))
    assert (restored.order, restored.tile_size) == ("ray", 2) and torch.equal(restored.render(view).color, explicit.color)
    old = GaussianModel(params, sh_degree=0).checkpoint()
    del old["order"], old["tile_size"]
    assert (GaussianModel.from_checkpoint(old).order, GaussianModel.from_checkpoint(old).tile_size) == ("center", 16)
    with pytest.raises(ValueError, match="order"):
        GaussianModel(params, sh_degree=0, order="nearest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tile_size"):
        GaussianModel(params, sh_degree=0, tile_size=0)


def test_outputs_of_a_ray_ordered_model_are_rendered_exactly_per_pixel():
    """render_output (meshes, evaluation, pictures) composites a ray-ordered model with one-pixel
    tiles, whatever tiles it trained with, and a centre-ordered one as render does."""
    view = _look_at_view([0.0, 0.0, 4.0], size=24, f=30.0, radius=0.5)
    params = _overlapping_splats()
    model = GaussianModel(params, sh_degree=0, order="ray", tile_size=8)
    exact = _rasterized(model, view, order="ray", tile_size=1)
    assert torch.equal(model.render_output(view).color, exact.color)
    assert not torch.equal(model.render(view).color, exact.color)  # the 8-px tiles' order differs somewhere
    assert model.tile_size == 8  # training's tiles are left as they are
    centre = GaussianModel(params, sh_degree=0, tile_size=8)
    assert torch.equal(centre.render_output(view).color, centre.render(view).color)


def _look_at_view(eye, size=48, f=60.0, name="v", radius=None) -> View:
    eye = torch.tensor(eye, dtype=torch.float64)
    z = -eye / eye.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    if abs(float(z @ up)) > 0.99:
        up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    # analytic mask of a sphere of ``radius`` at the origin: the pixel-centre ray hits it
    v, u = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    rays = torch.stack([(u - size / 2) / f, (v - size / 2) / f, torch.ones_like(u)], -1).double()
    rays = rays @ R  # camera -> world directions (R^T d, written row-wise)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    b = (rays @ eye)
    disc = b**2 - (eye @ eye - radius**2)
    mask = (disc > 0)[None]
    stokes = torch.zeros(3, 3, size, size)
    stokes[0] = 2 * 0.6 * mask.float()
    return View(name=name, K=K, world_to_camera=w2c, stokes=stokes, mask=mask)


@pytest.mark.slow
def test_visual_hull_points_lie_near_the_sphere():
    r = 0.5
    views = []
    for i in range(12):
        for elev in (-0.5, 0.4):
            a = 2 * math.pi * i / 12
            views.append(_look_at_view([3 * math.cos(a) * math.cos(elev), 3 * math.sin(a) * math.cos(elev), 3 * math.sin(elev)], radius=r, name=f"v{i}{elev}"))
    pts, cols = init_points_from_masks(views, 2000, resolution=48, generator=torch.Generator().manual_seed(0))
    assert pts.shape == (2000, 3) and cols.shape == (2000, 3)
    dist = pts.double().norm(dim=1)
    # on the hull's boundary, not inside its boundary voxels (voxel = 2 * 3 * (48 / 60) / 2 / 48
    # = 0.05, which put the samples 0.025 inside on average): the hull of the pixel-centre masks
    # of a sphere is the sphere to within about half a pixel's footprint (3 / 60 / 2 = 0.025),
    # and the samples are unbiased to a fifth of that
    half_pixel = 3 / 60 / 2
    assert float(dist.min()) > r - half_pixel and float(dist.max()) < r + 1.2 * half_pixel
    assert abs(float((dist - r).median())) < 0.2 * half_pixel
    # mean image colour at the projections: every sample projects inside every mask (0.6)
    assert float(cols.min()) == pytest.approx(0.6, abs=1e-6) and float(cols.max()) <= 0.6 + 1e-6
    extent = scene_extent(views)
    assert extent == pytest.approx(3.0 * 1.1, rel=0.1)  # cameras on a sphere of radius 3 around their centroid
