"""Placeholder losses (upstream names)."""

from polargs_plugin.ssim import ssim_map


def l1_loss(image, target):
    return (image - target).abs().mean()


def ssim(image, target):
    return ssim_map(image, target).mean()
