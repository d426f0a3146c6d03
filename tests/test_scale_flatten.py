"""The flattening loss's compiled backward against torch's autograd: equal to the last bit."""

import pytest
import torch

from polargs_plugin.losses import scale_loss
from polargs_plugin.scale_flatten import scale_loss_fused


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_value_and_gradient_equal_autograd_bit_for_bit_with_ties(dtype):
    gen = torch.Generator().manual_seed(0)
    scales = torch.rand(1001, 3, generator=gen, dtype=dtype) * 0.1
    scales[:5, :2] = 0.001  # two-way ties at the minimum
    scales[5:9] = scales[5:9, :1].clone()  # three-way ties
    grad = torch.tensor(0.37, dtype=dtype)
    ref = scales.clone().requires_grad_()
    expected = ref.amin(dim=-1).mean()
    (expected_grad,) = torch.autograd.grad(expected, ref, grad)
    fused = scales.clone().requires_grad_()
    got = scale_loss(fused)  # CPU float: the compiled backward
    assert type(got.grad_fn).__name__ == "_ScaleLossBackward"
    (got_grad,) = torch.autograd.grad(got, fused, grad)
    assert torch.equal(got, expected) and torch.equal(got_grad, expected_grad)
    # Analytic: a tie shares the row's 1/N equally.
    assert float(got_grad[5, 0]) == pytest.approx(0.37 / 1001 / 3, rel=1e-6)
    assert float(got_grad[0, 0]) == pytest.approx(0.37 / 1001 / 2, rel=1e-6)


def test_gradcheck():
    scales = (torch.rand(7, 3, dtype=torch.float64) + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(scale_loss_fused, (scales,))
