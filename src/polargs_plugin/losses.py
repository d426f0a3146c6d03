"""PolarGS losses: L = L_c + alpha L_n + beta L_dn + gamma L_scale, L_c = L_non + lambda_ref L_ref.

Photometric terms are (1 - lambda) L1 + lambda (1 - SSIM) per pixel (vanilla 3DGS's colour loss:
kornia's SSIM, 11x11 Gaussian window sigma 1.5, 'reflect' same padding, computed by the fused
:func:`polargs_plugin.ssim.ssim_map`, compiled with a hand-written backward on the CPU), summed
over the masked pixels and divided by the image's pixel count H*W. That normalisation makes
masked terms add up: the plain colour loss over the whole image equals its part on the
reflective pixels plus L_non, which is what lets :class:`~polargs_plugin.hooks.PolarHooks` swap
the target on reflective pixels only.

Every loss is finite with finite gradients on empty masks, zero opacity, zero intensity and zero
vectors (no 0/0, no sqrt or normalisation at 0).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from polargs_plugin.depth_normal import depth_normal_loss_fused
from polargs_plugin.optics.single_view import SingleViewNormals
from polargs_plugin.reflective_window import reflective_window_losses
from polargs_plugin.scale_flatten import scale_loss_fused
from polargs_plugin.ssim import gaussian_kernel1d, ssim_from_moments, ssim_map
from polargs_plugin.threads import numba_path

__all__ = [
    "photometric_loss_map",
    "photometric_loss",
    "reflective_loss",
    "mask_box",
    "ReflectiveTargets",
    "reflective_replacement",
    "normal_loss",
    "polar_normal_loss",
    "normals_within",
    "depth_to_points",
    "normal_from_depth",
    "depth_normal_loss",
    "scale_loss",
    "safe_normalize",
]

_SSIM_WINDOW = 11


def safe_normalize(vectors: Tensor, dim: int = -3, eps: float = 1e-12) -> Tensor:
    """Unit vectors along ``dim``; zero vectors stay zero with a finite gradient.

    Args:
        vectors: :math:`(*, 3, H, W)` (any shape with ``dim`` the vector axis).
        dim: vector axis.
        eps: floor on the squared norm.

    Returns:
        Same shape, unit length where the squared norm exceeds ``eps``.
    """
    return vectors * torch.rsqrt((vectors * vectors).sum(dim=dim, keepdim=True).clamp_min(eps))


def _loss_maps(pred: Tensor, targets: Tensor, ssim_weight: float) -> Tensor:
    """(B, 1, H, W) per-pixel photometric loss of one (C, H, W) prediction against B targets."""
    l1 = (pred[None] - targets).abs().mean(dim=1, keepdim=True)
    if ssim_weight == 0:
        return l1
    # 'same' padding needs H, W > window // 2: shrink the window on tiny images.
    window = min(_SSIM_WINDOW, 2 * min(pred.shape[-2:]) - 1)
    ssim = ssim_map(pred.expand_as(targets), targets, window).mean(dim=1, keepdim=True)
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim)


def photometric_loss_map(pred: Tensor, target: Tensor, ssim_weight: float = 0.2) -> Tensor:
    r"""Per-pixel :math:`(1-\lambda)\,\mathrm{mean}_c|P-T| + \lambda\,(1-\mathrm{mean}_c\,\mathrm{SSIM}(P,T))`.

    Args:
        pred: :math:`(C, H, W)` rendered colour.
        target: :math:`(C, H, W)` target colour.
        ssim_weight: :math:`\lambda` (0.2 in 3DGS).

    Returns:
        :math:`(1, H, W)` loss map; its mean is vanilla 3DGS's colour loss.
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
    return _loss_maps(pred, target[None], ssim_weight)[0]


def photometric_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None, ssim_weight: float = 0.2) -> Tensor:
    """:func:`photometric_loss_map` summed over ``mask`` and divided by H*W (0 for an empty mask).

    Args:
        pred: :math:`(C, H, W)`.
        target: :math:`(C, H, W)`.
        mask: optional :math:`(1, H, W)` bool or float weights; ``None`` = every pixel (the
            trainer's plain colour loss).
        ssim_weight: SSIM share.

    Returns:
        Scalar.
    """
    loss = photometric_loss_map(pred, target, ssim_weight)
    if mask is not None:
        loss = loss * mask.to(loss.dtype)
    return loss.sum() / loss[0].numel()


def reflective_loss(
    pred: Tensor,
    image: Tensor,
    specular_mask: Tensor,
    i_diff: Tensor,
    overexposed_mask: Tensor,
    i_chro: Tensor,
    ssim_weight: float = 0.2,
) -> tuple[Tensor, Tensor]:
    r"""The reflective-aware loss split into :math:`L_s(C, I_{diff})` and :math:`L_o(C, I_{chro})`.

    One target image is assembled (the training colour, with I_diff on specular pixels and I_chro
    on overexposed ones) so that SSIM windows straddling a highlight's border compare against the
    real surroundings; each term sums the loss map over its own mask (divided by H*W).

    Args:
        pred: :math:`(C, H, W)` rendered colour.
        image: :math:`(C, H, W)` training colour s0 / 2.
        specular_mask: :math:`(1, H, W)` bool.
        i_diff: :math:`(C, H, W)` target on specular pixels.
        overexposed_mask: :math:`(1, H, W)` bool (only pixels with a valid I_chro).
        i_chro: :math:`(C, H, W)` target on overexposed pixels.
        ssim_weight: SSIM share.

    Returns:
        ``(L_s, L_o)`` scalars.
    """
    target = torch.where(specular_mask, i_diff, torch.where(overexposed_mask, i_chro, image))
    loss = photometric_loss_map(pred, target, ssim_weight)
    count = loss[0].numel()
    return (loss * specular_mask).sum() / count, (loss * overexposed_mask).sum() / count


def mask_box(mask: Tensor, margin: int) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box of ``mask`` grown by ``margin`` (clipped to the
    image), or ``None`` for an empty mask.

    Args:
        mask: :math:`(1, H, W)` bool.
        margin: pixels added on every side.
    """
    rows = mask[0].any(dim=1).nonzero()
    if rows.numel() == 0:
        return None
    cols = mask[0].any(dim=0).nonzero()
    height, width = mask.shape[-2:]
    top, bottom = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, height)
    left, right = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, width)
    return slice(top, bottom), slice(left, right)


def _reflect(index: Tensor, size: int) -> Tensor:
    """Indices outside [0, size) mirrored without repeating the edge (torch's 'reflect' padding)."""
    index = index.abs()
    return torch.where(index > size - 1, 2 * (size - 1) - index, index)


class ReflectiveTargets:
    r"""One view's constants of :func:`reflective_replacement`, built once (e.g. at preprocess).

    The reflective pixels, the assembled L_ref target (training colour with I_diff on specular and
    I_chro on overexposed pixels) and the plain target are fixed during training: they are cut out
    here where the reflective pixels' SSIM windows reach, and a call computes the prediction's
    SSIM against the two targets (corrected and plain) there only:

    - *pixels* strategy: gathers the reflect-padded 11x11 window of each reflective pixel, with
      the targets' windowed mean and second moment precomputed (cheapest when highlights are
      sparse); equal to the whole-image values up to float rounding; on CPU float tensors one
      compiled pass (:func:`polargs_plugin.reflective_window.reflective_window_losses`), else
      torch operations;
    - *box* strategy: the fused :func:`polargs_plugin.ssim.ssim_map` on the reflective pixels'
      bounding box grown by the window radius (cheapest for dense highlights, and bounded in
      memory). The box holds every reflective pixel's whole window (or meets the image border,
      where the same reflection applies), so the SSIM there is computed by the same operations
      as on the whole image, and cancels the trainer's colour loss to the last bit.

    Both give the whole-image values of :func:`reflective_loss` and :func:`photometric_loss` on
    the reflective pixels (kornia's SSIM: Gaussian window 11, sigma 1.5, 'reflect' same padding).
    A call needs no host-device synchronisation.

    Args:
        image: :math:`(C, H, W)` training colour (the trainer's target).
        specular_mask, overexposed_mask: :math:`(1, H, W)` bool.
        i_diff, i_chro: :math:`(C, H, W)` targets on those masks.
        max_window_elements: largest number of (pixel, window tap) pairs the *pixels* strategy
            may hold; beyond it (or when it would cost more than the box) the box is used.
    """

    def __init__(
        self,
        image: Tensor,
        specular_mask: Tensor,
        i_diff: Tensor,
        overexposed_mask: Tensor,
        i_chro: Tensor,
        max_window_elements: int = 1 << 20,
    ) -> None:
        height, width = image.shape[-2:]
        self.count = height * width
        self.window = min(_SSIM_WINDOW, 2 * min(height, width) - 1)
        reflective = specular_mask | overexposed_mask
        target = torch.where(specular_mask, i_diff, torch.where(overexposed_mask, i_chro, image))
        targets = torch.stack([target, image])  # (2, C, H, W): corrected, plain
        self.kernel = gaussian_kernel1d(self.window, device=image.device, dtype=image.dtype)  # (k,)
        box = mask_box(reflective, self.window // 2)
        self.strategy = "empty" if box is None else "box"
        if box is None:
            return
        rows, cols = box
        pixels = reflective.reshape(-1).nonzero().squeeze(1)
        box_area = (rows.stop - rows.start) * (cols.stop - cols.start)
        # Gathering costs about window^2 per pixel, the separable box filters 2 window per box pixel.
        if pixels.numel() * self.window**2 <= min(2 * self.window * box_area, max_window_elements):
            self.strategy = "pixels"
            radius = self.window // 2
            offsets = torch.arange(-radius, radius + 1, device=pixels.device)
            win_rows = _reflect(pixels[:, None] // width + offsets, height)  # (P, k)
            win_cols = _reflect(pixels[:, None] % width + offsets, width)
            self.windows = (win_rows[:, :, None] * width + win_cols[:, None, :]).reshape(len(pixels), -1)
            self.weights = (self.kernel[:, None] * self.kernel[None, :]).reshape(-1)  # (k*k,)
            self.pixels = pixels
            flat = targets.reshape(*targets.shape[:2], -1)
            self.targets = flat[:, :, self.windows]  # (2, C, P, k*k)
            self.values = flat[:, :, pixels]  # (2, C, P)
            self.specular = specular_mask.reshape(-1)[pixels]
            self.overexposed = overexposed_mask.reshape(-1)[pixels]
            self.reflective = torch.ones_like(self.specular)
            self.target_mean = self._filter(self.targets)
            self.target_sq = self._filter(self.targets * self.targets)
        else:
            self.box = box
            self.targets = self.values = targets[:, :, rows, cols].contiguous()  # (2, C, h, w)
            self.specular = specular_mask[:, rows, cols]
            self.overexposed = overexposed_mask[:, rows, cols]
            self.reflective = reflective[:, rows, cols]

    def _filter(self, x: Tensor) -> Tensor:
        """Gaussian-windowed mean over the last axis (the gathered windows, *pixels* strategy)."""
        return x @ self.weights

    def _losses(self, pred: Tensor, ssim_weight: float) -> Tensor:
        """(2, ...) photometric loss of ``pred`` against the corrected and plain targets, at the
        reflective pixels (*pixels*) or over the box (*box*)."""
        if self.strategy == "pixels" and numba_path(pred) and pred.dtype == self.targets.dtype:
            return reflective_window_losses(pred, self.windows, self.pixels, self.weights, self.targets,
                                            self.values, self.target_mean, self.target_sq, ssim_weight)
        if self.strategy == "pixels":
            flat = pred.reshape(pred.shape[0], -1)
            pred, values = flat[:, self.windows], flat[:, self.pixels]  # (C, P, k*k), (C, P)
        else:
            rows, cols = self.box
            pred = values = pred[:, rows, cols]
        l1 = (values - self.values).abs().mean(dim=1)
        if ssim_weight == 0:
            return l1
        if self.strategy == "pixels":
            # One filtering call for the prediction's mean, its square and its products with both targets.
            moments = self._filter(torch.cat([pred[None], (pred * pred)[None], pred * self.targets]))
            mu, sq, cross = moments[0], moments[1], moments[2:]
            ssim = ssim_from_moments(mu, sq, self.target_mean, self.target_sq, cross).mean(dim=1)
        else:
            ssim = ssim_map(pred.expand_as(self.targets), self.targets, self.window).mean(dim=1)
        return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim)

    def __call__(
        self, pred: Tensor, lambda_ref: float = 1.0, ssim_weight: float = 0.2
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(extra, L_s, L_o, L_plain_reflective)`` of :func:`reflective_replacement` for ``pred``
        :math:`(C, H, W)`; all 0 (connected to ``pred``) when no pixel is reflective."""
        if self.strategy == "empty":
            zero = pred.sum() * 0
            return zero, zero, zero, zero
        corrected, plain = self._losses(pred, ssim_weight)
        l_s = (corrected * self.specular).sum() / self.count
        l_o = (corrected * self.overexposed).sum() / self.count
        l_plain = (plain * self.reflective).sum() / self.count
        return lambda_ref * (l_s + l_o) - l_plain, l_s, l_o, l_plain


def reflective_replacement(
    pred: Tensor,
    image: Tensor,
    specular_mask: Tensor,
    i_diff: Tensor,
    overexposed_mask: Tensor,
    i_chro: Tensor,
    lambda_ref: float = 1.0,
    ssim_weight: float = 0.2,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""What turns a plain whole-image colour loss into :math:`L_{non} + \lambda_{ref} L_{ref}`.

    ``extra = lambda_ref * (L_s + L_o) - L_plain(reflective)``, with ``L_plain(reflective)`` =
    ``photometric_loss(pred, image, reflective)``. Computed where the reflective pixels' SSIM
    windows reach only (:class:`ReflectiveTargets`), with the whole image's values. Build a
    :class:`ReflectiveTargets` once per view instead when calling this every iteration.

    Args:
        pred: :math:`(C, H, W)` rendered colour.
        image: :math:`(C, H, W)` training colour (the trainer's target).
        specular_mask, overexposed_mask: :math:`(1, H, W)` bool.
        i_diff, i_chro: :math:`(C, H, W)` targets on those masks.
        lambda_ref: weight of L_ref.
        ssim_weight: SSIM share.

    Returns:
        ``(extra, L_s, L_o, L_plain_reflective)`` scalars; all 0 (connected to ``pred``) when no
        pixel is reflective.
    """
    targets = ReflectiveTargets(image, specular_mask, i_diff, overexposed_mask, i_chro)
    return targets(pred, lambda_ref, ssim_weight)


def normal_loss(normal: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    r""":math:`L_n = \frac{1}{HW} \sum_{valid} \lVert \hat N - N_{opt} \rVert_1` with :math:`\hat N` the
    rendered normal made unit length (the rendered one is alpha-weighted, not unit).

    The sum over the valid pixels is divided by the number of pixels of the view, not by the
    number of valid ones, as for a dense normal prior whose invalid pixels weigh 0 (and as the
    masked colour losses here): each target pixel has the weight ``alpha / (H W)`` however few
    pixels PatchMatch kept, so a sparse target set (often the least reliable one) does not get
    the full weight ``alpha`` on a few pixels.

    Args:
        normal: :math:`(3, H, W)` rendered camera-frame normal.
        target: :math:`(3, H, W)` unit PatchMatch normal.
        valid: :math:`(1, H, W)` bool pixels with a target.

    Returns:
        Scalar, 0 where no pixel is valid.
    """
    per_pixel = (safe_normalize(normal, dim=0) - target).abs().sum(dim=0, keepdim=True)
    return (per_pixel * valid.to(normal.dtype)).sum() / valid[0].numel()


def polar_normal_loss(normal: Tensor, target: SingleViewNormals, where: Tensor | None = None) -> Tensor:
    r"""L_n against one view's own polarimetric normal
    (:func:`polargs_plugin.optics.single_view_normals`), on the pixels PatchMatch confirmed nothing.

    .. math::
        \frac{1}{HW}\Big(\sum_{full} \lVert \hat N - N_{pol} \rVert_1
        + \sum_{azimuth\ only} |\hat N \cdot m|\Big)

    with :math:`\hat N` the rendered normal made unit length, :math:`N_{pol}` = ``target.normal``
    and :math:`m` = ``target.plane``, the normal of the measured plane of incidence: on
    ``azimuth_only`` pixels only the component of :math:`\hat N` that leaves the measured azimuth
    is penalised, its zenith is free. Divided by the view's pixel count, as :func:`normal_loss`.

    Args:
        normal: :math:`(3, H, W)` rendered camera-frame normal (any length).
        target: a :class:`~polargs_plugin.optics.single_view.SingleViewNormals` of the view
            (:math:`(3, H, W)` and :math:`(1, H, W)` maps).
        where: optional :math:`(1, H, W)` bool, the pixels that may use it (with ``target.valid``).

    Returns:
        Scalar, 0 where no pixel is valid.
    """
    valid = target.valid if where is None else target.valid & where
    unit = safe_normalize(normal, dim=0)
    per_pixel = torch.where(target.azimuth_only, (unit * target.plane).sum(dim=0, keepdim=True).abs(),
                            (unit - target.normal).abs().sum(dim=0, keepdim=True))
    return (per_pixel * valid.to(normal.dtype)).sum() / valid[0].numel()


def normals_within(normal: Tensor, target: Tensor, max_deg: float) -> Tensor:
    """Where a normal map lies within ``max_deg`` degrees of a unit target map.

    L_n keeps a stale PatchMatch normal only where the render still agrees with it
    (``LossConfig.normal_hold_deg``).

    Args:
        normal: :math:`(3, H, W)` normal, any length (a rendered normal is alpha-weighted); zero
            vectors agree with nothing.
        target: :math:`(3, H, W)` unit normal.
        max_deg: the largest angle, in degrees.

    Returns:
        :math:`(1, H, W)` bool.

    >>> tilt = math.radians(5.0)
    >>> normal = torch.tensor([0.0, math.sin(tilt), -math.cos(tilt)]).view(3, 1, 1) * 0.4
    >>> target = torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1)
    >>> bool(normals_within(normal, target, 6.0)), bool(normals_within(normal, target, 4.0))
    (True, False)
    """
    cosine = (safe_normalize(normal, dim=0) * target).sum(dim=0, keepdim=True)
    return cosine >= math.cos(math.radians(max_deg))


def depth_to_points(depth: Tensor, K: Tensor) -> Tensor:
    """Camera-frame points of a camera-z depth map (pixel centres at +0.5).

    Args:
        depth: :math:`(1, H, W)` camera z.
        K: :math:`(3, 3)` intrinsics.

    Returns:
        :math:`(3, H, W)` points :math:`z K^{-1} [u + 0.5, v + 0.5, 1]^T`.
    """
    height, width = depth.shape[-2:]
    K = K.to(device=depth.device, dtype=torch.float64)
    u = torch.arange(width, device=depth.device, dtype=torch.float64) + 0.5
    v = torch.arange(height, device=depth.device, dtype=torch.float64) + 0.5
    x = ((u[None, :] - K[0, 2] - K[0, 1] * (v[:, None] - K[1, 2]) / K[1, 1]) / K[0, 0]).to(depth.dtype)
    y = ((v[:, None] - K[1, 2]) / K[1, 1]).expand(height, width).to(depth.dtype)
    rays = torch.stack([x, y, torch.ones_like(x)])
    return rays * depth


def normal_from_depth(depth: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Camera-frame normals from central differences of the back-projected depth, facing the camera.

    Args:
        depth: :math:`(1, H, W)` camera z (0 = nothing rendered).
        K: :math:`(3, 3)` intrinsics.

    Returns:
        ``(normal, valid)``: :math:`(3, H, W)` unit normals (0 where invalid) and :math:`(1, H, W)`
        bool, True where the pixel and its four neighbours have positive depth (never on the border).
    """
    points = depth_to_points(depth, K)
    d_u = torch.zeros_like(points)
    d_v = torch.zeros_like(points)
    d_u[:, :, 1:-1] = points[:, :, 2:] - points[:, :, :-2]
    d_v[:, 1:-1, :] = points[:, 2:, :] - points[:, :-2, :]
    # dP/dv x dP/du points towards the camera (x right, y down, z forward). Dividing by z^2 and
    # multiplying by fx fy makes its length O(1) whatever the scene scale, so the floor in
    # safe_normalize only bites on degenerate pixels.
    scale = (K[0, 0] * K[1, 1]).to(depth.dtype) / depth.square().clamp_min(1e-12)
    normal = safe_normalize(torch.linalg.cross(d_v, d_u, dim=0) * scale, dim=0)
    positive = depth > 0
    valid = torch.zeros_like(positive)
    valid[:, 1:-1, 1:-1] = (
        positive[:, 1:-1, 1:-1]
        & positive[:, 1:-1, 2:]
        & positive[:, 1:-1, :-2]
        & positive[:, 2:, 1:-1]
        & positive[:, :-2, 1:-1]
    )
    return normal * valid, valid


def depth_normal_loss(depth: Tensor, normal: Tensor, alpha: Tensor, K: Tensor) -> Tensor:
    r"""Depth-normal consistency :math:`\sum w (1 - \hat N_d \cdot \hat N) / \sum w`, :math:`w = \alpha`.

    The opacity weight is detached, so the term shapes geometry without pushing opacity down.

    Args:
        depth: :math:`(1, H, W)` rendered camera-z depth.
        normal: :math:`(3, H, W)` rendered normal.
        alpha: :math:`(1, H, W)` rendered opacity.
        K: :math:`(3, 3)` intrinsics.

    Returns:
        Scalar in [0, 2], 0 where no pixel is valid or alpha is 0.

    Note:
        On CPU float32/float64 tensors the fused kernel of :mod:`polargs_plugin.depth_normal`
        runs (same value, hand-written backward, once differentiable); elsewhere (CUDA, under
        ``torch.func`` transforms or tracing) these torch operations with autograd.
    """
    if numba_path(depth) and min(depth.shape[-2:]) >= 3:
        return depth_normal_loss_fused(depth, normal.to(depth.dtype), alpha, K)
    return _depth_normal_loss_torch(depth, normal, alpha, K)


def _depth_normal_loss_torch(depth: Tensor, normal: Tensor, alpha: Tensor, K: Tensor) -> Tensor:
    """:func:`depth_normal_loss` by torch operations (any device, autograd)."""
    depth_normal, valid = normal_from_depth(depth, K)
    weight = alpha.detach() * valid
    cosine = (depth_normal * safe_normalize(normal, dim=0)).sum(dim=0, keepdim=True)
    return (weight * (1 - cosine)).sum() / weight.sum().clamp_min(1e-8)


def scale_loss(scales: Tensor) -> Tensor:
    r"""Flattening :math:`L_{scale} = \mathrm{mean}_i \min(s_{i,1}, s_{i,2}, s_{i,3})`.

    Args:
        scales: :math:`(N, 3)` positive scales.

    Returns:
        Scalar, 0 for N = 0.

    Note:
        On CPU float32/float64 tensors the backward is the compiled pass of
        :mod:`polargs_plugin.scale_flatten` (the same gradient to the last bit).
    """
    if scales.shape[0] == 0:
        return scales.sum()
    if numba_path(scales) and scales.shape[-1] == 3:
        return scale_loss_fused(scales)
    return scales.amin(dim=-1).mean()
