"""The adapter kit against independent truth: analytic normals and depths, the graphdeco
projection written out from its FoV matrices, Adam state after appends, raw <-> activated."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from polargs_plugin import PolarConfig, PolarHooks
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.kit import (
    append_rows,
    aux_channels,
    depth_from_accumulated,
    depth_from_inverse,
    depth_from_plane,
    gaussian_normals,
    graphdeco_from_view,
    new_from_raw,
    raw_from_new,
    render_out_from_aux,
    state_from_raw,
    view_from_graphdeco,
    world_view_transform,
)
from polargs_plugin.types import NewGaussians, RenderOut, TrainingHooks, View

F64 = torch.float64


def _w2c(rotvec, t) -> torch.Tensor:
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = torch.tensor(Rotation.from_rotvec(rotvec).as_matrix())
    w2c[:3, 3] = torch.tensor(t, dtype=F64)
    return w2c


def _quat_wxyz(matrix: np.ndarray) -> torch.Tensor:
    return torch.tensor(np.roll(Rotation.from_matrix(matrix).as_quat(), 1))


# ------------------------------------------------------------------------------------ normals
def test_gaussian_normals_are_the_rotated_shortest_axis_facing_the_camera() -> None:
    w2c = _w2c([0.3, -0.2, 0.1], [0.1, -0.2, 3.0])
    rng = np.random.default_rng(1)
    rots = Rotation.random(64, random_state=2).as_matrix()
    quats = torch.stack([_quat_wxyz(r) for r in rots]) * 3.0  # any norm
    scales = torch.tensor(rng.uniform(0.1, 1.0, (64, 3)))
    shortest = rng.integers(0, 3, 64)
    scales[torch.arange(64), torch.tensor(shortest)] = 1e-3
    means = torch.tensor(rng.normal(0, 0.5, (64, 3)))
    normals = gaussian_normals(means, quats, scales, w2c)
    R, t = w2c[:3, :3].numpy(), w2c[:3, 3].numpy()
    for i in range(64):
        axis = R @ rots[i][:, shortest[i]]
        mean_cam = R @ means[i].numpy() + t
        expected = axis if axis @ mean_cam < 0 else -axis
        np.testing.assert_allclose(normals[i].numpy(), expected, atol=1e-12)
    assert torch.allclose(normals.norm(dim=-1), torch.ones(64, dtype=F64))


def _flat_plane_scene(z: float = 2.0):
    """A fronto-parallel wall of flat Gaussians at camera z = ``z`` (identity camera)."""
    xs = torch.linspace(-1.2, 1.2, 13, dtype=F64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    n = grid.shape[0]
    means = torch.cat([grid, torch.full((n, 1), z, dtype=F64)], dim=1)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1)
    scales = torch.tensor([[0.15, 0.15, 1e-6]], dtype=F64).repeat(n, 1)
    opacities = torch.full((n,), 0.9, dtype=F64)
    K = torch.tensor([[20.0, 0, 12.0], [0, 20.0, 10.0], [0, 0, 1]], dtype=F64)
    return means, quats, scales, opacities, K, torch.eye(4, dtype=F64)


def _render_channels(means, quats, scales, opacities, K, w2c, channels, width, height):
    """A rasterizer that composites any number of channels (3 at a time, background 0)."""
    out = []
    for start in range(0, channels.shape[1], 3):
        group = channels[:, start : start + 3]
        padded = torch.cat([group, group.new_zeros(group.shape[0], 3 - group.shape[1])], dim=1)
        rendered = rasterize(means, quats, scales, opacities, padded, K, w2c, width, height, backend="torch")
        out.append(rendered.color[: group.shape[1]])
    return torch.cat(out), rendered


def test_aux_pass_renders_the_contract_maps_of_a_plane() -> None:
    means, quats, scales, opacities, K, w2c = _flat_plane_scene(2.0)
    aux = aux_channels(means, quats, scales, w2c)
    image, reference = _render_channels(means, quats, scales, opacities, K, w2c, aux, 24, 20)
    out = render_out_from_aux(reference.color, image, K=K)
    covered = out.alpha > 1e-3
    assert covered.float().mean() > 0.9
    torch.testing.assert_close(out.alpha, reference.alpha)
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.0))
    expected = torch.tensor([0.0, 0.0, -1.0], dtype=F64)[:, None, None] * out.alpha
    torch.testing.assert_close(out.normal, expected)
    # the same maps the reference rasterizer computes itself
    torch.testing.assert_close(out.normal, reference.normal)
    torch.testing.assert_close(out.plane_depth[covered], torch.full_like(out.depth[covered], 2.0))
    torch.testing.assert_close(out.plane_depth, reference.plane_depth)
    assert render_out_from_aux(reference.color, image).plane_depth is None  # no K, no plane depth
    with pytest.raises(ValueError, match=r"aux must be \(6, H, W\)"):
        render_out_from_aux(reference.color, image[:5])


# ------------------------------------------------------------------------------------- depths
def test_depth_from_inverse_and_accumulated_on_analytic_layers() -> None:
    alpha = torch.tensor([[[0.8, 0.0, 0.5]]], dtype=F64)
    z = torch.tensor([[[2.0, 3.0, 4.0]]], dtype=F64)
    torch.testing.assert_close(depth_from_inverse(alpha / z, alpha), torch.tensor([[[2.0, 0.0, 4.0]]], dtype=F64))
    torch.testing.assert_close(depth_from_accumulated(alpha * z, alpha), torch.tensor([[[2.0, 0.0, 4.0]]], dtype=F64))
    # two layers with weights 0.6 at z=1 and 0.3 at z=3: harmonic vs arithmetic mean
    w = torch.tensor([0.6, 0.3], dtype=F64)
    zs = torch.tensor([1.0, 3.0], dtype=F64)
    a = w.sum().reshape(1, 1, 1)
    assert float(depth_from_inverse((w / zs).sum().reshape(1, 1, 1), a)) == pytest.approx(0.9 / (0.6 + 0.1))
    assert float(depth_from_accumulated((w * zs).sum().reshape(1, 1, 1), a)) == pytest.approx(1.5 / 0.9)


@pytest.mark.parametrize("pixel_center", [0.5, 0.0])
def test_depth_from_plane_is_the_ray_plane_intersection(pixel_center: float) -> None:
    height, width = 9, 12
    K = torch.tensor([[15.0, 0, 6.0], [0, 14.0, 4.5], [0, 0, 1]], dtype=F64)
    n = torch.tensor([0.3, -0.2, -1.0], dtype=F64)
    n = n / n.norm()
    point = torch.tensor([0.1, 0.2, 2.5], dtype=F64)  # on the plane, in front of the camera
    d = float(-(n @ point))  # n . x = -d with d > 0
    alpha = 0.7  # alpha-blended values: both scaled by alpha
    distance = torch.full((1, height, width), d * alpha, dtype=F64)
    normal = (n * alpha)[:, None, None].expand(3, height, width)
    depth = depth_from_plane(distance, normal, K, pixel_center=pixel_center)
    v, u = np.mgrid[0:height, 0:width] + pixel_center
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K.numpy()).T
    t = d / -(rays @ n.numpy())
    np.testing.assert_allclose(depth[0].numpy(), t, rtol=1e-12)
    # back-projected points lie on the plane
    points = rays * t[..., None]
    np.testing.assert_allclose(points @ n.numpy(), -d, atol=1e-12)


# ------------------------------------------------------------------------------------ cameras
def test_render_out_detached_drops_the_graph_and_shares_the_storage() -> None:
    x = torch.rand(4, 2, 3, requires_grad=True)
    render = RenderOut(color=x[:3] * 2, depth=x[3:] + 1, normal=-x[:3], alpha=x[3:].sigmoid(), radii=torch.ones(5))
    detached = render.detached()
    for name in ("color", "depth", "normal", "alpha", "radii"):
        got, want = getattr(detached, name), getattr(render, name)
        assert got.grad_fn is None and not got.requires_grad
        assert got.data_ptr() == want.data_ptr() and torch.equal(got, want)
    assert detached.median_depth is None and detached.plane_depth is None and detached.means2d is None
    render.color.sum().backward()  # the original keeps its graph
    assert torch.equal(x.grad[:3], torch.full((3, 2, 3), 2.0))


def test_graphdeco_camera_round_trip_and_its_own_projection() -> None:
    width, height = 40, 30
    fov_x, fov_y = 0.9, 0.7
    w2c = _w2c([0.2, 0.4, -0.1], [0.3, -0.1, 2.0])

    class Camera:  # graphdeco stores R = w2c rotation transposed, T, FoVs, size, name
        R = w2c[:3, :3].T.numpy()
        T = w2c[:3, 3].numpy()
        FoVx, FoVy = fov_x, fov_y
        image_width, image_height = width, height
        image_name = "cam0"

    stokes = torch.rand(3, 3, height, width)
    view = view_from_graphdeco(Camera(), stokes)
    torch.testing.assert_close(view.world_to_camera, w2c)
    # graphdeco's projection: p_ndc from (W2C)^T and the FoV frustum, pixel = ((ndc + 1) S - 1) / 2
    # in integer-centre coordinates, i.e. (ndc + 1) S / 2 with this project's +0.5 centres
    point = torch.tensor([0.2, -0.1, 0.3], dtype=F64)
    cam = torch.cat([point, torch.ones(1, dtype=F64)]) @ world_view_transform(Camera.R, Camera.T).double()
    ndc = cam[:2] / cam[2] / torch.tensor([math.tan(fov_x / 2), math.tan(fov_y / 2)], dtype=F64)
    expected = ((ndc + 1) * torch.tensor([width, height], dtype=F64) - 1) / 2 + 0.5
    uvw = view.K @ (view.R @ point + view.t)
    torch.testing.assert_close(uvw[:2] / uvw[2], expected, atol=1e-5, rtol=0)  # float32 W2C
    back = graphdeco_from_view(view)
    np.testing.assert_allclose(back.R, Camera.R, atol=1e-12)
    np.testing.assert_allclose(back.T, Camera.T, atol=1e-12)
    assert back.FoVx == pytest.approx(fov_x) and back.FoVy == pytest.approx(fov_y)
    assert (back.image_width, back.image_height) == (width, height)
    with pytest.raises(ValueError, match="trainer's camera is 30x40"):
        view_from_graphdeco(Camera(), torch.rand(3, 3, 10, 10))


def test_graphdeco_from_view_refuses_an_off_centre_principal_point() -> None:
    K = torch.tensor([[30.0, 0, 21.0], [0, 30.0, 15.0], [0, 0, 1]], dtype=F64)
    view = View("v", K, torch.eye(4, dtype=F64), torch.rand(3, 3, 30, 40))
    with pytest.raises(ValueError, match="off the image centre"):
        graphdeco_from_view(view)


# ------------------------------------------------------------------------------------- append
def _raw(n: int, sh_rest: int = 3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(n)
    return {
        "means": torch.randn(n, 3, generator=g),
        "sh_dc": torch.randn(n, 1, 3, generator=g),
        "sh_rest": torch.randn(n, sh_rest, 3, generator=g),
        "opacity_logits": torch.randn(n, generator=g),
        "log_scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),
    }


def _train_one_step(params, optimizers) -> None:
    loss = sum((p ** 2).sum() for p in params.values())
    loss.backward()
    for opt in optimizers if isinstance(optimizers, list) else [optimizers]:
        opt.step()
        opt.zero_grad()


@pytest.mark.parametrize("layout", ["named_groups", "one_per_name"])
def test_append_rows_zero_moments_step_kept_state_padded(layout: str) -> None:
    params = {k: torch.nn.Parameter(v) for k, v in _raw(5).items()}
    if layout == "named_groups":
        optimizers = torch.optim.Adam([{"params": [p], "name": k, "lr": 0.01} for k, p in params.items()])
        opt_list = optimizers
        state_of = lambda name: optimizers.state[params[name]]  # noqa: E731
    else:
        optimizers = {k: torch.optim.Adam([p], lr=0.01) for k, p in params.items()}
        opt_list = list(optimizers.values())
        state_of = lambda name: optimizers[name].state[params[name]]  # noqa: E731
    _train_one_step(params, opt_list)
    _train_one_step(params, opt_list)
    before = {k: (p.detach().clone(), {s: v.clone() for s, v in state_of(k).items()}) for k, p in params.items()}
    stats = {"grad2d": torch.rand(5), "count": torch.arange(5.0), "radii": None, "binoms": torch.rand(7, 7)}
    new_rows = _raw(3)
    append_rows(params, optimizers, new_rows, state=stats)
    for name, param in params.items():
        old_value, old_state = before[name]
        assert param.shape[0] == 8
        assert torch.equal(param[:5].detach(), old_value) and torch.equal(param[5:].detach(), new_rows[name])
        state = state_of(name)
        assert torch.equal(state["step"], old_state["step"])  # the step counter is kept
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(state[key][:5], old_state[key][:5])
            assert bool((state[key][5:] == 0).all())
    assert stats["grad2d"].shape == (8,) and bool((stats["grad2d"][5:] == 0).all())
    assert torch.equal(stats["count"][:5], torch.arange(5.0))
    assert stats["radii"] is None and stats["binoms"].shape == (7, 7)  # not per-Gaussian: untouched
    _train_one_step(params, opt_list)  # the next Adam step runs on the new rows
    assert all(not torch.equal(params[k][5:].detach(), new_rows[k]) for k in params)


def test_append_rows_names_the_bad_input() -> None:
    params = {k: torch.nn.Parameter(v) for k, v in _raw(4).items()}
    optimizer = torch.optim.Adam([{"params": [p], "name": k} for k, p in params.items()])
    rows = _raw(2)
    with pytest.raises(KeyError, match="no new rows for \\['quats'\\]"):
        append_rows(params, optimizer, {k: v for k, v in rows.items() if k != "quats"})
    rows["sh_rest"] = torch.zeros(2, 8, 3)
    with pytest.raises(ValueError, match="rows\\['sh_rest'\\] has shape \\(2, 8, 3\\), expected \\(M, 3, 3\\)"):
        append_rows(params, optimizer, rows)
    assert params["means"].shape[0] == 4


def test_raw_and_activated_gaussians_round_trip() -> None:
    new = NewGaussians(
        means=torch.randn(6, 3, dtype=F64),
        quats=torch.nn.functional.normalize(torch.randn(6, 4, dtype=F64), dim=-1),
        scales=torch.rand(6, 3, dtype=F64) + 0.01,
        colors=torch.rand(6, 3, dtype=F64),
        opacities=torch.rand(6, dtype=F64) * 0.98 + 0.01,
    )
    raw = raw_from_new(new, sh_rest_coeffs=8)
    assert raw["sh_rest"].shape == (6, 8, 3) and bool((raw["sh_rest"] == 0).all())
    assert raw["sh_dc"].shape == (6, 1, 3)
    back = new_from_raw(raw)
    for field in ("means", "quats", "scales", "colors", "opacities"):
        torch.testing.assert_close(getattr(back, field), getattr(new, field))
    state = state_from_raw(raw)
    torch.testing.assert_close(state.scales, new.scales)
    torch.testing.assert_close(state.opacities, new.opacities)
    # the reference model decodes appended rows the same way
    torch.testing.assert_close(0.28209479177387814 * raw["sh_dc"][:, 0] + 0.5, new.colors)


# ---------------------------------------------------------------------------- hook contract
def test_polar_hooks_meet_the_protocol_and_default_to_the_synthetic_preset() -> None:
    hooks = PolarHooks()
    assert isinstance(hooks, TrainingHooks)
    assert hooks.config == PolarConfig.synthetic()


def test_config_from_env_gates_native_terms_before_the_json_file(tmp_path) -> None:
    from polargs_plugin.service.configs import config_from_environment as config_from_env

    native = ("use_depth_normal", "use_scale")
    cfg = config_from_env({}, native_terms=native)
    assert cfg == PolarConfig.real().update({"losses": {"use_depth_normal": False, "use_scale": False}})
    kept = config_from_env({"POLARGS_KEEP_NATIVE": "1", "POLARGS_PRESET": "synthetic"}, native_terms=native)
    assert kept == PolarConfig.synthetic()
    path = tmp_path / "polar.json"
    path.write_text('{"losses": {"use_scale": true, "alpha_normal": 0.3}}')
    cfg = config_from_env({"POLARGS_CONFIG": str(path)}, native_terms=native)
    assert cfg.losses.use_scale and not cfg.losses.use_depth_normal and cfg.losses.alpha_normal == 0.3
    path.write_text('{"losses": {"alpha_nromal": 0.3}}')
    with pytest.raises(ValueError, match="polar.json: polar.losses: unknown setting 'alpha_nromal'"):
        config_from_env({"POLARGS_CONFIG": str(path)})
    path.write_text('{"densify": {"interval": 0}}')
    with pytest.raises(ValueError, match=re.escape("polar.json: polar.densify.interval: must be a positive integer, got 0")):
        config_from_env({"POLARGS_CONFIG": str(path)})
    with pytest.raises(ValueError, match="POLARGS_PRESET: unknown preset 'paper'"):
        config_from_env({"POLARGS_PRESET": "paper"})
