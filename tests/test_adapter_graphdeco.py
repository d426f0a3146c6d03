"""The graphdeco adapter against a stand-in with graphdeco's attribute surface and conventions
(R stored transposed, FoV only, clamped renders, inverse accumulated depth, postfix append)."""

from __future__ import annotations

import pytest
import torch

from polargs_adapters.graphdeco import GraphdecoAdapter
from polargs_plugin.backends.reference.model import init_points_from_masks
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.kit import depth_from_inverse
import scene_cache
from adapter_config import rough_model_config
from standins import inria

SIZE = 40


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("bumpy_mixed", num_views=8, width=SIZE, height=SIZE)


def _trainer(scene, version=2024, n=400):
    points, colors = init_points_from_masks(scene.views, n, resolution=24, generator=torch.Generator().manual_seed(0))
    cameras = [inria.Camera(v) for v in scene.views]
    return inria.Scene(cameras), inria.make_model(points, colors, version=version)


def test_views_carry_the_cameras_geometry_and_the_datasets_stokes(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = GraphdecoAdapter(trainer_scene, model, None, inria.render, scene.views, config=rough_model_config())
    for view in scene.views:
        got = adapter.views[view.name]
        torch.testing.assert_close(got.world_to_camera, view.world_to_camera, atol=1e-12, rtol=0)
        torch.testing.assert_close(got.K, view.K, atol=1e-9, rtol=0)
        assert torch.equal(got.stokes, view.stokes) and torch.equal(got.mask, view.mask)


def test_half_resolution_trainer_gets_area_averaged_stokes(scene, synthetic_views) -> None:
    half = [v for v in synthetic_views("bumpy_mixed", num_views=8, width=SIZE // 2, height=SIZE // 2)]
    cameras = [inria.Camera(v) for v in half]
    _, model = _trainer(scene)
    adapter = GraphdecoAdapter(inria.Scene(cameras), model, None, inria.render, scene.views, config=rough_model_config())
    got = adapter.views[half[0].name]
    assert got.stokes.shape[-2:] == (SIZE // 2, SIZE // 2)
    full = scene.views[0].stokes
    torch.testing.assert_close(got.stokes[..., 3, 5], full[..., 6:8, 10:12].mean(dim=(-1, -2)))


def test_missing_polarimetric_view_names_both_sides(scene) -> None:
    trainer_scene, model = _trainer(scene)
    trainer_scene.cameras[2].image_name = "IMG_0042"
    with pytest.raises(ValueError, match=r"no view for 1 of the trainer's 8 images \(e.g. \['IMG_0042'\]\)"):
        GraphdecoAdapter(trainer_scene, model, None, inria.render, scene.views, config=rough_model_config())


def test_render_out_of_a_flat_wall_is_in_the_project_conventions(synthetic_views) -> None:
    """Flat Gaussians at camera z = 2 facing a camera: depth 2, normal (0, 0, -1) x alpha."""
    view = synthetic_views("bumpy_mixed", num_views=1, width=SIZE, height=SIZE)[0]
    w2c = view.world_to_camera.float()
    xs = torch.linspace(-0.8, 0.8, 9)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    cam_points = torch.cat([grid, torch.full((81, 1), 2.0)], dim=1)
    points = (cam_points - w2c[:3, 3]) @ w2c[:3, :3]  # camera -> world
    model = inria.make_model(points, torch.full((81, 3), 0.5))
    rotation = torch.tensor(__import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation
                            .from_matrix(w2c[:3, :3].T.double().numpy()).as_quat()).float()
    with torch.no_grad():
        model._rotation.copy_(torch.roll(rotation, 1).expand(81, 4))  # axes = camera axes
        model._scaling.copy_(torch.log(torch.tensor([0.12, 0.12, 1e-6])).expand(81, 3))
        model._opacity.fill_(2.0)
    camera = inria.Camera(view)
    adapter = GraphdecoAdapter(inria.Scene([camera]), model, None, inria.render, [view], config=rough_model_config())
    pkg = inria.render(camera, model, None, torch.zeros(3))
    out = adapter.render_out(camera, pkg)
    reference = rasterize(model.get_xyz, model.get_rotation, model.get_scaling, model.get_opacity[:, 0],
                          torch.ones(81, 3), view.K.float(), w2c, SIZE, SIZE)
    covered = reference.alpha > 0.05
    assert covered.float().mean() > 0.3
    torch.testing.assert_close(out.alpha, reference.alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.0), atol=1e-4, rtol=0)
    # the plane distance rides in the alpha-depth pass's third channel: the same plane depth
    torch.testing.assert_close(out.plane_depth[covered], torch.full_like(out.depth[covered], 2.0), atol=1e-4, rtol=0)
    torch.testing.assert_close(out.plane_depth[covered], reference.plane_depth[covered], atol=1e-4, rtol=0)
    expected = torch.tensor([0.0, 0.0, -1.0])[:, None, None] * out.alpha
    torch.testing.assert_close(out.normal, expected, atol=1e-5, rtol=0)
    # graphdeco's own inverse depth gives the same camera z (single layer)
    torch.testing.assert_close(depth_from_inverse(pkg["depth"], out.alpha)[covered], out.depth[covered], atol=1e-4, rtol=0)
    assert adapter.render_out(camera, pkg, geometry=False).normal.abs().sum() == 0


def test_extra_passes_leave_the_densification_statistics_alone(scene) -> None:
    trainer_scene, model = _trainer(scene)
    cfg = rough_model_config()
    cfg.correction.enabled = False  # only geometry terms: nothing of them may reach viewspace_points
    cfg.losses.use_scale = False
    adapter = GraphdecoAdapter(trainer_scene, model, None, inria.render, scene.views, config=cfg)
    camera = trainer_scene.cameras[0]
    pkg = inria.render(camera, model, None, torch.zeros(3))
    extra = adapter.loss(30, camera, pkg)
    assert float(extra) > 0 and "l_dn" in adapter.logs
    extra.backward()
    assert pkg["viewspace_points"].grad is None
    assert model._rotation.grad is not None and float(model._rotation.grad.abs().sum()) > 0


@pytest.mark.parametrize("version", [2024, pytest.param(2023, marks=pytest.mark.slow)])
def test_fifty_steps_lower_the_loss_and_append_with_consistent_state(scene, version) -> None:
    trainer_scene, model = _trainer(scene, version=version)
    adapter = GraphdecoAdapter(trainer_scene, model, None, inria.render, scene.views, config=rough_model_config())
    cameras = trainer_scene.getTrainCameras()
    background = torch.zeros(3)
    losses, appended = [], 0
    called = []  # hooks.densify runs only where Dense is due (no state built elsewhere)
    densify = adapter.hooks.densify
    adapter.hooks.densify = lambda it, *args, **kwargs: (called.append(it), densify(it, *args, **kwargs))[1]
    for iteration in range(1, 51):  # the shape of graphdeco's train.py loop
        camera = cameras[(iteration * 3) % len(cameras)]
        render_pkg = inria.render(camera, model, None, background)
        image = render_pkg["render"]
        loss = inria.l1_ssim_loss(image, camera.original_image)
        loss = loss + adapter.loss(iteration, camera, render_pkg)
        loss.backward()
        with torch.no_grad():
            model.add_densification_stats(render_pkg["viewspace_points"], render_pkg["visibility_filter"])
            model.optimizer.step()
            model.optimizer.zero_grad(set_to_none=True)
            appended += adapter.densify(iteration, camera, render_pkg)
        losses.append(float(loss))
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10])
    assert appended > 0 and adapter.appended == appended
    assert called and len(called) < 50 and called == [it for it in range(1, 51) if adapter.hooks.densify_due(it)]
    n = model.get_xyz.shape[0]
    assert n == 400 + appended
    for group in model.optimizer.param_groups:
        param = group["params"][0]
        assert param.shape[0] == n
        state = model.optimizer.state[param]
        assert state["exp_avg"].shape == param.shape and state["exp_avg_sq"].shape == param.shape
        assert int(state["step"]) == 50  # the step counter survived every append
    assert model.xyz_gradient_accum.shape == (n, 1) and model.denom.shape == (n, 1) and model.max_radii2D.shape == (n,)
    assert model.tmp_radii is None
    assert float(model.denom.sum()) > 0  # statistics accumulated before the appends were kept
    assert torch.isfinite(model.get_xyz).all()
