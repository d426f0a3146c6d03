r"""Fused per-pixel colour losses of the reflective pixels (PC's replacement), compiled for the CPU.

:class:`polargs_plugin.losses.ReflectiveTargets` (its *pixels* strategy) needs, for each of P
reflective pixels and each of two targets (the corrected one and the plain training colour), the
photometric loss of the prediction there:

.. math::
    L_{t,p} = \frac{1}{C}\sum_c \Big[(1-\lambda)\,|x_{c,p} - y_{t,c,p}|
              + \lambda\,\big(1 - \mathrm{SSIM}_{t,c,p}\big)\Big],

with the SSIM of the Gaussian window around p (weights :math:`w_k` over the K window taps, the
targets' windowed moments precomputed). Done by torch operations this is a gather of the
windows, a matrix product and about twenty small element-wise operations, each with its autograd
node: about 2 ms a step for a few dozen pixels, nearly all of it overhead. Here one pass forms
the moments and the losses, and the backward scatters the gradient back onto the window taps,
serially in pixel order (windows overlap, and P is small: at most ``max_window_elements`` taps).
The SSIM formula and its partial derivatives are those of :mod:`polargs_plugin.ssim`; the L1's
gradient at 0 is 0, as torch's. Arithmetic is float64 whatever the input dtype.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from polargs_plugin.ssim import C1, C2, EPS

__all__ = ["reflective_window_losses"]


@numba.njit(inline="always")
def _ssim(mu, sq, mu_t, sq_t, cross):
    """SSIM (kornia's order of operations, :func:`polargs_plugin.ssim.ssim_from_moments`) and its
    partial derivatives w.r.t. the prediction's mean, second moment and cross moment."""
    mu_sq, mu_t_sq, mu_mu_t = mu * mu, mu_t * mu_t, mu * mu_t
    a1 = 2.0 * mu_mu_t + C1
    a2 = 2.0 * (cross - mu_mu_t) + C2
    b1 = mu_sq + mu_t_sq + C1
    b2 = (sq - mu_sq) + (sq_t - mu_t_sq) + C2
    den = b1 * b2 + EPS
    value = (a1 * a2) / den
    inv = 1.0 / den
    # S = A1 A2 / D: dS/dA1 = A2/D, dS/dA2 = A1/D, dS/dB1 = -S B2/D, dS/dB2 = -S B1/D.
    d_mu = 2.0 * inv * (mu_t * (a2 - a1) + mu * value * (b1 - b2))
    d_sq = -value * b1 * inv
    d_cross = 2.0 * a1 * inv
    return value, d_mu, d_sq, d_cross


@numba.njit(cache=True)
def _kernel(pred, windows, pixels, weights, targets, values, target_mean, target_sq, ssim_weight,
            grad_losses, losses, grad_pred, backward):
    """Forward (``backward`` False): ``losses`` (2, P). Backward: ``grad_pred`` (C, H*W) from the
    gradient ``grad_losses`` (2, P) of the losses."""
    channels, count = pred.shape[0], windows.shape[0]
    taps = windows.shape[1]
    l1_share = (1.0 - ssim_weight) / channels
    ssim_share = ssim_weight / channels
    for p in range(count):
        for c in range(channels):
            mu = sq = cross0 = cross1 = 0.0
            for k in range(taps):
                x = float(pred[c, windows[p, k]])
                wx = float(weights[k]) * x
                mu += wx
                sq += wx * x
                cross0 += wx * float(targets[0, c, p, k])
                cross1 += wx * float(targets[1, c, p, k])
            x_p = float(pred[c, pixels[p]])
            s0, dmu0, dsq0, dcr0 = _ssim(mu, sq, float(target_mean[0, c, p]), float(target_sq[0, c, p]), cross0)
            s1, dmu1, dsq1, dcr1 = _ssim(mu, sq, float(target_mean[1, c, p]), float(target_sq[1, c, p]), cross1)
            diff0 = x_p - float(values[0, c, p])
            diff1 = x_p - float(values[1, c, p])
            if not backward:
                losses[0, p] += l1_share * abs(diff0) + ssim_share * (1.0 - s0)
                losses[1, p] += l1_share * abs(diff1) + ssim_share * (1.0 - s1)
                continue
            g0, g1 = float(grad_losses[0, p]), float(grad_losses[1, p])
            grad_pred[c, pixels[p]] += l1_share * (g0 * np.sign(diff0) + g1 * np.sign(diff1))
            # d(1 - S)/dx_k = -(dS/dmu w_k + dS/dsq 2 w_k x_k + dS/dcross w_k y_k)
            a = -ssim_share * (g0 * dmu0 + g1 * dmu1)
            b = -ssim_share * 2.0 * (g0 * dsq0 + g1 * dsq1)
            e0, e1 = -ssim_share * g0 * dcr0, -ssim_share * g1 * dcr1
            for k in range(taps):
                x = float(pred[c, windows[p, k]])
                grad_pred[c, windows[p, k]] += float(weights[k]) * (
                    a + b * x + e0 * float(targets[0, c, p, k]) + e1 * float(targets[1, c, p, k]))


class _ReflectiveWindowLosses(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, windows, pixels, weights, targets, values, target_mean, target_sq, ssim_weight):
        arrays = tuple(t.detach().contiguous().numpy() for t in
                       (pred.reshape(pred.shape[0], -1), windows, pixels, weights, targets, values, target_mean, target_sq))
        losses = np.zeros((2, windows.shape[0]), np.float64)
        _kernel(*arrays, float(ssim_weight), losses, losses, np.zeros((1, 1)), False)
        ctx.arrays, ctx.ssim_weight, ctx.shape, ctx.dtype = arrays, float(ssim_weight), pred.shape, pred.dtype
        return torch.from_numpy(losses).to(pred.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_losses):
        arrays = ctx.arrays
        grad_pred = np.zeros(arrays[0].shape, np.float64)
        _kernel(*arrays, ctx.ssim_weight, grad_losses.detach().to(torch.float64).contiguous().numpy(),
                np.zeros((1, 1)), grad_pred, True)
        return (torch.from_numpy(grad_pred).to(ctx.dtype).reshape(ctx.shape),) + (None,) * 8


def reflective_window_losses(
    pred: Tensor, windows: Tensor, pixels: Tensor, weights: Tensor, targets: Tensor, values: Tensor,
    target_mean: Tensor, target_sq: Tensor, ssim_weight: float,
) -> Tensor:
    r"""Photometric losses of ``pred`` at P pixels against two targets (see the module docstring).

    Args:
        pred: :math:`(C, H, W)` CPU float prediction (the differentiable input).
        windows: :math:`(P, K)` int64 flat indices (into H*W) of each pixel's window taps.
        pixels: :math:`(P,)` int64 flat index of each pixel.
        weights: :math:`(K,)` window weights (summing to 1).
        targets: :math:`(2, C, P, K)` the two targets at the window taps.
        values: :math:`(2, C, P)` the two targets at the pixels.
        target_mean, target_sq: :math:`(2, C, P)` the targets' windowed mean and second moment.
        ssim_weight: :math:`\lambda`, the SSIM share.

    Returns:
        :math:`(2, P)` losses in ``pred``'s dtype, differentiable once w.r.t. ``pred``.

    Example:
        >>> pred = torch.rand(3, 8, 8)
        >>> windows = torch.tensor([[9, 10, 11]]); pixels = torch.tensor([10])
        >>> weights = torch.full((3,), 1 / 3)
        >>> same = pred.reshape(3, -1)[:, windows][None].expand(2, -1, -1, -1)  # targets = pred
        >>> mean = (same * weights).sum(-1); sq = (same * same * weights).sum(-1)
        >>> losses = reflective_window_losses(pred, windows, pixels, weights, same, pred.reshape(3, -1)[:, pixels][None].expand(2, -1, -1),
        ...                                   mean, sq, 0.2)
        >>> bool(losses.abs().max() < 1e-5)  # the target itself: 0 up to float32 rounding
        True
    """
    return _ReflectiveWindowLosses.apply(pred, windows, pixels, weights, targets, values, target_mean, target_sq, ssim_weight)
