"""The fused reflective-pixel losses (polargs_plugin.reflective_window) against the torch
operations they replace (ReflectiveTargets' *pixels* strategy), by gradcheck, and at ties."""

from __future__ import annotations

import pytest
import torch

import polargs_plugin.losses as losses_module
from polargs_plugin.losses import ReflectiveTargets
from polargs_plugin.reflective_window import reflective_window_losses


def _targets(dtype, seed=3, H=24, W=28, fraction=0.03):
    gen = torch.Generator().manual_seed(seed)
    image, i_diff, i_chro = (torch.rand(3, H, W, generator=gen, dtype=dtype) for _ in range(3))
    spec = torch.rand(1, H, W, generator=gen) < fraction
    spec[0, 0, 1] = True  # a window reflected at the border
    over = (torch.rand(1, H, W, generator=gen) < fraction) & ~spec
    over[0, -1, -1] = True
    targets = ReflectiveTargets(image, spec, i_diff, over, i_chro)
    assert targets.strategy == "pixels"
    pred = torch.rand(3, H, W, generator=gen, dtype=dtype)
    return targets, pred


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("ssim_weight", [0.2, 0.0, 1.0])
def test_fused_equals_the_torch_operations(monkeypatch, dtype, tol, ssim_weight):
    targets, pred = _targets(dtype)
    fused_pred = pred.clone().requires_grad_()
    fused = targets(fused_pred, 0.7, ssim_weight)
    fused[0].backward()
    monkeypatch.setattr(losses_module, "numba_path", lambda tensor: False)
    torch_pred = pred.clone().requires_grad_()
    reference = targets(torch_pred, 0.7, ssim_weight)
    reference[0].backward()
    for a, b in zip(fused, reference):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)
    torch.testing.assert_close(fused_pred.grad, torch_pred.grad, atol=tol, rtol=0)
    assert fused_pred.grad.abs().sum() > 0


@pytest.mark.slow
def test_gradcheck():
    targets, pred = _targets(torch.float64, seed=5)
    inputs = (targets.windows, targets.pixels, targets.weights, targets.targets, targets.values,
              targets.target_mean, targets.target_sq)
    pred.requires_grad_()
    assert torch.autograd.gradcheck(lambda x: reflective_window_losses(x, *inputs, 0.2), (pred,), eps=1e-6, atol=1e-8)


def test_l1_gradient_is_zero_at_a_tie():
    """|x - y| at x == y: gradient 0, as torch's abs (SSIM off, so only the L1 remains)."""
    targets, pred = _targets(torch.float64, seed=9)
    pixel = targets.pixels[0]
    pred.reshape(3, -1)[:, pixel] = targets.values[0, :, 0]  # the corrected target, exactly
    pred.requires_grad_()
    losses = reflective_window_losses(pred, targets.windows, targets.pixels, targets.weights, targets.targets,
                                      targets.values, targets.target_mean, targets.target_sq, 0.0)
    (grad,) = torch.autograd.grad(losses[0, 0], pred)
    assert float(losses[0, 0].detach()) == 0 and not grad.any()
