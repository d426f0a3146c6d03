"""Fused SSIM map (Gaussian window, sigma 1.5, 'reflect' same padding) with a hand-written backward.

The values are those of ``kornia.metrics.ssim(img1, img2, window_size)`` (max_val 1, eps 1e-12,
padding 'same'), the SSIM of vanilla 3DGS's colour loss, up to float rounding:

.. math::

    \\text{SSIM}(x, y) = \\frac{(2\\mu_x\\mu_y + c_1)(2\\sigma_{xy} + c_2)}
    {(\\mu_x^2 + \\mu_y^2 + c_1)(\\sigma_x^2 + \\sigma_y^2 + c_2) + \\epsilon}

with :math:`c_1 = 0.01^2`, :math:`c_2 = 0.03^2`, :math:`\\epsilon = 10^{-12}`, the means and moments
windowed by the separable sampled Gaussian (``window_size`` taps, sigma 1.5, normalized to sum 1)
after 'reflect' padding (mirrored about the edge pixel, not repeating it) by ``window_size // 2``.

On the CPU (float32 / float64) one compiled Numba pass per output row filters the five moments
:math:`x, y, x^2, y^2, xy` (vertical taps, then horizontal ones on the row) and forms the SSIM
and the four per-pixel partial derivatives of SSIM w.r.t. the moments; the backward pass applies
the adjoint of the reflect-padded separable filter to (incoming gradient x partials), again one
row at a time, and combines them into the gradient of either image. No intermediate image is
kept by autograd. Elsewhere (CUDA) the same map is computed by torch (separable ``conv2d``,
autograd).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from polargs_plugin.threads import numba_path, numba_scheduling

__all__ = [
    "C1",
    "C2",
    "EPS",
    "SIGMA",
    "gaussian_kernel1d",
    "gaussian_filter",
    "ssim_from_moments",
    "ssim_map",
]

SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2
EPS = 1e-12


def gaussian_kernel1d(window_size: int, sigma: float = SIGMA, *, device=None, dtype=None) -> Tensor:
    """Sampled Gaussian :math:`\\exp(-n^2 / 2\\sigma^2)`, n = -r..r, normalized to sum 1 (kornia's
    ``get_gaussian_kernel1d``).

    Args:
        window_size: odd number of taps.
        sigma: standard deviation in pixels.
        device, dtype: of the result (default dtype when ``None``).

    Returns:
        :math:`(\\text{window\\_size},)` weights.
    """
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be odd and positive, got {window_size}")
    dtype = dtype or torch.get_default_dtype()
    compute = torch.float64 if dtype == torch.float64 else torch.float32
    offsets = torch.arange(window_size, dtype=compute) - window_size // 2
    weights = torch.exp(-offsets.pow(2.0) / (2 * sigma**2))
    return (weights / weights.sum()).to(device=device, dtype=dtype)


def gaussian_filter(x: Tensor, kernel: Tensor) -> Tensor:
    """Separable Gaussian-windowed mean of every :math:`(H, W)` plane, 'reflect' same padding (torch,
    differentiable; the filter :func:`ssim_map` uses).

    Args:
        x: :math:`(*, H, W)` with H, W > ``len(kernel) // 2``.
        kernel: :math:`(k,)` odd number of taps, applied along W then H.

    Returns:
        :math:`(*, H, W)`.
    """
    shape = x.shape
    radius = kernel.shape[-1] // 2
    planes = x.reshape(-1, 1, *shape[-2:])
    weight = kernel.to(x.dtype).reshape(1, 1, 1, -1)
    planes = F.conv2d(F.pad(planes, [radius, radius, 0, 0], mode="reflect"), weight)
    planes = F.conv2d(F.pad(planes, [0, 0, radius, radius], mode="reflect"), weight.reshape(1, 1, -1, 1))
    return planes.reshape(shape)


def ssim_from_moments(mu1: Tensor, sq1: Tensor, mu2: Tensor, sq2: Tensor, cross: Tensor) -> Tensor:
    """SSIM from windowed means ``mu``, second moments ``sq`` and cross moment, in kornia's order of
    operations (max_val 1, eps 1e-12). Any broadcastable shapes."""
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    num = (2.0 * mu1_mu2 + C1) * (2.0 * (cross - mu1_mu2) + C2)
    den = (mu1_sq + mu2_sq + C1) * ((sq1 - mu1_sq) + (sq2 - mu2_sq) + C2)
    return num / (den + EPS)


def _ssim_torch(img1: Tensor, img2: Tensor, kernel: Tensor) -> Tensor:
    """(N, H, W) SSIM map by torch (autograd): the five moments in one filtering call."""
    moments = gaussian_filter(torch.stack([img1, img2, img1 * img1, img2 * img2, img1 * img2]), kernel)
    mu1, mu2, sq1, sq2, cross = moments.unbind(0)
    return ssim_from_moments(mu1, sq1, mu2, sq2, cross)


# ---------------------------------------------------------------------------------------------
# CPU: Numba kernels. Planes are (N, H, W) contiguous; one prange task per output row.
# ---------------------------------------------------------------------------------------------


@numba.njit(inline="always")
def _reflect(index, size):
    """Index mirrored into [0, size) without repeating the edge (needs |overshoot| < size)."""
    if index < 0:
        return -index
    if index > size - 1:
        return 2 * (size - 1) - index
    return index


@numba.njit(inline="always")
def _filter_row(row, pad, weights, radius, out):
    """``out`` = 'reflect'-padded correlation of ``row`` with ``weights`` (``pad`` is scratch of
    length W + 2 radius)."""
    width = row.shape[0]
    for q in range(width + 2 * radius):
        pad[q] = row[_reflect(q - radius, width)]
    out[:] = 0.0
    for t in range(weights.shape[0]):
        wt = weights[t]
        for j in range(width):
            out[j] += wt * pad[j + t]


@numba.njit(inline="always")
def _filter_row_adjoint(row, pad, acc, flipped, radius, out):
    """Adjoint of :func:`_filter_row`: ``out`` = transpose of (reflect-pad then correlate) applied to
    ``row``. ``pad`` and ``acc`` are scratch of lengths W + 4 radius and W + 2 radius, ``flipped``
    the reversed weights."""
    width = row.shape[0]
    pad[:] = 0.0
    for j in range(width):
        pad[2 * radius + j] = row[j]
    # Gradient of the padded row at padded index q (q = 0 .. W + 2r - 1):
    # sum_t w[t] row[q - t] = sum_s w[2r - s] pad[q + s].
    acc[:] = 0.0
    for s in range(flipped.shape[0]):
        wt = flipped[s]
        for q in range(width + 2 * radius):
            acc[q] += wt * pad[q + s]
    for j in range(width):
        out[j] = acc[j + radius]
    for q in range(radius):  # padded q held row[r - q], q + W + r held row[W - 2 - q]
        out[radius - q] += acc[q]
        out[width - 2 - q] += acc[width + radius + q]


@numba.njit(parallel=True, cache=True, fastmath=False, error_model="numpy")
def _forward_kernel(x, y, weights, c1, c2, eps, ssim, coef, with_coef):
    """SSIM map of the planes ``x``, ``y`` (N, H, W) into ``ssim``; with ``with_coef`` also the
    partial derivatives of SSIM w.r.t. (mu_x, E[x^2] and E[y^2], E[xy], mu_y) into ``coef`` (4, N, H, W)."""
    planes, height, width = x.shape
    taps = weights.shape[0]
    radius = taps // 2
    for task in numba.prange(planes * height):
        p = task // height
        i = task - p * height
        # Vertical taps of the five moments at row i.
        v = np.zeros((5, width), x.dtype)
        for t in range(taps):
            src = _reflect(i + t - radius, height)
            wt = weights[t]
            xr = x[p, src]
            yr = y[p, src]
            for j in range(width):
                a = xr[j]
                b = yr[j]
                v[0, j] += wt * a
                v[1, j] += wt * b
                v[2, j] += wt * (a * a)
                v[3, j] += wt * (b * b)
                v[4, j] += wt * (a * b)
        # Horizontal taps, row by row.
        pad = np.empty(width + 2 * radius, x.dtype)
        m = np.empty((5, width), x.dtype)
        for q in range(5):
            _filter_row(v[q], pad, weights, radius, m[q])
        for j in range(width):
            mu1 = m[0, j]
            mu2 = m[1, j]
            mu1_sq = mu1 * mu1
            mu2_sq = mu2 * mu2
            mu1_mu2 = mu1 * mu2
            a1 = 2.0 * mu1_mu2 + c1
            a2 = 2.0 * (m[4, j] - mu1_mu2) + c2
            b1 = mu1_sq + mu2_sq + c1
            b2 = (m[2, j] - mu1_sq) + (m[3, j] - mu2_sq) + c2
            den = b1 * b2 + eps
            value = (a1 * a2) / den
            ssim[p, i, j] = value
            if with_coef:
                # S = A1 A2 / D: dS/dA1 = A2/D, dS/dA2 = A1/D, dS/dB1 = -S B2/D, dS/dB2 = -S B1/D.
                inv = 1.0 / den
                da = a2 - a1
                db = value * (b1 - b2)
                coef[0, p, i, j] = 2.0 * inv * (mu2 * da + mu1 * db)  # d/d mu_x
                coef[1, p, i, j] = -value * b1 * inv  # d/d E[x^2] = d/d E[y^2]
                coef[2, p, i, j] = 2.0 * a1 * inv  # d/d E[xy]
                coef[3, p, i, j] = 2.0 * inv * (mu1 * da + mu2 * db)  # d/d mu_y


@numba.njit(inline="always")
def _add_rows(v, grad_row, coef, p, i, count, wt):
    for c in range(count):
        cr = coef[c, p, i]
        for j in range(grad_row.shape[0]):
            v[c, j] += wt * (grad_row[j] * cr[j])


@numba.njit(parallel=True, cache=True, fastmath=False, error_model="numpy")
def _backward_kernel(x, y, grad, coef, weights, grad_x, grad_y, want_x, want_y):
    """Gradients of sum(grad * SSIM) w.r.t. the planes ``x`` and/or ``y`` (N, H, W).

    The moment maps are filtered images, so their gradient is the filter's adjoint applied to
    grad * partial derivative: vertical adjoint (each source row i reaches row j through its
    taps, reflections included) then horizontal adjoint on the row."""
    planes, height, width = x.shape
    taps = weights.shape[0]
    radius = taps // 2
    flipped = weights[::-1].copy()
    count = 4 if want_y else 3
    for task in numba.prange(planes * height):
        p = task // height
        j = task - p * height
        v = np.zeros((count, width), x.dtype)
        for t in range(taps):
            wt = weights[t]
            # Output row i reads padded row i + t - r; padded rows j, -j (j > 0) and
            # 2 (H - 1) - j (j < H - 1) are input row j.
            i = j + radius - t
            if i >= 0 and i < height:
                _add_rows(v, grad[p, i], coef, p, i, count, wt)
            if j > 0:
                i = radius - t - j
                if i >= 0 and i < height:
                    _add_rows(v, grad[p, i], coef, p, i, count, wt)
            if j < height - 1:
                i = 2 * (height - 1) - j + radius - t
                if i >= 0 and i < height:
                    _add_rows(v, grad[p, i], coef, p, i, count, wt)
        pad = np.empty(width + 4 * radius, x.dtype)
        acc = np.empty(width + 2 * radius, x.dtype)
        h = np.empty((count, width), x.dtype)
        for c in range(count):
            _filter_row_adjoint(v[c], pad, acc, flipped, radius, h[c])
        xr = x[p, j]
        yr = y[p, j]
        if want_x:
            out = grad_x[p, j]
            for col in range(width):
                out[col] = h[0, col] + 2.0 * xr[col] * h[1, col] + yr[col] * h[2, col]
        if want_y:
            out = grad_y[p, j]
            for col in range(width):
                out[col] = h[3, col] + 2.0 * yr[col] * h[1, col] + xr[col] * h[2, col]


class _FusedSSIM(torch.autograd.Function):
    """(N, H, W) float32/float64 CPU planes -> (N, H, W) SSIM map; backward by hand."""

    @staticmethod
    def forward(ctx, img1: Tensor, img2: Tensor, kernel: Tensor) -> Tensor:
        x = img1.detach().contiguous().numpy()
        y = img2.detach().contiguous().numpy()
        weights = kernel.detach().to(img1.dtype).contiguous().numpy()
        with_coef = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        ssim = np.empty_like(x)
        coef = np.empty((4, *x.shape) if with_coef else (4, 0, 0, 0), x.dtype)
        with numba_scheduling():
            _forward_kernel(x, y, weights, C1, C2, EPS, ssim, coef, with_coef)
        if with_coef:
            ctx.arrays = (x, y, coef, weights)
            ctx.dtype = img1.dtype
        return torch.from_numpy(ssim)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        want_x, want_y = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        x, y, coef, weights = ctx.arrays
        g = grad.to(ctx.dtype).contiguous().numpy()
        grad_x = np.empty_like(x) if want_x else np.empty((0, 0, 0), x.dtype)
        grad_y = np.empty_like(x) if want_y else np.empty((0, 0, 0), x.dtype)
        with numba_scheduling():
            _backward_kernel(x, y, g, coef, weights, grad_x, grad_y, want_x, want_y)
        return (torch.from_numpy(grad_x) if want_x else None, torch.from_numpy(grad_y) if want_y else None, None)


def ssim_map(img1: Tensor, img2: Tensor, window_size: int = 11) -> Tensor:
    r"""Per-pixel, per-channel SSIM of two images (kornia's ``metrics.ssim`` with max_val 1,
    eps 1e-12, 'same' padding), differentiable w.r.t. both.

    Args:
        img1: :math:`(*, H, W)`, e.g. :math:`(B, C, H, W)` or :math:`(C, H, W)`, float; H and W must
            exceed ``window_size // 2`` ('reflect' padding).
        img2: same shape as ``img1``.
        window_size: odd number of Gaussian taps (sigma 1.5 whatever the size).

    Returns:
        :math:`(*, H, W)` SSIM map in the promoted dtype of the inputs (float32 for half or integer
        inputs, which are computed in float32), 1 - O(eps) where ``img1 == img2``.

    Note:
        On CPU float32/float64 tensors the compiled path runs (once differentiable: no double
        backward); on other devices, under ``torch.func`` transforms or tracing, torch's
        separable ``conv2d`` with autograd.

    Example:
        >>> img1, img2 = torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
        >>> ssim_map(img1, img2, 11).shape
        torch.Size([1, 3, 16, 16])
    """
    if not isinstance(img1, Tensor) or not isinstance(img2, Tensor):
        raise TypeError("img1 and img2 must be tensors")
    if img1.shape != img2.shape:
        raise ValueError(f"img1 {tuple(img1.shape)} and img2 {tuple(img2.shape)} differ in shape")
    if img1.ndim < 2:
        raise ValueError(f"expected (*, H, W) images, got shape {tuple(img1.shape)}")
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be odd and positive, got {window_size}")
    height, width = img1.shape[-2:]
    if window_size // 2 >= min(height, width):
        raise ValueError(f"'reflect' padding needs H, W > window_size // 2, got {height}x{width}, window {window_size}")
    dtype = torch.promote_types(img1.dtype, img2.dtype)
    if dtype not in (torch.float32, torch.float64):
        dtype = torch.float32
    shape = img1.shape
    x = img1.to(dtype).reshape(-1, height, width)
    y = img2.to(dtype).reshape(-1, height, width)
    kernel = gaussian_kernel1d(window_size, SIGMA, device=x.device, dtype=dtype)
    if numba_path(x) and x.numel() > 0:
        out = _FusedSSIM.apply(x, y, kernel)
    else:
        out = _ssim_torch(x, y, kernel)
    return out.reshape(shape)

