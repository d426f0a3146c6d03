"""The PGSR adapter against a stand-in with PGSR's attribute surface and conventions (Inria camera
plus Fx/Fy/Cx/Cy, plane outputs with integer-pixel rays, no alpha, app_image, ``_knn_f`` and the
seven-argument postfix in PGSR's order, ``max_all_points``, abs-gradient statistics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from polargs_adapters.pgsr import PgsrAdapter, attach
from polargs_plugin import PolarConfig
from polargs_plugin.backends.reference.model import init_points_from_masks
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.ssim import ssim_map
import scene_cache
from adapter_config import rough_model_config
from standins import pgsr

SIZE = 40


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("bumpy_mixed", num_views=8, width=SIZE, height=SIZE)


def _trainer(scene, n=400, max_all_points=6_000_000):
    points, colors = init_points_from_masks(scene.views, n, resolution=24, generator=torch.Generator().manual_seed(0))
    cameras = [pgsr.Camera(v, uid=i) for i, v in enumerate(scene.views)]
    return pgsr.Scene(cameras), pgsr.make_model(points, colors, max_all_points=max_all_points)


def _config() -> PolarConfig:
    cfg = rough_model_config()
    cfg.densify.seed_behind_surface = True  # wherever the render disagrees with PatchMatch
    return cfg


# -------------------------------------------------------------------------------- cameras
def test_views_carry_the_cameras_geometry_and_the_datasets_stokes(scene) -> None:
    trainer_scene, model = _trainer(scene)
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config())
    for camera, view in zip(trainer_scene.cameras, scene.views):
        got = adapter.views[view.name]
        torch.testing.assert_close(got.world_to_camera, view.world_to_camera, atol=1e-12, rtol=0)
        torch.testing.assert_close(got.K, view.K, atol=1e-9, rtol=0)
        assert torch.equal(got.stokes, view.stokes) and torch.equal(got.mask, view.mask)
        # PGSR's own K is the View's: same focal lengths, principal point W/2, H/2 (+0.5 centres)
        torch.testing.assert_close(camera.get_k().double(), got.K, atol=1e-4, rtol=0)


def test_missing_polarimetric_view_names_both_sides(scene) -> None:
    trainer_scene, model = _trainer(scene)
    trainer_scene.cameras[2].image_name = "IMG_0042"
    with pytest.raises(ValueError, match=r"no view for 1 of the trainer's 8 images \(e.g. \['IMG_0042'\]\)"):
        PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config())


def test_attach_needs_the_data_folder(scene, monkeypatch) -> None:
    trainer_scene, model = _trainer(scene)
    monkeypatch.delenv("POLARGS_DATA", raising=False)
    with pytest.raises(ValueError, match="POLARGS_DATA"):
        attach(trainer_scene, model, None, pgsr.render, app_model=pgsr.AppModel())


# ------------------------------------------------------------------------------ render out
WALL_NORMAL = torch.tensor([0.45, 0.3, -1.0])  # camera frame, facing the camera, strongly tilted
WALL_POINT = torch.tensor([0.0, 0.0, 2.0])


def _tilted_wall():
    """Flat Gaussians tiling the plane n . x = n . p0 (camera frame) in front of one camera."""
    view = scene_cache.views("bumpy_mixed", num_views=1, width=SIZE, height=SIZE)[0]
    w2c = view.world_to_camera.float()
    n = torch.nn.functional.normalize(WALL_NORMAL, dim=0)
    u = torch.nn.functional.normalize(torch.linalg.cross(n, torch.tensor([0.0, 1.0, 0.0])), dim=0)
    v = torch.linalg.cross(n, u)
    axes_cam = torch.stack([u, v, n], dim=1)  # columns: in-plane u, v, then the normal (shortest)
    xs = torch.linspace(-1.3, 1.3, 14)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    cam_points = WALL_POINT + grid[:, :1] * u + grid[:, 1:] * v
    points = (cam_points - w2c[:3, 3]) @ w2c[:3, :3]  # camera -> world
    count = points.shape[0]
    model = pgsr.make_model(points, torch.full((count, 3), 0.5))
    axes_world = w2c[:3, :3].T @ axes_cam
    quat = torch.tensor(np.roll(Rotation.from_matrix(axes_world.double().numpy()).as_quat(), 1)).float()
    with torch.no_grad():
        model._rotation.copy_(quat.expand(count, 4))
        model._scaling.copy_(torch.log(torch.tensor([0.16, 0.16, 1e-6])).expand(count, 3))
        model._opacity.fill_(3.0)
    return view, model, n


def _analytic_depth(K: torch.Tensor, n: torch.Tensor, offset: float) -> torch.Tensor:
    """Camera z where the ray through (u + offset, v + offset) meets the wall."""
    K = K.double()
    n = n.double()
    vv, uu = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64) + offset,
                            torch.arange(SIZE, dtype=torch.float64) + offset, indexing="ij")
    rays = torch.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], torch.ones_like(uu)])
    return (n @ WALL_POINT.double() / torch.einsum("c,chw->hw", n, rays))[None].float()


def test_render_out_of_a_tilted_wall_is_in_the_project_conventions() -> None:
    """Depth = the analytic ray-plane camera z at +0.5 pixel centres; normal = the wall's
    camera-frame normal (facing the camera) x alpha; alpha from the extra pass."""
    view, model, n = _tilted_wall()
    camera = pgsr.Camera(view)
    adapter = PgsrAdapter(pgsr.Scene([camera]), model, None, pgsr.render, [view], config=_config())
    pkg = pgsr.render(camera, model, None, torch.zeros(3))
    out = adapter.render_out(camera, pkg)

    reference = rasterize(model.get_xyz, model.get_rotation, model.get_scaling, model.get_opacity[:, 0],
                          torch.ones(model.get_xyz.shape[0], 3), view.K.float(), view.world_to_camera.float(),
                          SIZE, SIZE)
    covered = reference.alpha > 0.05
    assert covered.float().mean() > 0.5
    torch.testing.assert_close(out.alpha, reference.alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.normal, n[:, None, None] * out.alpha, atol=1e-5, rtol=0)
    assert (out.normal[2][covered[0]] < 0).all()  # faces the camera

    at_centres = _analytic_depth(view.K, n, 0.5)
    torch.testing.assert_close(out.depth[covered], at_centres[covered], atol=1e-4, rtol=0)
    # PGSR's own plane_depth is the same plane along integer-pixel rays: half a pixel off, which
    # on this wall is far beyond the tolerance above (so ignoring the half pixel would fail)
    at_integers = _analytic_depth(view.K, n, 0.0)
    torch.testing.assert_close(pkg["plane_depth"][covered], at_integers[covered], atol=1e-4, rtol=0)
    assert float((at_integers - at_centres)[covered].abs().min()) > 50 * 1e-4

    assert adapter.render_out(camera, pkg, geometry=False).normal.abs().sum() == 0
    assert torch.equal(adapter.render_out(camera, pkg, geometry=False).color, pkg["render"])


def test_colour_is_what_the_trainers_l1_compares(scene) -> None:
    """app_image while PGSR's SSIM loss is below 0.5 (the trainer's condition), render otherwise."""
    trainer_scene, model = _trainer(scene)
    app_model = pgsr.AppModel(len(scene.views))
    with torch.no_grad():
        app_model.appear_ab[:, 0] = 0.3
    model.use_app = True
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config(),
                          render_kwargs={"app_model": app_model})
    camera = trainer_scene.cameras[1]
    pkg = pgsr.render(camera, model, None, torch.zeros(3), app_model=app_model)
    assert "app_image" in pkg

    camera.original_image = pkg["render"].detach().clamp(0, 1)  # SSIM loss 0: app_image is used
    color = adapter.render_out(camera, pkg, geometry=False).color
    torch.testing.assert_close(color, pkg["app_image"])
    color.sum().backward()
    assert app_model.appear_ab.grad is not None and float(app_model.appear_ab.grad.abs().sum()) > 0

    camera.original_image = 1 - camera.original_image  # SSIM loss > 0.5: the trainer uses render
    assert float(1 - ssim_map(pkg["render"].detach(), camera.original_image).mean()) > 0.5
    torch.testing.assert_close(adapter.render_out(camera, pkg, geometry=False).color, pkg["render"])

    plain = pgsr.render(camera, model, None, torch.zeros(3))  # no app_model: no app_image
    assert adapter.render_out(camera, plain, geometry=False).color is plain["render"]


# ---------------------------------------------------------------------------- native terms
def test_native_terms_are_gated_and_the_cap_comes_from_the_model(scene) -> None:
    trainer_scene, model = _trainer(scene, max_all_points=1234)
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config())
    losses = adapter.config.losses
    assert not losses.use_depth_normal and not losses.use_scale
    assert losses.use_normal and losses.use_ref
    assert adapter.max_gaussians == 1234
    kept = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config(),
                       keep_native_terms=True, max_gaussians=99)
    assert kept.config.losses.use_depth_normal and kept.config.losses.use_scale
    assert kept.max_gaussians == 99


def test_extra_pass_leaves_the_densification_statistics_alone(scene) -> None:
    trainer_scene, model = _trainer(scene)
    cfg = _config()
    cfg.correction.enabled = False  # only geometry terms: nothing of them may reach viewspace_points
    cfg.losses.use_scale = False
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=cfg, keep_native_terms=True)
    camera = trainer_scene.cameras[0]
    pkg = pgsr.render(camera, model, None, torch.zeros(3), return_plane=False, return_depth_normal=False)
    extra = adapter.loss(30, camera, pkg)  # geometry from the adapter's own pass (package has none)
    assert float(extra.detach()) > 0 and "l_dn" in adapter.logs
    extra.backward()
    assert pkg["viewspace_points"].grad is None and pkg["viewspace_points_abs"].grad is None
    assert model._rotation.grad is not None and float(model._rotation.grad.abs().sum()) > 0


# ------------------------------------------------------------------------------- training
def _train(scene, model, trainer_scene, adapter, app_model, steps=50, single_view_from=25, knn_f_state=False):
    """The shape of PGSR's train.py loop (iterations 1-based). PGSR never reads ``_knn_f``, so it
    gets no gradient and Adam keeps no state for it; ``knn_f_state`` adds a zero term so that it
    has Adam moments too (a fork that uses it), whose padding is then checked as well."""
    cameras = trainer_scene.getTrainCameras()
    background = torch.zeros(3)
    losses, appended = [], 0
    for iteration in range(1, steps + 1):
        camera = cameras[(iteration * 3) % len(cameras)]
        gt_image, _ = camera.get_image()
        if iteration > 10:
            model.use_app = True
        geometry = iteration > single_view_from
        render_pkg = pgsr.render(camera, model, None, background, app_model=app_model,
                                 return_plane=geometry, return_depth_normal=geometry)
        visibility_filter = render_pkg["visibility_filter"]
        loss = pgsr.image_loss(render_pkg, gt_image)
        loss = loss + pgsr.scale_loss(model, visibility_filter)
        if geometry:
            loss = loss + pgsr.single_view_loss(render_pkg)
        if knn_f_state:
            loss = loss + 0.0 * model._knn_f.sum()
        loss = loss + adapter.loss(iteration, camera, render_pkg)
        loss.backward()
        with torch.no_grad():
            mask = (render_pkg["out_observe"] > 0) & visibility_filter
            model.max_radii2D[mask] = torch.maximum(model.max_radii2D[mask], render_pkg["radii"][mask].float())
            model.add_densification_stats(render_pkg["viewspace_points"], render_pkg["viewspace_points_abs"],
                                          visibility_filter)
            model.optimizer.step()
            app_model.optimizer.step()
            model.optimizer.zero_grad(set_to_none=True)
            app_model.optimizer.zero_grad(set_to_none=True)
            appended += adapter.densify(iteration, camera, render_pkg)
        losses.append(float(loss))
    return losses, appended


@pytest.mark.slow
def test_fifty_steps_lower_the_loss_and_append_with_consistent_state(scene) -> None:
    trainer_scene, model = _trainer(scene)
    app_model = pgsr.AppModel(len(scene.views))
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config(),
                          render_kwargs={"app_model": app_model})
    losses, appended = _train(scene, model, trainer_scene, adapter, app_model, knn_f_state=True)
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10])
    assert appended > 0 and adapter.appended == appended
    n = model.get_xyz.shape[0]
    assert n == 400 + appended
    names = [group["name"] for group in model.optimizer.param_groups]
    assert names == ["xyz", "knn_f", "f_dc", "f_rest", "opacity", "scaling", "rotation"]
    for group in model.optimizer.param_groups:
        param = group["params"][0]
        assert param.shape[0] == n, group["name"]
        assert param is getattr(model, model._attr(group["name"]))
        state = model.optimizer.state[param]
        assert state["exp_avg"].shape == param.shape and state["exp_avg_sq"].shape == param.shape
        assert int(state["step"]) == 50  # the step counter survived every append
    assert model._knn_f.shape == (n, 6) and torch.isfinite(model._knn_f).all()
    assert float(model._knn_f[400:].std()) > 0.5  # standard-normal rows, as create_from_pcd
    for name in ("xyz_gradient_accum", "xyz_gradient_accum_abs", "denom", "denom_abs"):
        assert getattr(model, name).shape == (n, 1), name
    assert model.max_radii2D.shape == (n,) and model.max_weight.shape == (n,)
    # statistics accumulated before the appends were kept, the new rows start at zero
    assert float(model.denom[:400].sum()) > 0 and float(model.denom_abs[:400].sum()) > 0
    assert float(model.xyz_gradient_accum_abs[:400].sum()) > 0 and float(model.max_radii2D[:400].sum()) > 0
    assert torch.isfinite(model.get_xyz).all()


@pytest.mark.slow
def test_appends_stop_at_max_all_points(scene) -> None:
    trainer_scene, model = _trainer(scene, max_all_points=405)
    app_model = pgsr.AppModel(len(scene.views))
    adapter = PgsrAdapter(trainer_scene, model, None, pgsr.render, scene.views, config=_config(),
                          render_kwargs={"app_model": app_model})
    _, appended = _train(scene, model, trainer_scene, adapter, app_model, steps=20)
    assert appended == 5 and model.get_xyz.shape[0] == 405
    for group in model.optimizer.param_groups:
        param = group["params"][0]
        assert param.shape[0] == 405 and param is getattr(model, model._attr(group["name"]))
        state = model.optimizer.state.get(param, {})
        if group["name"] == "knn_f":
            assert not state  # as in PGSR: never a gradient, so no Adam state (and none invented)
        else:
            assert state["exp_avg"].shape == param.shape and int(state["step"]) == 20
    assert model.xyz_gradient_accum_abs.shape == (405, 1) and model.max_weight.shape == (405,)
