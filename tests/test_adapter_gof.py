"""The GOF adapter against a stand-in with GOF's attribute surface and conventions (9-channel
render, kernel_size on every render, 3D filter, absolute-gradient statistics, six-argument postfix)."""

from __future__ import annotations

import pytest
import torch

import polargs_plugin.service.adapters as service_adapters
from polargs_adapters.gof import GofAdapter, attach
from polargs_plugin.backends.reference.model import init_points_from_masks
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.config import LossConfig
from polargs_plugin.service.adapters import ENV_DATA
from polargs_plugin.service.data import Dataset
from polargs_plugin.types import NewGaussians
import scene_cache
from adapter_config import rough_model_config
from standins import gof

SIZE = 40
KERNEL_SIZE = 0.1
# every per-Gaussian statistic GOF's densification_postfix resets
GOF_STATISTICS = ("xyz_gradient_accum", "xyz_gradient_accum_abs", "xyz_gradient_accum_abs_max", "denom", "max_radii2D")


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("bumpy_mixed", num_views=8, width=SIZE, height=SIZE)


class RecordingRender:
    """GOF's render, remembering the keyword arguments of every call."""

    def __init__(self):
        self.calls: list[dict] = []

    def __call__(self, camera, pc, pipe, bg_color, *args, **kwargs):
        self.calls.append(dict(kwargs, positional=len(args)))
        return gof.render(camera, pc, pipe, bg_color, *args, **kwargs)


def _trainer(scene, n=400):
    points, colors = init_points_from_masks(scene.views, n, resolution=24, generator=torch.Generator().manual_seed(0))
    cameras = [gof.Camera(v) for v in scene.views]
    model = gof.make_model(points, colors)
    model.compute_3D_filter(cameras=cameras)  # as GOF's train.py before its loop
    return gof.Scene(cameras), model


def _adapter(trainer_scene, model, views, render=gof.render, **kwargs) -> GofAdapter:
    return GofAdapter(trainer_scene, model, None, render, views, config=kwargs.pop("config", rough_model_config()),
                      render_kwargs={"kernel_size": KERNEL_SIZE}, **kwargs)


def test_views_carry_the_cameras_geometry_and_the_datasets_stokes(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    for view in scene.views:
        got = adapter.views[view.name]
        torch.testing.assert_close(got.world_to_camera, view.world_to_camera, atol=1e-12, rtol=0)
        torch.testing.assert_close(got.K, view.K, atol=1e-9, rtol=0)
        assert torch.equal(got.stokes, view.stokes) and torch.equal(got.mask, view.mask)


def test_attach_reads_the_environment_and_keeps_kernel_size(scene, monkeypatch) -> None:
    trainer_scene, model = _trainer(scene)
    monkeypatch.setattr(service_adapters, "load_dataset", lambda path: Dataset(path, scene.views, "fake"))
    monkeypatch.setenv(ENV_DATA, "/somewhere/polar")
    monkeypatch.setenv("POLARGS_PRESET", "synthetic")
    polar = attach(trainer_scene, model, None, gof.render, kernel_size=KERNEL_SIZE)
    assert isinstance(polar, GofAdapter) and polar.render_kwargs == {"kernel_size": KERNEL_SIZE}
    assert polar.config.losses.use_depth_normal is False
    with pytest.raises(TypeError, match="kernel_size"):
        attach(trainer_scene, model, None, gof.render)
    monkeypatch.delenv(ENV_DATA)
    with pytest.raises(ValueError, match=ENV_DATA):
        attach(trainer_scene, model, None, gof.render, kernel_size=KERNEL_SIZE)


def _wall(view, opacity_logit=2.0):
    """Flat Gaussians on the plane camera z = 2, axes along the camera's."""
    from scipy.spatial.transform import Rotation

    w2c = view.world_to_camera.float()
    xs = torch.linspace(-0.8, 0.8, 9)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    cam_points = torch.cat([grid, torch.full((81, 1), 2.0)], dim=1)
    points = (cam_points - w2c[:3, 3]) @ w2c[:3, :3]  # camera -> world
    model = gof.make_model(points, torch.full((81, 3), 0.5))
    rotation = torch.tensor(Rotation.from_matrix(w2c[:3, :3].T.double().numpy()).as_quat()).float()
    with torch.no_grad():
        model._rotation.copy_(torch.roll(rotation, 1).expand(81, 4))  # xyzw -> wxyz
        model._scaling.copy_(torch.log(torch.tensor([0.12, 0.12, 1e-6])).expand(81, 3))
        model._opacity.fill_(opacity_logit)
    return model


def test_render_out_of_a_flat_wall_is_in_the_project_conventions(synthetic_views) -> None:
    """depth = plane z (GOF's median depth, where alpha > 0.5), normal (0, 0, -1) x alpha, alpha."""
    view = synthetic_views("bumpy_mixed", num_views=1, width=SIZE, height=SIZE)[0]
    model = _wall(view)
    camera = gof.Camera(view)
    model.compute_3D_filter(cameras=[camera])
    model.filter_3D = torch.zeros_like(model.filter_3D)  # no filter: the wall is exactly flat
    adapter = _adapter(gof.Scene([camera]), model, [view])
    pkg = gof.render(camera, model, None, torch.zeros(3), kernel_size=KERNEL_SIZE)
    out = adapter.render_out(camera, pkg)
    reference = rasterize(model.get_xyz, model.get_rotation, model.get_scaling, model.get_opacity[:, 0],
                          torch.ones(81, 3), view.K.float(), view.world_to_camera.float(), SIZE, SIZE)
    covered = reference.alpha > 0.5
    assert covered.float().mean() > 0.3
    torch.testing.assert_close(out.alpha, reference.alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.0), atol=1e-4, rtol=0)
    assert out.median_depth is out.depth
    expected = torch.tensor([0.0, 0.0, -1.0])[:, None, None] * out.alpha
    torch.testing.assert_close(out.normal, expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.color, pkg["render"][:3], atol=0, rtol=0)

    # with GOF's 3D filter (std f): a splat much thinner than f fades (the filter keeps its volume),
    # so give the wall a thickness of 2 f; the maps stay the wall's within the filtered thickness
    model.compute_3D_filter(cameras=[camera])
    f = float(model.filter_3D.max())
    assert f > 1e-3 and float(model.get_opacity_with_3D_filter.max()) < 1e-3
    with torch.no_grad():
        model._scaling[:, 2] = torch.log(torch.tensor(2 * f))
    out = adapter.render_out(camera, gof.render(camera, model, None, torch.zeros(3), kernel_size=KERNEL_SIZE))
    covered = out.alpha > 0.5
    assert covered.float().mean() > 0.3
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.0), atol=0.02, rtol=0)
    assert float(-out.normal[2][covered[0]].min()) > 0.5 and float(out.normal[:2].abs().max()) < 0.05

    with pytest.raises(ValueError, match=r"\(9, H, W\)"):
        adapter.render_out(camera, {"render": pkg["render"][:3]})


def test_native_depth_normal_is_off_by_default_and_kept_on_request(scene) -> None:
    assert set(GofAdapter.native_terms) == {"use_depth_normal"}
    assert all(hasattr(LossConfig(), switch) for switch in GofAdapter.native_terms)
    trainer_scene, model = _trainer(scene)
    camera = trainer_scene.cameras[0]
    pkg = gof.render(camera, model, None, torch.zeros(3), kernel_size=KERNEL_SIZE)

    default = _adapter(trainer_scene, model, scene.views)
    losses = default.config.losses
    assert losses.use_depth_normal is False
    assert losses.use_ref and losses.use_normal and losses.use_scale  # the other terms stay on
    default.loss(30, camera, pkg)
    assert "l_dn" not in default.logs and "l_scale" in default.logs

    kept = _adapter(trainer_scene, model, scene.views, keep_native_terms=True)
    assert kept.config.losses.use_depth_normal is True
    kept.loss(30, camera, pkg)
    assert "l_dn" in kept.logs


def test_hooks_see_the_raw_scales_and_opacities(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    state = adapter.gaussian_state()
    assert torch.equal(state.scales, model.get_scaling) and torch.equal(state.opacities, model.get_opacity[:, 0])
    assert not torch.equal(state.scales, model.get_scaling_with_3D_filter)
    cfg = rough_model_config()
    cfg.correction.enabled = False
    cfg.losses.use_normal = False
    adapter = _adapter(trainer_scene, model, scene.views, config=cfg)
    camera = trainer_scene.cameras[0]
    extra = adapter.loss(1, camera, gof.render(camera, model, None, torch.zeros(3), kernel_size=KERNEL_SIZE))
    extra.backward()  # L_scale only: on the raw log-scales
    assert set(adapter.logs) == {"l_scale"} and float(model._scaling.grad.abs().sum()) > 0


def _seeds(model, m):
    g = torch.Generator().manual_seed(1)
    means = model.get_xyz.detach()[:m] + 0.01 * torch.randn(m, 3, generator=g)
    quats = torch.nn.functional.normalize(torch.randn(m, 4, generator=g), dim=-1)
    return NewGaussians(means, quats, torch.full((m, 3), 0.02), torch.rand(m, 3, generator=g), torch.full((m,), 0.5))


def test_append_pads_every_statistic_recomputes_the_filter_and_renders(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    n, m = model.get_xyz.shape[0], 30
    for name in GOF_STATISTICS:
        setattr(model, name, torch.rand_like(getattr(model, name)) + 1)
    before = {name: getattr(model, name).clone() for name in GOF_STATISTICS}
    computed = model.filter_3D_computations
    assert adapter.append(_seeds(model, m)) == m
    for name in GOF_STATISTICS:
        value = getattr(model, name)
        assert value.shape[0] == n + m
        assert torch.equal(value[:n], before[name]) and not value[n:].any()  # padded, not wiped
    assert model.filter_3D.shape == (n + m, 1) and model.filter_3D_computations == computed + 1
    torch.testing.assert_close(torch.sigmoid(model._opacity[n:, 0]), torch.full((m,), 0.5))  # raw opacity
    out = adapter.render_view(adapter.views[trainer_scene.cameras[0].image_name])
    assert out.color.shape == (3, SIZE, SIZE)

    # without the recomputation the next render fails, as GOF's does
    model.filter_3D = model.filter_3D[:n]
    with pytest.raises(RuntimeError):
        gof.render(trainer_scene.cameras[0], model, None, torch.zeros(3), kernel_size=KERNEL_SIZE)


@pytest.mark.slow
def test_fifty_steps_lower_the_loss_and_append_with_consistent_state(scene) -> None:
    trainer_scene, model = _trainer(scene)
    render = RecordingRender()
    adapter = _adapter(trainer_scene, model, scene.views, render=render)
    cameras = trainer_scene.getTrainCameras()
    background = torch.zeros(3)
    filter_sizes = []
    original_compute = model.compute_3D_filter

    def compute_3D_filter(cameras):
        original_compute(cameras)
        filter_sizes.append((model.get_xyz.shape[0], model.filter_3D.shape[0]))

    model.compute_3D_filter = compute_3D_filter
    losses, appended, padded_checks = [], 0, 0
    for iteration in range(1, 51):  # the shape of GOF's train.py loop
        camera = cameras[(iteration * 3) % len(cameras)]
        render_pkg = render(camera, model, None, background, kernel_size=KERNEL_SIZE)
        rendering = render_pkg["render"]
        image = rendering[:3]
        loss = gof.l1_ssim_loss(image, camera.original_image) + 100 * rendering[8].mean()
        loss = loss + adapter.loss(iteration, camera, render_pkg)
        loss.backward()
        with torch.no_grad():
            visible = render_pkg["visibility_filter"]
            radii = render_pkg["radii"].float()
            model.max_radii2D[visible] = torch.maximum(model.max_radii2D[visible], radii[visible])
            model.add_densification_stats(render_pkg["viewspace_points"], visible)
            model.optimizer.step()
            model.optimizer.zero_grad(set_to_none=True)
            n_before = model.get_xyz.shape[0]
            abs_before = model.xyz_gradient_accum_abs.clone()
            added = adapter.densify(iteration, camera, render_pkg)
            if added:
                assert torch.equal(model.xyz_gradient_accum_abs[:n_before], abs_before)
                assert not model.xyz_gradient_accum_abs[n_before:].any()
                assert filter_sizes[-1] == (n_before + added, n_before + added)
                padded_checks += 1
            appended += added
        losses.append(float(loss.detach()))
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10])
    assert appended > 0 and adapter.appended == appended and padded_checks == len(filter_sizes)
    n = model.get_xyz.shape[0]
    assert n == 400 + appended
    for group in model.optimizer.param_groups:
        param = group["params"][0]
        assert param.shape[0] == n
        state = model.optimizer.state[param]
        assert state["exp_avg"].shape == param.shape and state["exp_avg_sq"].shape == param.shape
        assert int(state["step"]) == 50  # the step counter survived every append
    for name in GOF_STATISTICS:
        assert getattr(model, name).shape[0] == n
    assert model.filter_3D.shape == (n, 1)
    assert float(model.denom.sum()) > 0 and float(model.xyz_gradient_accum_abs.sum()) > 0  # kept
    assert torch.isfinite(model.get_xyz).all()
    # every render went through with GOF's kernel_size: the loop's and the adapter's Dense sources
    assert len(render.calls) > 50
    assert all(call.get("kernel_size") == KERNEL_SIZE for call in render.calls)
