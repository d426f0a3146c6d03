"""Stand-in for ``fused_ssim`` (rahul-goel/fused-ssim, a CUDA extension gsplat's simple_trainer
imports): ``fused_ssim(img1, img2, padding="same", train=True)``, the mean SSIM (11x11 Gaussian
window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2) of two ``[B, C, H, W]`` images, differentiable
w.r.t. ``img1``, on :func:`polargs_plugin.ssim.ssim_map`.

``padding="valid"`` (simple_trainer's) averages the map over the pixels whose window lies inside
the image: the same value as the CUDA kernel up to float rounding. ``padding="same"`` averages
every pixel; at the border the stand-in's window is reflected where the kernel's is zero-padded.
"""

from __future__ import annotations

from torch import Tensor

from polargs_plugin.ssim import ssim_map

__all__ = ["fused_ssim", "WINDOW"]

WINDOW = 11
"""fused-ssim's window size (fixed)."""


def fused_ssim(img1: Tensor, img2: Tensor, padding: str = "same", train: bool = True) -> Tensor:
    """Mean SSIM of ``img1`` and ``img2`` (``[B, C, H, W]``); ``train`` only selects the CUDA
    kernel's backward buffers upstream and changes nothing here."""
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    ssim = ssim_map(img1, img2.detach(), WINDOW)
    if padding == "valid":
        border = WINDOW // 2
        ssim = ssim[..., border:-border, border:-border]
    return ssim.mean()
