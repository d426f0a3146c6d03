"""Colour Refinement Maps (CRMs): colour targets for reflective pixels.

- ``I_diff = (s0 - (Imax - Imin)) / 2`` per channel, for specular pixels: the polarized part of the
  light (mostly specular) removed, in the units of the training colour s0 / 2.
- ``I_chro = rho_d * I_prop / (sum_c I_prop + mean_c I_diff)`` for overexposed pixels, where
  ``I_prop`` is ``I_diff`` propagated from nearby non-reflective *donor* pixels whose features are
  close (Mahalanobis distance below a threshold) within a bounded window.

Feature vector and rho_d: docs/choices.md. Everything is vectorised: the propagation gathers the
window of every target pixel at once (chunked to bound memory), no per-pixel Python loop.
"""

from __future__ import annotations

import torch
from torch import Tensor


__all__ = ["diffuse_map", "whiten_features", "propagate", "chromaticity_map"]

# Gathered neighbour values per chunk (target pixels x window x channels) kept under this count.
_CHUNK_ELEMENTS = 1 << 24
_COVARIANCE_SAMPLES = 1 << 18


def diffuse_map(stokes: Tensor) -> Tensor:
    r"""Specular-free colour :math:`I_{diff} = (s_0 - (I_{max} - I_{min})) / 2 = I_{min}`, clamped at 0.

    Args:
        stokes: :math:`(*, 3, C, H, W)` Stokes (s0, s1, s2).

    Returns:
        :math:`(*, C, H, W)` I_diff, in the units of the training colour s0 / 2.

    Example:
        >>> diffuse_map(torch.tensor([1.0, 0.3, 0.4]).reshape(3, 1, 1, 1)).flatten()
        tensor([0.2500])
    """
    s0, s1, s2 = stokes.unbind(dim=-4)
    return ((s0 - torch.hypot(s1, s2)) * 0.5).clamp_(min=0.0)  # hypot = Imax - Imin


def whiten_features(features: Tensor, sample_mask: Tensor, ridge: float = 1e-4) -> Tensor:
    r"""Map features to a space where Euclidean distance is the Mahalanobis distance.

    The covariance is estimated over the pixels of ``sample_mask`` (plus ``ridge`` on the diagonal,
    so that a constant feature, like PRI of a mono image, stays finite); with fewer than two samples
    the identity is used.

    Args:
        features: :math:`(F, H, W)` per-pixel feature vectors.
        sample_mask: :math:`(1, H, W)` bool pixels that define the distribution.
        ridge: diagonal regulariser.

    Returns:
        :math:`(F, H, W)` whitened features :math:`L^{-1} f` with :math:`\Sigma = L L^T`.

    Example:
        >>> f = torch.tensor([[[0.0, 2.0]]])
        >>> whiten_features(f, torch.ones(1, 1, 2, dtype=torch.bool), ridge=0.0).flatten()  # var 2
        tensor([0.0000, 1.4142])
    """
    count = int(features.shape[0])
    flat = features.reshape(count, -1)
    samples = flat[:, sample_mask.reshape(-1)]
    if samples.shape[1] < 2:
        return features
    # A strided subset estimates a 2x2..FxF covariance as well as millions of samples would.
    samples = samples[:, :: max(1, samples.shape[1] // _COVARIANCE_SAMPLES)].double()
    cov = torch.cov(samples).reshape(count, count)
    cov = cov + ridge * torch.eye(count, dtype=cov.dtype, device=cov.device)
    inverse_chol = torch.linalg.inv(torch.linalg.cholesky(cov)).to(features.dtype)  # L^-1, F x F
    return (inverse_chol @ flat).reshape(features.shape)


def propagate(
    values: Tensor,
    features: Tensor,
    target_mask: Tensor,
    donor_mask: Tensor,
    radius: int,
    threshold: float,
    components: Tensor | None = None,
    step: int = 1,
) -> tuple[Tensor, Tensor]:
    r"""Fill target pixels with the weighted mean of donor values of similar features.

    For a target pixel p and a donor q in the (2r+1)x(2r+1) window around p (sampled every
    ``step`` pixels along each axis, centre included), with
    :math:`d = \lVert f_p - f_q \rVert` (features already whitened, so ``d`` is the Mahalanobis
    distance), q contributes with weight :math:`\exp(-d^2/2)` if :math:`d <` ``threshold``.
    ``components`` lets a target pixel compare on some whitened components only; with Cholesky
    whitening, keeping the leading ones gives the Mahalanobis distance of the leading raw features.

    Args:
        values: :math:`(C, H, W)` values to propagate (I_diff).
        features: :math:`(F, H, W)` whitened features (see :func:`whiten_features`).
        target_mask: :math:`(1, H, W)` bool pixels to fill.
        donor_mask: :math:`(1, H, W)` bool pixels allowed to give their value.
        radius: half window size r in pixels.
        threshold: Mahalanobis distance below which a donor counts.
        components: optional :math:`(F, H, W)` bool, the components each target pixel compares on
            (default all).
        step: window sampling stride (1 = every pixel of the window).

    Returns:
        ``(filled, valid)``: :math:`(C, H, W)` propagated values (0 outside ``valid``) and
        :math:`(1, H, W)` bool target pixels with at least one accepted donor.

    Example:
        >>> v = torch.tensor([[[0.2, 0.0, 0.6]]])
        >>> f = torch.zeros(1, 1, 3)
        >>> filled, valid = propagate(v, f, v == 0, v > 0, radius=1, threshold=0.8)
        >>> filled.flatten()
        tensor([0.0000, 0.4000, 0.0000])
    """
    if radius < 0 or step < 1:
        raise ValueError(f"need radius >= 0 and step >= 1, got radius {radius}, step {step}")
    filled = torch.zeros_like(values)
    valid = torch.zeros_like(target_mask)
    box = _target_box(target_mask, radius)
    if box is None:
        return filled, valid
    height, width = values.shape[-2:]
    top, bottom, left, right = box
    if (bottom - top, right - left) != (height, width):
        # Only the targets' bounding box grown by the radius can matter: work on that crop.
        crop = (slice(None), slice(top, bottom), slice(left, right))
        parts = propagate(
            values[crop], features[crop], target_mask[crop], donor_mask[crop], radius, threshold,
            None if components is None else components[crop], step,
        )
        filled[crop], valid[crop] = parts
        return filled, valid
    targets = target_mask.reshape(-1).nonzero().squeeze(1)
    table = _padded_table(values, features, donor_mask, radius)
    padded_width = width + 2 * radius
    half = radius // step * step
    steps = torch.arange(-half, half + 1, step, device=values.device)
    offsets = (steps[:, None] * padded_width + steps[None, :]).reshape(-1)  # (K,)
    centres = (targets // width + radius) * padded_width + targets % width + radius
    num_features = features.shape[0]
    target_components = None
    if components is not None:
        target_components = components.reshape(num_features, -1)[:, targets].T.to(values.dtype)  # (T, F)
    _gather_donors(table, offsets, centres, targets, target_components, threshold, filled, valid)
    return filled, valid


def _target_box(target_mask: Tensor, radius: int) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right), end exclusive, of the target pixels' bounding box grown by
    ``radius`` and clipped to the image; None when there is no target."""
    height, width = target_mask.shape[-2:]
    rows = target_mask[0].any(dim=1).nonzero()
    if rows.numel() == 0:
        return None
    cols = target_mask[0].any(dim=0).nonzero()
    top, bottom = max(int(rows[0]) - radius, 0), min(int(rows[-1]) + radius + 1, height)
    left, right = max(int(cols[0]) - radius, 0), min(int(cols[-1]) + radius + 1, width)
    return top, bottom, left, right


def _padded_table(values: Tensor, features: Tensor, donor_mask: Tensor, radius: int) -> Tensor:
    """One pixel-major table (Hp * Wp, F + C + 1) of features, values and donor flag, padded by
    ``radius`` (padding = not a donor): a window is then a fixed set of flat offsets, and one row
    gather fetches features, values and donor flag together."""
    height, width = values.shape[-2:]
    planes = [*features, *values, donor_mask[0]]
    table = values.new_zeros(height + 2 * radius, width + 2 * radius, len(planes))
    for index, plane in enumerate(planes):
        table[radius : radius + height, radius : radius + width, index] = plane
    return table.reshape(-1, len(planes))


def _gather_donors(
    table: Tensor,
    offsets: Tensor,
    centres: Tensor,
    targets: Tensor,
    target_components: Tensor | None,
    threshold: float,
    filled: Tensor,
    valid: Tensor,
) -> None:
    """Fill ``filled`` (C, H, W) and ``valid`` (1, H, W) at the flat pixels ``targets`` from
    their windows, chunk by chunk of targets (memory bounded by :data:`_CHUNK_ELEMENTS`).

    ``table`` is :func:`_padded_table`'s, ``offsets`` (K,) the window's flat offsets in it,
    ``centres`` (T,) the targets' rows in it, ``target_components`` (T, F) or None the components
    each target compares on.
    """
    channels = filled.shape[0]
    num_features = table.shape[1] - channels - 1
    threshold_sq = threshold * threshold
    window = offsets.numel()
    chunk = max(1, _CHUNK_ELEMENTS // (window * table.shape[1]))
    out_flat = filled.reshape(channels, -1)
    valid_flat = valid.reshape(-1)
    for start in range(0, targets.numel(), chunk):
        pixels = targets[start : start + chunk]  # (M,)
        centre = centres[start : start + chunk]
        rows = table.index_select(0, (centre[:, None] + offsets[None]).reshape(-1))
        rows = rows.reshape(pixels.numel(), window, -1)  # (M, K, F + C + 1)
        diff = rows[..., :num_features] - table[centre, None, :num_features]
        if target_components is not None:
            diff = diff * target_components[start : start + chunk, None]
        dist_sq = (diff * diff).sum(dim=-1)  # (M, K)
        weight = torch.exp(-0.5 * dist_sq) * ((dist_sq < threshold_sq) & (rows[..., -1] > 0))
        total = weight.sum(dim=1)  # (M,)
        weighted = torch.einsum("mk,mkc->cm", weight, rows[..., num_features:-1])
        out_flat[:, pixels] = weighted / total.clamp_min(torch.finfo(total.dtype).tiny)
        valid_flat[pixels] = total > 0


def chromaticity_map(i_prop: Tensor, i_diff: Tensor, rho_d: float | None = None) -> Tensor:
    r""":math:`I_{chro} = \rho_d\, I_{prop} / (\sum_c I_{prop} + \operatorname{mean}_c I_{diff})`.

    ``rho_d=None`` (default, docs/choices.md) sets :math:`\rho_d` per pixel to the denominator, so
    that the target keeps the donors' colour and brightness (:math:`I_{chro} = I_{prop}`): the
    donors are the only unclipped colour evidence at an overexposed pixel. A number gives the
    paper's normalised chromaticity scaled by that constant. Pixels with a zero denominator get 0.

    Args:
        i_prop: :math:`(*, C, H, W)` propagated diffuse colour.
        i_diff: :math:`(*, C, H, W)` the pixel's own I_diff.
        rho_d: constant brightness, or ``None`` for the brightness-preserving choice.

    Returns:
        :math:`(*, C, H, W)` I_chro.

    Example:
        >>> p = torch.tensor([0.4, 0.2, 0.2]).reshape(3, 1, 1)
        >>> chromaticity_map(p, torch.full((3, 1, 1), 0.2), rho_d=1.0).flatten()
        tensor([0.4000, 0.2000, 0.2000])
    """
    denominator = i_prop.sum(dim=-3, keepdim=True) + i_diff.mean(dim=-3, keepdim=True)
    positive = denominator > 0
    safe = torch.where(positive, denominator, torch.ones_like(denominator))
    rho = safe if rho_d is None else torch.full_like(safe, float(rho_d))
    return torch.where(positive, rho * i_prop / safe, torch.zeros_like(i_prop))
