"""Rasterizer geometry against analytic truth: planar splats render their plane's depth and
normal, the median depth of two layers, near/far culling, SH colours (scipy), input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from scipy.special import sph_harm_y

from polargs_plugin.backends.reference.rasterizer import rasterize, resolve_backend
from polargs_plugin.geometry import eval_sh, rgb_to_sh

BACKENDS = ["torch", "numba"]
F64 = torch.float64


def _quat_wxyz(rot: np.ndarray) -> torch.Tensor:
    return torch.tensor(np.roll(Rotation.from_matrix(rot).as_quat(), 1))


@pytest.mark.parametrize("backend", BACKENDS)
def test_flat_gaussians_render_their_plane(backend: str) -> None:
    width, height = 32, 24
    K = torch.tensor([[28.0, 0, 15.0], [0, 30.0, 12.5], [0, 0, 1]], dtype=F64)
    rot = Rotation.from_rotvec([0.2, -0.3, 0.1]).as_matrix()
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = torch.tensor(rot)
    w2c[:3, 3] = torch.tensor([0.2, 0.1, -0.4])
    n_cam = np.array([0.35, -0.45, -1.0]) / np.linalg.norm([0.35, -0.45, -1.0])  # tilted ~30 deg
    p0_cam = np.array([0.05, -0.03, 3.0])
    tangent = np.cross(n_cam, [1.0, 0.0, 0.0])
    tangent /= np.linalg.norm(tangent)
    frame_cam = np.stack([tangent, np.cross(n_cam, tangent), n_cam], axis=1)
    means, quats = [], []
    for offset, spin in (((0.0, 0.0), 0.0), ((0.4, 0.2), 0.7), ((-0.3, 0.35), -1.1)):
        in_plane = frame_cam @ Rotation.from_rotvec([0, 0, spin]).as_matrix()  # stays in the plane
        means.append(rot.T @ (p0_cam + offset[0] * frame_cam[:, 0] + offset[1] * frame_cam[:, 1] - w2c[:3, 3].numpy()))
        quats.append(_quat_wxyz(rot.T @ in_plane))
    means, quats = torch.tensor(np.array(means)), torch.stack(quats)
    scales = torch.tensor([[0.35, 0.2, 1e-7], [0.3, 0.25, 1e-7], [0.2, 0.3, 1e-7]], dtype=F64)
    opac = torch.tensor([0.9, 0.7, 0.8], dtype=F64)
    colors = torch.rand(3, 3, dtype=F64)
    out = rasterize(means, quats, scales, opac, colors, K, w2c, width, height, tile_size=8, backend=backend)

    ys, xs = np.mgrid[0:height, 0:width]
    rays = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, dtype=float)], -1) @ np.linalg.inv(K.numpy()).T
    plane_z = torch.tensor((n_cam @ p0_cam) / (rays @ n_cam))[None]
    covered = out.alpha > 0
    assert covered.float().mean() > 0.3
    torch.testing.assert_close(out.depth[covered], plane_z[covered], atol=1e-5, rtol=0)
    torch.testing.assert_close(out.plane_depth[covered], plane_z[covered], atol=1e-5, rtol=0)
    opaque = out.alpha > 0.5
    assert opaque.any()
    torch.testing.assert_close(out.median_depth[opaque], plane_z[opaque], atol=1e-5, rtol=0)
    facing = torch.tensor(n_cam if n_cam @ p0_cam < 0 else -n_cam)
    expected_normal = facing[:, None, None].expand(3, height, width) * covered
    torch.testing.assert_close(out.normal / out.alpha.clamp_min(1e-12), expected_normal)
    assert (out.normal[2][covered[0]] < 0).all()


def _layer(z: float, scale: float, opacity: float) -> dict[str, torch.Tensor]:
    return {
        "means": torch.tensor([[0.0, 0.0, z]], dtype=F64),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
        "scales": torch.tensor([[scale, scale, 1e-6]], dtype=F64),
        "opacities": torch.tensor([opacity], dtype=F64),
    }


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("front_opacity", [0.995, 0.4])
def test_two_layers_median_and_expected_depth(backend: str, front_opacity: float) -> None:
    """Fronto-parallel layers on the optical axis: screen footprint sigma = f s / z exactly."""
    width, height, focal = 20, 20, 16.0
    K = torch.tensor([[focal, 0, 10.0], [0, focal, 10.0], [0, 0, 1]], dtype=F64)
    front, back = _layer(2.0, 0.25, front_opacity), _layer(3.0, 0.6, 0.9)
    params = {k: torch.cat([front[k], back[k]]) for k in front}
    out = rasterize(params["means"], params["quats"], params["scales"], params["opacities"],
                    torch.rand(2, 3, dtype=F64), K, torch.eye(4, dtype=F64), width, height, backend=backend)

    ys, xs = np.mgrid[0:height, 0:width]
    r2 = (xs + 0.5 - 10.0) ** 2 + (ys + 0.5 - 10.0) ** 2
    trans = np.ones((height, width))
    weights, crossing = [], []
    for layer, z in ((front, 2.0), (back, 3.0)):
        sigma2 = (focal * float(layer["scales"][0, 0]) / z) ** 2 + 0.3
        alpha = np.minimum(0.99, float(layer["opacities"][0]) * np.exp(-0.5 * r2 / sigma2))
        alpha = np.where(alpha >= 1 / 255, alpha, 0.0)
        weights.append(alpha * trans)
        crossing.append((trans >= 0.5) & (trans * (1 - alpha) < 0.5))
        trans = trans * (1 - alpha)
    median = np.where(crossing[0], 2.0, np.where(crossing[1], 3.0, 0.0))
    assert crossing[0].any() == (front_opacity > 0.5) and crossing[1].any() and (median == 0).any()
    expected_depth = (2.0 * weights[0] + 3.0 * weights[1]) / np.maximum(weights[0] + weights[1], 1e-300)
    torch.testing.assert_close(out.median_depth[0], torch.tensor(median), atol=1e-9, rtol=0)
    torch.testing.assert_close(out.depth[0], torch.tensor(expected_depth), atol=1e-9, rtol=0)
    # Parallel planes facing the camera: the blended plane's depth is the blended z.
    torch.testing.assert_close(out.plane_depth[0], torch.tensor(expected_depth), atol=1e-9, rtol=0)
    torch.testing.assert_close(out.alpha[0], torch.tensor(1 - trans), atol=1e-12, rtol=0)
    torch.testing.assert_close(out.normal[2], -out.alpha[0])  # both layers face the camera


@pytest.mark.parametrize("backend", BACKENDS)
def test_culling_near_far_and_behind(backend: str) -> None:
    width, height = 12, 10
    K = torch.tensor([[10.0, 0, 6], [0, 10.0, 5], [0, 0, 1]], dtype=F64)
    eye = torch.eye(4, dtype=F64)
    means = torch.tensor([[0.0, 0.0, 0.005], [0.0, 0.0, -1.0], [0.0, 0.0, 150.0], [0.0, 0.0, 0.5]], dtype=F64)
    means.requires_grad_(True)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(4, 1)
    scales = torch.tensor([[0.01, 0.01, 0.01], [0.5, 0.5, 0.5], [9.0, 9.0, 9.0], [0.05, 0.05, 0.04]], dtype=F64)
    opac = torch.full((4,), 0.8, dtype=F64)
    colors = torch.rand(4, 3, dtype=F64)
    out = rasterize(means, quats, scales, opac, colors, K, eye, width, height, near=0.01, far=100.0, backend=backend)
    assert out.radii.tolist()[:3] == [0, 0, 0] and out.radii[3] > 0
    alone = rasterize(means[3:], quats[3:], scales[3:], opac[3:], colors[3:], K, eye, width, height, backend=backend)
    torch.testing.assert_close(out.color, alone.color)
    torch.testing.assert_close(out.depth, alone.depth)
    out.color.sum().add(out.depth.sum()).backward()
    assert torch.isfinite(means.grad).all() and (means.grad[:3] == 0).all() and means.grad[3].abs().sum() > 0

    culled = rasterize(means, quats, scales, opac, colors, K, eye, width, height, near=0.6, backend=backend)
    assert (culled.radii == 0).all() and (culled.alpha == 0).all() and (culled.depth == 0).all()


def _real_sh_basis(dirs: np.ndarray) -> np.ndarray:
    """Real SH up to degree 3 from scipy's complex harmonics (Condon-Shortley phase kept)."""
    theta, phi = np.arccos(dirs[:, 2]), np.arctan2(dirs[:, 1], dirs[:, 0])
    cols = []
    for degree in range(4):
        for m in range(-degree, degree + 1):
            y = sph_harm_y(degree, abs(m), theta, phi)
            cols.append(math.sqrt(2) * y.imag if m < 0 else (y.real if m == 0 else math.sqrt(2) * y.real))
    return np.stack(cols, -1)


def test_eval_sh_matches_scipy() -> None:
    dirs = np.random.default_rng(0).normal(size=(64, 3)) * 3.0
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    coeffs = torch.randn(64, 16, 3, dtype=F64) * 0.1
    expected = np.einsum("nk,nkc->nc", _real_sh_basis(unit), coeffs.numpy()) + 0.5
    torch.testing.assert_close(eval_sh(coeffs, torch.tensor(dirs)), torch.tensor(np.maximum(expected, 0.0)))
    with pytest.raises(ValueError):
        eval_sh(torch.zeros(2, 5, 3), torch.ones(2, 3))


@pytest.mark.parametrize("backend", BACKENDS)
def test_sh_colours_in_the_render(backend: str) -> None:
    from test_rasterizer import _random_scene

    width, height = 16, 12
    (means, quats, scales, opac, rgb), K, w2c = _random_scene(12, width, height, seed=8)
    args = (means, quats, scales, opac)
    plain = rasterize(*args, rgb, K, w2c, width, height, backend=backend)
    sh0 = rasterize(*args, rgb_to_sh(rgb)[:, None, :], K, w2c, width, height, backend=backend)
    torch.testing.assert_close(sh0.color, plain.color, atol=1e-12, rtol=0)

    coeffs = torch.randn(12, 16, 3, dtype=F64) * 0.2
    camera_centre = torch.linalg.inv(w2c)[:3, 3]
    view_dirs = (means - camera_centre).numpy()
    view_dirs /= np.linalg.norm(view_dirs, axis=1, keepdims=True)
    per_view = np.maximum(np.einsum("nk,nkc->nc", _real_sh_basis(view_dirs), coeffs.numpy()) + 0.5, 0.0)
    sh3 = rasterize(*args, coeffs, K, w2c, width, height, backend=backend)
    expected = rasterize(*args, torch.tensor(per_view), K, w2c, width, height, backend=backend)
    torch.testing.assert_close(sh3.color, expected.color, atol=1e-10, rtol=0)


def test_backend_choice_and_input_checks() -> None:
    assert resolve_backend("auto", torch.device("cpu")) == "numba"
    assert resolve_backend("auto", torch.device("cuda")) == "torch"
    with pytest.raises(ValueError):
        resolve_backend("numba", torch.device("cuda"))
    with pytest.raises(ValueError):
        resolve_backend("fast", torch.device("cpu"))
    K = torch.eye(3)
    with pytest.raises(ValueError, match="means"):
        rasterize(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2), torch.ones(2, 3), K,
                  torch.eye(4), 4, 4)
    with pytest.raises(ValueError, match="colors"):
        rasterize(torch.zeros(2, 3), torch.ones(2, 4), torch.ones(2, 3), torch.ones(2), torch.ones(2, 4), K,
                  torch.eye(4), 4, 4)
