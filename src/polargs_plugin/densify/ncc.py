"""Bilateral-weighted NCC of plane hypotheses (Schönberger et al. 2016; COLMAP's cost).

For a reference pixel ``p`` and a plane hypothesis, the window samples ``q = p + o`` (integer
offsets ``o`` on a ``window_step`` grid within ``window_radius``) are read from the reference
grey image at integer pixels and from each source image bilinearly at ``H q~`` (zero outside).
Weights ``w(q) = exp(-|o|^2 / (2 sigma_s^2) - (I(q) - I(p))^2 / (2 sigma_c^2))`` depend only on
the reference, so the reference statistics are precomputed once per pixel. The cost is
``1 - cov / sqrt(var_r var_s)`` clamped to [0, 2], and 2 where either variance is below 1e-5 or
the plane projects behind the source camera.

The homography is applied in factored form (see homography.py):
``H q~ = A (p~ + o~) + b (1 / d + m_xy . o)`` with ``A = K_s R K_ref^-1``, ``b = K_s t`` and
``m = -K_ref^-T n / d_plane`` (so ``m . p~ = 1 / d``); the per-source parts are shared by every
hypothesis.

Two interchangeable backends compute the same numbers: ``"torch"`` (vectorised ``grid_sample``,
CPU and CUDA, the reference) and ``"numba"`` (the parallel CPU kernel of numba_kernels.py, the
same per-window routine the fused PatchMatch search uses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "MAX_COST",
    "MIN_VARIANCE",
    "RefWindows",
    "window_offsets",
    "reference_windows",
    "bilateral_ncc_cost",
    "numba_available",
]

MAX_COST = 2.0
MIN_VARIANCE = 1e-5

try:  # numba is a declared dependency; the torch path stays the reference if it is missing
    import numba as _numba
except ImportError:  # pragma: no cover - exercised only on installations without numba
    _numba = None


def numba_available() -> bool:
    """Whether the numba backend can run."""
    return _numba is not None


@dataclass
class RefWindows:
    """Precomputed reference windows for every pixel (flattened row-major, ``P = H * W``).

    Attributes:
        values: (P, Q) grey values at the window samples.
        weights: (P, Q) bilateral weights normalised to sum to one.
        mean: (P,) weighted mean; var: (P,) weighted variance.
    """

    values: Tensor
    weights: Tensor
    mean: Tensor
    var: Tensor


def window_offsets(radius: int, step: int, device=None) -> Tensor:
    """(Q, 2) integer (x, y) window offsets ``range(-radius, radius + 1, step)`` squared."""
    if radius < 1 or step < 1:
        raise ValueError(f"window radius and step must be >= 1, got {radius}, {step}")
    r = torch.arange(-radius, radius + 1, step, device=device, dtype=torch.float32)
    oy, ox = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([ox.reshape(-1), oy.reshape(-1)], dim=-1)


def reference_windows(
    gray: Tensor, offsets: Tensor, sigma_spatial: float, sigma_color: float
) -> RefWindows:
    """Reference window values, bilateral weights and weighted statistics for all pixels.

    Args:
        gray: (H, W) reference grey image in [0, 1].
        offsets: (Q, 2) integer offsets from :func:`window_offsets`.
        sigma_spatial: spatial sigma in pixels (the window radius when <= 0).
        sigma_color: intensity sigma.

    Returns:
        RefWindows over ``H * W`` pixels; windows leaving the image replicate the border.
    """
    height, width = gray.shape
    radius = int(offsets.abs().max().item())
    if sigma_spatial <= 0:
        sigma_spatial = float(radius)
    padded = F.pad(gray[None, None], (radius,) * 4, mode="replicate")[0, 0]
    v, u = torch.meshgrid(
        torch.arange(height, device=gray.device), torch.arange(width, device=gray.device), indexing="ij"
    )
    ox = offsets[:, 0].long()
    oy = offsets[:, 1].long()
    rows = v.reshape(-1, 1) + radius + oy
    cols = u.reshape(-1, 1) + radius + ox
    values = padded[rows, cols]
    centre = gray.reshape(-1, 1)
    spatial = (offsets**2).sum(-1) / (2 * sigma_spatial**2)
    weights = torch.exp(-spatial - (values - centre) ** 2 / (2 * sigma_color**2))
    weights = weights / weights.sum(-1, keepdim=True)
    mean = (weights * values).sum(-1)
    var = (weights * values**2).sum(-1) - mean**2
    return RefWindows(values.contiguous(), weights.contiguous(), mean, var)


def bilateral_ncc_cost(
    sources: Tensor,
    A: Tensor,
    b: Tensor,
    pixels: Tensor,
    inv_depth: Tensor,
    m_xy: Tensor,
    offsets: Tensor,
    ref_values: Tensor,
    ref_weights: Tensor,
    ref_mean: Tensor,
    ref_var: Tensor,
    *,
    backend: str = "auto",
    chunk_elements: int = 1 << 22,
) -> Tensor:
    """Bilateral NCC cost of ``M`` plane hypotheses at ``P`` pixels against ``S`` sources.

    Args:
        sources: (S, Hs, Ws) source grey images.
        A: (S, 3, 3) ``K_s R K_ref^-1``; b: (S, 3) ``K_s t`` (pixel units, centres at +0.5).
        pixels: (P, 2) reference pixel centres (u + 0.5, v + 0.5).
        inv_depth: (P, M) ``1 / depth`` of each hypothesis.
        m_xy: (P, M, 2) the x, y components of ``m = -K_ref^-T n / d_plane``.
        offsets: (Q, 2) window offsets.
        ref_values, ref_weights: (P, Q); ref_mean, ref_var: (P,) from :class:`RefWindows`.
        backend: "torch", "numba" (CPU only) or "auto" (numba on CPU when available).
        chunk_elements: bound on P * M * S * Q per torch chunk (memory).

    Returns:
        (P, M, S) costs in [0, 2].
    """
    if backend == "auto":
        backend = "numba" if sources.device.type == "cpu" and numba_available() else "torch"
    if backend == "numba":
        if sources.device.type != "cpu":
            raise ValueError("the numba NCC backend runs on CPU tensors only")
        return _cost_numba(sources, A, b, pixels, inv_depth, m_xy, offsets, ref_values,
                           ref_weights, ref_mean, ref_var)
    if backend != "torch":
        raise ValueError(f"unknown NCC backend '{backend}' (torch, numba, auto)")
    num_p, num_m = inv_depth.shape
    per_pixel = num_m * sources.shape[0] * offsets.shape[0]
    step = max(1, chunk_elements // max(per_pixel, 1))
    out = [
        _cost_torch(sources, A, b, pixels[i : i + step], inv_depth[i : i + step],
                    m_xy[i : i + step], offsets, ref_values[i : i + step],
                    ref_weights[i : i + step], ref_mean[i : i + step], ref_var[i : i + step])
        for i in range(0, num_p, step)
    ]
    if not out:
        return sources.new_zeros((0, num_m, sources.shape[0]))
    return torch.cat(out)


def _cost_torch(sources, A, b, pixels, inv_depth, m_xy, offsets, r_val, r_w, r_mean, r_var):
    num_s, height, width = sources.shape
    ones = torch.ones_like(pixels[:, :1])
    base = torch.einsum("sij,pj->psi", A, torch.cat([pixels, ones], -1))  # (P, S, 3)
    a_off = torch.einsum("sij,qj->sqi", A[:, :, :2], offsets)  # (S, Q, 3)
    k = inv_depth[..., None] + torch.einsum("pmj,qj->pmq", m_xy, offsets)  # (P, M, Q)
    proj = (
        base[:, None, :, None, :]
        + a_off[None, None]
        + b[None, None, :, None, :] * k[:, :, None, :, None]
    )  # (P, M, S, Q, 3)
    z = proj[..., 2]
    behind = (z <= 1e-8).any(-1)  # (P, M, S)
    z = z.clamp_min(1e-8)
    gx = proj[..., 0] / z * (2.0 / width) - 1.0
    gy = proj[..., 1] / z * (2.0 / height) - 1.0
    grid = torch.stack([gx, gy], -1).permute(2, 0, 1, 3, 4)  # (S, P, M, Q, 2)
    num_p, num_m, num_q = k.shape
    grid = grid.reshape(num_s, num_p * num_m, num_q, 2)
    samples = F.grid_sample(
        sources[:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False
    )[:, 0].reshape(num_s, num_p, num_m, num_q).permute(1, 2, 0, 3)  # (P, M, S, Q)
    w = r_w[:, None, None, :]
    s_mean = (w * samples).sum(-1)
    s_var = (w * samples**2).sum(-1) - s_mean**2
    cov = (w * samples * r_val[:, None, None, :]).sum(-1) - s_mean * r_mean[:, None, None]
    rv = r_var[:, None, None]
    ok = (s_var >= MIN_VARIANCE) & (rv >= MIN_VARIANCE) & ~behind
    cost = 1.0 - cov / torch.sqrt((rv * s_var).clamp_min(1e-12))
    return torch.where(ok, cost.clamp(0.0, MAX_COST), torch.full_like(cost, MAX_COST))


def _cost_numba(sources, A, b, pixels, inv_depth, m_xy, offsets, r_val, r_w, r_mean, r_var):
    import numpy as np

    from polargs_plugin.densify.numba_kernels import ncc_kernel

    num_p, num_m = inv_depth.shape
    out = np.empty((num_p, num_m, sources.shape[0]), dtype=np.float32)
    if num_p == 0:
        return torch.from_numpy(out)
    radius, step = _grid_of(offsets)
    # two zero pixels around each source let the kernel clamp instead of bounds-checking taps
    padded = F.pad(sources.float(), (2, 2, 2, 2))
    f32 = lambda t: t.detach().to(torch.float32).contiguous().numpy()  # noqa: E731
    f64 = lambda t: t.detach().to(torch.float64).contiguous().numpy()  # noqa: E731
    ncc_kernel(f32(padded), f64(A), f64(b), f64(pixels), f64(inv_depth), f64(m_xy), radius, step,
               f32(r_w), f32(r_w * (r_val - r_mean[:, None])), f32(r_var), out)
    return torch.from_numpy(out)


def _grid_of(offsets: Tensor) -> tuple[int, int]:
    """(radius, step) of offsets made by :func:`window_offsets` (the numba kernel walks that grid)."""
    radius = int(offsets.abs().max().item())
    step = int(offsets[1, 0].item() - offsets[0, 0].item()) if offsets.shape[0] > 1 else 1
    if step < 1 or not torch.equal(offsets.cpu().float(), window_offsets(radius, step)):
        raise ValueError("the numba NCC backend needs offsets from window_offsets(radius, step)")
    return radius, step
