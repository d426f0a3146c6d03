"""Rasterizer gradients: finite differences (gradcheck, float64) for both compositing paths,
the Numba backward against the torch path, and the screen-space gradient in means2d."""

from __future__ import annotations

import pytest
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize

from test_rasterizer import _camera, _edge_on_gaussian, _look_transform, _random_scene, _scene_with_occluders


def _outputs(out) -> torch.Tensor:
    return torch.cat([out.color, out.depth, out.median_depth, out.normal, out.alpha, out.plane_depth]).reshape(-1)


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize(("sh", "order"), [(False, "center"), (True, "center"), (False, "ray")])
def test_gradcheck(backend: str, sh: bool, order: str) -> None:
    width, height = 10, 8
    (means, quats, scales, opac, colors), K, w2c = _random_scene(5, width, height, seed=4)
    scales = scales * 2.5  # a few pixels wide: every Gaussian overlaps several pixels and others
    opac = 0.3 + 0.5 * opac
    if sh:
        colors = torch.randn(5, 9, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 0.3

    def render(m, q, s, o, c):
        return _outputs(rasterize(m, q, s, o, c, K, w2c, width, height, tile_size=4, backend=backend, order=order))

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    assert render(*inputs).abs().sum() > 0
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_gradcheck_edge_on_splat(backend: str) -> None:
    """Depth clamp active over part of the footprint: gradients then go to the clamp bounds."""
    width, height = 12, 10
    K, w2c = _camera(width, height, focal=1.2 * width), _look_transform(9)
    mean, quat = _edge_on_gaussian(w2c)
    scales = torch.tensor([[0.2, 0.12, 0.002]], dtype=torch.float64)

    def render(m, q, s):
        out = rasterize(m, q, s, torch.tensor([0.8], dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64),
                        K, w2c, width, height, tile_size=4, backend=backend)
        return torch.cat([out.depth, out.median_depth]).reshape(-1)

    inputs = [t[None].clone().requires_grad_(True) for t in (mean, quat)] + [scales.requires_grad_(True)]
    assert render(*inputs).abs().sum() > 0
    assert torch.autograd.gradcheck(render, inputs, eps=1e-7, atol=1e-5, rtol=1e-3, fast_mode=True)


@pytest.mark.parametrize("order", ["center", "ray"])
def test_numba_gradients_match_torch(order: str) -> None:
    width, height = 22, 17
    params, K, w2c = _scene_with_occluders(1, width, height)
    weights = torch.rand(10, height, width, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    grads = {}
    for backend in ("torch", "numba"):
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, K, w2c, width, height, tile_size=8 if order == "center" else 2, backend=backend,
                        order=order)
        (_outputs(out).reshape(10, height, width) * weights).sum().backward()
        grads[backend] = [p.grad for p in leaves] + [out.means2d.grad]
    for g_torch, g_numba in zip(grads["torch"], grads["numba"]):
        assert g_torch.abs().max() > 0
        torch.testing.assert_close(g_numba, g_torch, atol=1e-9, rtol=1e-7)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_means2d_grad_is_screen_space_gradient(backend: str) -> None:
    """On the optical axis an isotropic Gaussian's footprint is stationary under small lateral
    moves, so dL/dx_world = dL/du * fx / z exactly for a loss on colour and alpha."""
    width, height, z = 16, 12, 3.0
    K = torch.tensor([[20.0, 0, 8], [0, 24.0, 6], [0, 0, 1]], dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, z]], dtype=torch.float64, requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64)
    scales = torch.full((1, 3), 0.3, dtype=torch.float64)
    opac = torch.tensor([0.8], dtype=torch.float64)
    colors = torch.tensor([[0.9, 0.4, 0.1]], dtype=torch.float64)
    out = rasterize(means, quats, scales, opac, colors, K, torch.eye(4, dtype=torch.float64), width, height,
                    backend=backend)
    weights = torch.rand(4, height, width, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    (torch.cat([out.color, out.alpha]) * weights).sum().backward()
    g2d = out.means2d.grad[0]
    assert g2d.abs().min() > 1e-3
    torch.testing.assert_close(means.grad[0, :2], g2d * torch.stack([K[0, 0], K[1, 1]]) / z, atol=1e-10, rtol=1e-8)
