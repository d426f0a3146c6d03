"""The fused L_dn (polargs_plugin.depth_normal) against the torch operations, gradcheck and analytic cases."""

import math

import numba
import pytest
import torch

from polargs_plugin.depth_normal import depth_normal_loss_fused
from polargs_plugin.losses import _depth_normal_loss_torch, depth_normal_loss

K_SKEW = torch.tensor([[30.0, 0.7, 9.0], [0.0, 28.0, 10.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _inputs(dtype=torch.float64, height=20, width=17, seed=0):
    gen = torch.Generator().manual_seed(seed)
    u = torch.linspace(-1, 1, width, dtype=torch.float64)
    v = torch.linspace(-1, 1, height, dtype=torch.float64)
    depth = 2 + 0.3 * torch.sin(3 * u)[None, :] * torch.cos(2 * v)[:, None]
    depth = (depth + 0.01 * torch.rand(height, width, generator=gen, dtype=torch.float64))[None]
    normal = torch.randn(3, height, width, generator=gen, dtype=torch.float64)
    alpha = torch.rand(1, height, width, generator=gen, dtype=torch.float64)
    return depth.to(dtype), normal.to(dtype), alpha.to(dtype)


def _value_and_grads(fn, depth, normal, alpha, K):
    d, n = depth.clone().requires_grad_(), normal.clone().requires_grad_()
    loss = fn(d, n, alpha, K)
    loss.backward()
    return loss.detach(), d.grad, n.grad


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_fused_equals_torch_operations_with_holes_and_zero_normals(dtype, tol):
    depth, normal, alpha = _inputs(dtype)
    depth[0, 5, 6] = 0.0  # a hole: it and its 4 neighbours are invalid
    depth[0, 12, 3] = -1.0
    normal[:, 3, 4] = 0.0  # a zero normal (the floor of safe_normalize)
    fused = _value_and_grads(depth_normal_loss_fused, depth, normal, alpha, K_SKEW)
    plain = _value_and_grads(_depth_normal_loss_torch, depth, normal, alpha, K_SKEW)
    for got, want in zip(fused, plain):
        assert got.dtype == dtype and got.shape == want.shape
        assert torch.allclose(got, want, rtol=tol, atol=tol * float(want.abs().max())), float((got - want).abs().max())


@pytest.mark.slow
def test_gradcheck_and_dispatch():
    depth, normal, alpha = _inputs(height=9, width=8, seed=1)
    depth.requires_grad_(), normal.requires_grad_()
    assert torch.autograd.gradcheck(lambda d, n: depth_normal_loss_fused(d, n, alpha, K_SKEW), (depth, normal))
    # depth_normal_loss takes the fused path on the CPU: its backward is the fused one.
    loss = depth_normal_loss(depth, normal, alpha, K_SKEW)
    assert type(loss.grad_fn).__name__.startswith("_FusedDepthNormal")


def test_value_without_gradients_and_scaled_incoming_gradient():
    """The forward computes the gradient only when one is needed (one pass); the value is the same
    either way, and the backward scales it by the incoming gradient (here 3, through one input)."""
    depth, normal, alpha = _inputs(height=11, width=10, seed=3)
    with torch.no_grad():
        bare = depth_normal_loss_fused(depth, normal, alpha, K_SKEW)
    n = normal.clone().requires_grad_()
    (3 * depth_normal_loss_fused(depth, n, alpha, K_SKEW)).backward()
    value, _, want = _value_and_grads(_depth_normal_loss_torch, depth, normal, alpha, K_SKEW)
    assert math.isclose(float(bare), float(value), rel_tol=1e-12)
    assert torch.allclose(n.grad, 3 * want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))


def test_analytic_tilted_plane():
    """A fronto-parallel plane (unit normal (0, 0, -1) facing the camera) against a rendered normal
    tilted by 0.3 rad: 1 - cos(0.3) at every valid pixel, whatever alpha."""
    depth = torch.full((1, 12, 14), 2.0, dtype=torch.float64)
    alpha = torch.rand(1, 12, 14, dtype=torch.float64) + 0.1
    tilt = 0.3
    tilted = torch.tensor([math.sin(tilt), 0.0, -math.cos(tilt)], dtype=torch.float64)[:, None, None].expand(3, 12, 14)
    assert math.isclose(float(depth_normal_loss_fused(depth, 0.5 * tilted, alpha, K_SKEW)), 1 - math.cos(tilt), rel_tol=1e-12)


def test_nothing_valid_is_zero_with_zero_gradients():
    depth = torch.zeros(1, 6, 7, dtype=torch.float32, requires_grad=True)
    normal = torch.zeros(3, 6, 7, requires_grad=True)
    loss = depth_normal_loss_fused(depth, normal, torch.ones(1, 6, 7), K_SKEW.float())
    loss.backward()
    assert float(loss) == 0 and not depth.grad.any() and not normal.grad.any()


def test_thread_count_does_not_change_the_result():
    depth, normal, alpha = _inputs(torch.float32, 64, 48, seed=2)
    previous = numba.get_num_threads(), torch.get_num_threads()
    results = []
    try:
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            torch.set_num_threads(threads)
            results.append(_value_and_grads(depth_normal_loss_fused, depth, normal, alpha, K_SKEW))
    finally:
        numba.set_num_threads(previous[0])
        torch.set_num_threads(previous[1])
    for a, b in zip(*results):
        assert torch.equal(a, b)
