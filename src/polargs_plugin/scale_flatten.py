r"""The flattening loss :math:`L_{scale} = \mathrm{mean}_i \min_k s_{ik}` with a compiled backward,
bit for bit the torch operations.

The value is torch's ``scales.amin(dim=-1).mean()`` (its summation order); the backward, which
torch runs as half a dozen (N, 3) operations (the mean's division, the minimum's tie mask, its
count and the division by it), is one pass over the Gaussians here with the same arithmetic in
the input's dtype: each entry equal to its row's minimum gets (g / N) / (entries equal to it),
the others 0 (tests/ check it against autograd with ``torch.equal``).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from polargs_plugin.threads import numba_scheduling

__all__ = ["scale_loss_fused"]


@numba.njit(parallel=True, cache=True)
def _backward_kernel(scales, share, grad):
    zero = scales.dtype.type(0)
    for i in numba.prange(scales.shape[0]):
        smallest = min(scales[i, 0], min(scales[i, 1], scales[i, 2]))
        ties = 0
        for k in range(3):
            if scales[i, k] == smallest:
                ties += 1
        each = share / scales.dtype.type(ties)
        for k in range(3):
            grad[i, k] = each if scales[i, k] == smallest else zero


class _ScaleLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scales: Tensor) -> Tensor:
        ctx.scales, ctx.dtype = scales.detach().contiguous().numpy(), scales.dtype
        return scales.detach().amin(dim=-1).mean()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        scales = ctx.scales
        # The mean's backward, g / N, by the same torch division.
        share = (grad.to(ctx.dtype) / scales.shape[0]).item()
        out = np.empty_like(scales)
        with numba_scheduling():
            _backward_kernel(scales, scales.dtype.type(share), out)
        return torch.from_numpy(out)


def scale_loss_fused(scales: Tensor) -> Tensor:
    """:func:`polargs_plugin.losses.scale_loss` of a CPU float (N, 3) tensor, N >= 1 (differentiable once).

    Example:
        >>> s = torch.tensor([[0.1, 0.5, 0.1], [0.3, 0.2, 0.4]], requires_grad=True)
        >>> scale_loss_fused(s).backward()
        >>> s.grad
        tensor([[0.2500, 0.0000, 0.2500],
                [0.0000, 0.5000, 0.0000]])
    """
    return _ScaleLoss.apply(scales)
