"""The 2DGS adapter against a stand-in with 2DGS's attribute surface and conventions (surfels with
two scales, world-frame rendered normals, surf_depth / rend_alpha maps, six-argument postfix)."""

from __future__ import annotations

import math

import pytest
import torch

import polargs_plugin.service.adapters as service_adapters
from polargs_adapters.twodgs import TwoDGSAdapter, attach
from polargs_plugin.backends.reference.model import init_points_from_masks
from polargs_plugin.config import LossConfig
from polargs_plugin.service.adapters import ENV_DATA
from polargs_plugin.service.data import Dataset
from polargs_plugin.types import NewGaussians
import scene_cache
from adapter_config import rough_model_config
from standins import twodgs

SIZE = 40
STATISTICS = ("xyz_gradient_accum", "denom", "max_radii2D")


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("bumpy_mixed", num_views=8, width=SIZE, height=SIZE)


def _trainer(scene, n=400):
    points, colors = init_points_from_masks(scene.views, n, resolution=24, generator=torch.Generator().manual_seed(0))
    cameras = [twodgs.Camera(v) for v in scene.views]
    return twodgs.Scene(cameras), twodgs.make_model(points, colors)


def _adapter(trainer_scene, model, views, **kwargs) -> TwoDGSAdapter:
    return TwoDGSAdapter(trainer_scene, model, None, twodgs.render, views, config=kwargs.pop("config", rough_model_config()),
                         **kwargs)


def test_attach_reads_the_environment_and_turns_the_native_terms_off(scene, monkeypatch) -> None:
    trainer_scene, model = _trainer(scene)
    monkeypatch.setattr(service_adapters, "load_dataset", lambda path: Dataset(path, scene.views, "fake"))
    monkeypatch.setenv(ENV_DATA, "/somewhere/polar")
    monkeypatch.setenv("POLARGS_PRESET", "synthetic")
    polar = attach(trainer_scene, model, None, twodgs.render)
    assert isinstance(polar, TwoDGSAdapter)
    assert polar.config.losses.use_depth_normal is False and polar.config.losses.use_scale is False
    assert polar.config.losses.use_ref and polar.config.losses.use_normal
    assert all(hasattr(LossConfig(), switch) for switch in TwoDGSAdapter.native_terms)


def _wall(view, rotation_angle: float = 0.0):
    """Surfels on the plane camera z = 2, their normal along the camera's z axis (spun about it)."""
    from scipy.spatial.transform import Rotation

    w2c = view.world_to_camera.float()
    xs = torch.linspace(-0.8, 0.8, 9)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    cam_points = torch.cat([grid, torch.full((81, 1), 2.0)], dim=1)
    points = (cam_points - w2c[:3, 3]) @ w2c[:3, :3]  # camera -> world
    model = twodgs.make_model(points, torch.full((81, 3), 0.5))
    spin = Rotation.from_euler("z", rotation_angle)
    rotation = Rotation.from_matrix(w2c[:3, :3].T.double().numpy()) * spin  # surfel axes in the world
    quat = torch.tensor(rotation.as_quat()).float()
    with torch.no_grad():
        model._rotation.copy_(torch.roll(quat, 1).expand(81, 4))  # xyzw -> wxyz
        model._scaling.copy_(torch.log(torch.tensor([0.12, 0.12])).expand(81, 2))
        model._opacity.fill_(2.0)
    return model


@pytest.mark.parametrize("spin", [0.0, 0.7])
def test_render_out_of_a_flat_wall_is_in_the_project_conventions(spin: float, synthetic_views) -> None:
    """depth = plane z, normal = (0, 0, -1) x alpha in the CAMERA frame (2DGS's is world), alpha."""
    view = synthetic_views("bumpy_mixed", num_views=1, width=SIZE, height=SIZE)[0]
    model = _wall(view, spin)
    camera = twodgs.Camera(view)
    adapter = _adapter(twodgs.Scene([camera]), model, [view])
    pkg = twodgs.render(camera, model, None, torch.zeros(3))
    w2c = view.world_to_camera.float()
    world_normal = -w2c[2, :3]  # the camera's -z axis in world coordinates
    covered = pkg["rend_alpha"] > 0.5
    assert covered.float().mean() > 0.3
    assert torch.allclose(pkg["rend_normal"][:, covered[0]], world_normal[:, None] * pkg["rend_alpha"][covered],
                          atol=1e-4)
    out = adapter.render_out(camera, pkg)
    torch.testing.assert_close(out.normal, torch.tensor([0.0, 0.0, -1.0])[:, None, None] * out.alpha,
                               atol=1e-4, rtol=0)
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.0), atol=1e-4, rtol=0)
    assert out.alpha is pkg["rend_alpha"] and out.color is pkg["render"]
    with pytest.raises(KeyError, match="rend_normal"):
        adapter.render_out(camera, {k: v for k, v in pkg.items() if k != "rend_normal"})


def test_hooks_see_surfels_with_a_zero_third_scale(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    state = adapter.gaussian_state()
    assert state.scales.shape == (model.get_xyz.shape[0], 3)
    assert torch.equal(state.scales[:, :2], model.get_scaling) and not state.scales[:, 2].any()
    camera = trainer_scene.cameras[0]
    pkg = twodgs.render(camera, model, None, torch.zeros(3))
    adapter.loss(30, camera, pkg)
    assert "l_scale" not in adapter.logs and "l_dn" not in adapter.logs
    kept = _adapter(trainer_scene, model, scene.views, keep_native_terms=True)
    kept.loss(30, camera, pkg)
    assert {"l_scale", "l_dn"} <= set(kept.logs)


def test_seeds_are_appended_as_surfels_keeping_their_normal_and_the_statistics(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    n, m = model.get_xyz.shape[0], 30
    for name in STATISTICS:
        setattr(model, name, torch.rand_like(getattr(model, name)) + 1)
    before = {name: getattr(model, name).clone() for name in STATISTICS}
    g = torch.Generator().manual_seed(1)
    quats = torch.nn.functional.normalize(torch.randn(m, 4, generator=g), dim=-1)
    scales = torch.stack([torch.full((m,), 0.03), torch.full((m,), 0.02), torch.full((m,), 0.001)], dim=-1)
    new = NewGaussians(model.get_xyz.detach()[:m] + 0.01, quats, scales, torch.rand(m, 3, generator=g),
                       torch.full((m,), 0.5))
    assert adapter.append(new) == m
    assert model._scaling.shape == (n + m, 2)
    torch.testing.assert_close(model.get_scaling[n:], scales[:, :2])
    torch.testing.assert_close(model.get_rotation[n:], quats)  # the seed's third axis: the surfel normal
    for name in STATISTICS:
        value = getattr(model, name)
        assert value.shape[0] == n + m and torch.equal(value[:n], before[name]) and not value[n:].any()
    state = model.optimizer.state.get(model._scaling)
    assert state is None or state["exp_avg"].shape == (n + m, 2)
    out = adapter.render_view(adapter.views[trainer_scene.cameras[0].image_name])
    assert out.color.shape == (3, SIZE, SIZE) and torch.isfinite(out.depth).all()


@pytest.mark.slow
def test_fifty_steps_lower_the_loss_and_append_surfels(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = _adapter(trainer_scene, model, scene.views)
    cameras = trainer_scene.getTrainCameras()
    background = torch.zeros(3)
    losses, appended = [], 0
    for iteration in range(1, 51):  # the shape of 2DGS's train.py loop
        camera = cameras[(iteration * 3) % len(cameras)]
        render_pkg = twodgs.render(camera, model, None, background)
        loss = twodgs.l1_ssim_loss(render_pkg["render"], camera.original_image)
        normal_loss = 0.05 * (1 - (render_pkg["rend_normal"] * render_pkg["surf_normal"]).sum(dim=0)).mean()
        total_loss = loss + normal_loss + render_pkg["rend_dist"].mean()
        total_loss = total_loss + adapter.loss(iteration, camera, render_pkg)
        total_loss.backward()
        with torch.no_grad():
            model.add_densification_stats(render_pkg["viewspace_points"], render_pkg["visibility_filter"])
            model.optimizer.step()
            model.optimizer.zero_grad(set_to_none=True)
            appended += adapter.densify(iteration, camera, render_pkg)
        losses.append(float(loss.detach()))
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10])
    n = model.get_xyz.shape[0]
    assert appended > 0 and n == 400 + appended and model._scaling.shape == (n, 2)
    for group in model.optimizer.param_groups:
        param = group["params"][0]
        assert param.shape[0] == n
        state = model.optimizer.state[param]
        assert state["exp_avg"].shape == param.shape and int(state["step"]) == 50
    assert all(math.isfinite(v) for v in losses)
