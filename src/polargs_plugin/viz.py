"""Pictures of polarization maps, coloured the way polanalyser draws them, saved atomically as PNG.

AoLP is drawn with the HSV hue circle: hue = AoLP / pi of a full turn, quantised to OpenCV's
8-bit hue steps exactly as ``polanalyser.applyColorToAoLP`` does (hue index
floor(AoLP / pi * 179) out of 180; saturation and value floor(x * 255) / 255), so our pictures
match polanalyser's to one 8-bit level. The "dark" style puts DoLP in the value (unpolarized
pixels black), the "light" style in the saturation (unpolarized pixels white).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.io import atomic_path
from polargs_plugin.optics import aolp_from_stokes, dolp_from_stokes
from polargs_plugin.types import PolarMaps

__all__ = ["AOLP_STYLES", "hsv_to_rgb", "aolp_to_rgb", "dolp_to_rgb", "save_png", "save_polar_pictures", "polar_panels", "save_contact_sheet", "save_map_pictures"]

AOLP_STYLES = ("dark", "light")


def hsv_to_rgb(hue: Tensor, saturation: Tensor, value: Tensor) -> Tensor:
    """HSV to RGB (the standard hexcone model, as OpenCV's ``COLOR_HSV2RGB``).

    Args:
        hue: :math:`(*, H, W)` in turns, [0, 1) is the full colour circle.
        saturation: :math:`(*, H, W)` in [0, 1].
        value: :math:`(*, H, W)` in [0, 1].

    Returns:
        :math:`(*, 3, H, W)` RGB in [0, 1].

    Example:
        >>> hsv_to_rgb(torch.tensor([[1 / 3]]), torch.ones(1, 1), torch.ones(1, 1)).flatten()
        tensor([0., 1., 0.])
    """
    h6 = torch.remainder(hue, 1.0) * 6.0
    sector = torch.clamp(torch.floor(h6), 0, 5)
    f = h6 - sector
    p = value * (1 - saturation)
    q = value * (1 - saturation * f)
    t = value * (1 - saturation * (1 - f))
    # (R, G, B) for sectors 0..5: (v,t,p) (q,v,p) (p,v,t) (p,q,v) (t,p,v) (v,p,q).
    table = torch.stack(
        [
            torch.stack([value, t, p]),
            torch.stack([q, value, p]),
            torch.stack([p, value, t]),
            torch.stack([p, q, value]),
            torch.stack([t, p, value]),
            torch.stack([value, p, q]),
        ]
    )  # (6, 3, *, H, W)
    index = sector.long().unsqueeze(0).unsqueeze(0).expand(1, 3, *sector.shape)
    return table.gather(0, index).squeeze(0).movedim(0, -3)


def _floor_level(x: Tensor) -> Tensor:
    return torch.floor(torch.clamp(x, 0.0, 1.0) * 255) / 255


def aolp_to_rgb(aolp: Tensor, dolp: Tensor | None = None, style: str = "dark") -> Tensor:
    """Colour an AoLP map with the HSV hue circle (polanalyser's ``applyColorToAoLP``, as RGB).

    Args:
        aolp: :math:`(*, 1, H, W)` AoLP in radians (wrapped modulo pi).
        dolp: optional :math:`(*, 1, H, W)` DoLP in [0, 1] (clamped); ``None`` draws full colour.
        style: ``"dark"`` (DoLP as value) or ``"light"`` (DoLP as saturation).

    Returns:
        :math:`(*, 3, H, W)` float RGB in [0, 1].

    Example:
        >>> aolp_to_rgb(torch.zeros(1, 1, 1)).flatten()  # AoLP 0 is red
        tensor([1., 0., 0.])
    """
    if style not in AOLP_STYLES:
        raise ValueError(f"unknown AoLP style {style!r}, expected one of {AOLP_STYLES}")
    if aolp.ndim < 3 or aolp.shape[-3] != 1:
        raise ValueError(f"aolp must have shape (..., 1, H, W), got {tuple(aolp.shape)}")
    if dolp is not None and dolp.shape != aolp.shape:
        raise ValueError(f"dolp shape {tuple(dolp.shape)} differs from aolp shape {tuple(aolp.shape)}")
    angle = aolp.squeeze(-3)
    hue = torch.floor(torch.remainder(angle, math.pi) / math.pi * 179) / 180
    ones = torch.ones_like(angle)
    weight = ones if dolp is None else _floor_level(dolp.squeeze(-3))
    if style == "dark":
        return hsv_to_rgb(hue, ones, weight)
    return hsv_to_rgb(hue, weight, ones)


def dolp_to_rgb(dolp: Tensor) -> Tensor:
    """Grey-level DoLP picture (black = unpolarized, white = fully polarized).

    Args:
        dolp: :math:`(*, 1, H, W)` DoLP, clamped to [0, 1].

    Returns:
        :math:`(*, 3, H, W)` float RGB in [0, 1].

    Example:
        >>> dolp_to_rgb(torch.full((1, 1, 1), 0.25)).flatten()
        tensor([0.2500, 0.2500, 0.2500])
    """
    if dolp.ndim < 3 or dolp.shape[-3] != 1:
        raise ValueError(f"dolp must have shape (..., 1, H, W), got {tuple(dolp.shape)}")
    return torch.clamp(dolp, 0.0, 1.0).expand(*dolp.shape[:-3], 3, *dolp.shape[-2:])


def save_png(path: str | os.PathLike, image: Tensor | np.ndarray, bit_depth: int = 8) -> Path:
    """Write a channel-first image as PNG, atomically (nothing is left half-written).

    Args:
        path: destination file (parent folders are created).
        image: :math:`(C, H, W)` with C = 1 (grey), 3 (RGB) or 4 (RGBA); float in [0, 1]
            (clamped, rounded to the nearest level) or uint8.
        bit_depth: 8 or 16 bits per channel in the file.

    Returns:
        The path written.

    Example:
        >>> import tempfile
        >>> out = save_png(Path(tempfile.mkdtemp()) / "red.png", torch.tensor([1.0, 0, 0]).reshape(3, 1, 1))
        >>> cv2.imread(str(out))[0, 0].tolist()  # OpenCV reads BGR
        [0, 0, 255]
    """
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    array = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if array.ndim != 3 or array.shape[0] not in (1, 3, 4):
        raise ValueError(f"image must have shape (C, H, W) with C in (1, 3, 4), got {array.shape}")
    full = 2**bit_depth - 1
    if array.dtype == np.uint8:
        levels = array.astype(np.uint16) * (full // 255)
    elif np.issubdtype(array.dtype, np.floating):
        if not np.isfinite(array).all():
            raise ValueError("image contains non-finite values")
        levels = np.round(np.clip(array, 0.0, 1.0) * full)
    else:
        raise ValueError(f"image must be float in [0, 1] or uint8, got dtype {array.dtype}")
    pixels = np.moveaxis(levels.astype(np.uint8 if bit_depth == 8 else np.uint16), 0, -1)
    if pixels.shape[-1] == 1:
        pixels = pixels[..., 0]
    else:  # RGB(A) -> BGR(A) for OpenCV
        pixels = np.concatenate([pixels[..., 2::-1], pixels[..., 3:]], axis=-1)
    path = Path(path)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(pixels)):
            raise OSError(f"{path}: OpenCV could not write the PNG")
    return path


def save_polar_pictures(stokes: Tensor, out_dir: str | os.PathLike, prefix: str) -> list[Path]:
    """Save AoLP, DoLP, AoLP-with-DoLP and intensity pictures of one Stokes image.

    AoLP and DoLP are computed from the channel-mean Stokes (one map for colour data).
    Files: ``<prefix>_aolp.png`` (hue only), ``<prefix>_dolp.png`` (grey),
    ``<prefix>_aolp_dolp.png`` (dark style), ``<prefix>_s0.png`` (s0 / 2, the training colour,
    linear, clamped to [0, 1]).

    Args:
        stokes: :math:`(3, C, H, W)` Stokes (s0, s1, s2).
        out_dir: folder to write into (created if missing).
        prefix: file name prefix, e.g. the view name.

    Returns:
        The four paths written, in the order above.

    Example:
        >>> import tempfile
        >>> s = torch.tensor([1.0, 0.5, 0.0]).reshape(3, 1, 1, 1).expand(3, 3, 4, 4)
        >>> [p.name for p in save_polar_pictures(s, tempfile.mkdtemp(), "view0")]
        ['view0_aolp.png', 'view0_dolp.png', 'view0_aolp_dolp.png', 'view0_s0.png']
    """
    if stokes.ndim != 4 or stokes.shape[0] != 3:
        raise ValueError(f"stokes must have shape (3, C, H, W), got {tuple(stokes.shape)}")
    out_dir = Path(out_dir)
    return [save_png(out_dir / f"{prefix}_{name}.png", image) for name, image in polar_panels(stokes).items()]


def polar_panels(stokes: Tensor) -> dict[str, Tensor]:
    """The pictures :func:`save_polar_pictures` writes, as (3, H, W) float RGB tensors.

    Args:
        stokes: :math:`(3, C, H, W)` Stokes (s0, s1, s2).

    Returns:
        ``{"aolp", "dolp", "aolp_dolp", "s0"}`` -> :math:`(C', H, W)` in [0, 1] (C' = 3, or C for s0).

    Example:
        >>> s = torch.tensor([1.0, 0.0, 0.5]).reshape(3, 1, 1, 1).expand(3, 3, 2, 2)
        >>> {name: tuple(p.shape) for name, p in polar_panels(s).items()}["aolp"]
        (3, 2, 2)
    """
    if stokes.ndim != 4 or stokes.shape[0] != 3:
        raise ValueError(f"stokes must have shape (3, C, H, W), got {tuple(stokes.shape)}")
    mean = stokes.mean(dim=1, keepdim=True).float()  # (3, 1, H, W)
    aolp, dolp = aolp_from_stokes(mean), dolp_from_stokes(mean)
    return {
        "aolp": aolp_to_rgb(aolp),
        "dolp": dolp_to_rgb(dolp),
        "aolp_dolp": aolp_to_rgb(aolp, dolp, "dark"),
        "s0": torch.clamp(stokes[0].float() / 2, 0.0, 1.0),
    }


def save_contact_sheet(rows: list[list[Tensor]], path: str | os.PathLike, gap: int = 2) -> Path:
    """Tile pictures into one PNG: one list per row, all pictures (C, H, W) of one size.

    Grey pictures (C = 1) are repeated to RGB; gaps are white. Written atomically.

    Args:
        rows: pictures per row, each :math:`(1 \text{ or } 3, H, W)` float in [0, 1].
        path: destination PNG.
        gap: white pixels between pictures.

    Returns:
        The path written.

    Example:
        >>> import tempfile
        >>> grey = torch.full((1, 4, 4), 0.5)
        >>> out = save_contact_sheet([[grey, grey]], Path(tempfile.mkdtemp()) / "sheet.png")
        >>> cv2.imread(str(out)).shape
        (4, 10, 3)
    """
    if not rows or not rows[0]:
        raise ValueError("contact sheet needs at least one picture")
    height, width = rows[0][0].shape[-2:]
    columns = max(len(row) for row in rows)
    sheet = torch.ones(3, len(rows) * (height + gap) - gap, columns * (width + gap) - gap)
    for r, row in enumerate(rows):
        for c, picture in enumerate(row):
            if picture.shape[-2:] != (height, width):
                raise ValueError(f"picture ({r}, {c}) is {tuple(picture.shape[-2:])}, expected {(height, width)}")
            y, x = r * (height + gap), c * (width + gap)
            sheet[:, y : y + height, x : x + width] = picture.detach().float().cpu().expand(3, -1, -1)
    return save_png(path, sheet)


# the masks picture: specular pixels tinted magenta, overexposed ones cyan
_SPECULAR_TINT = (1.0, 0.0, 1.0)
_OVEREXPOSED_TINT = (0.0, 1.0, 1.0)


def _overlay(image: Tensor, masks: list) -> Tensor:
    out = image.clamp(0, 1).clone()
    for mask, tint in masks:
        colour = torch.tensor(tint, dtype=out.dtype)[:, None, None]
        out = torch.where(mask, 0.4 * out + 0.6 * colour, out)
    return out


def save_map_pictures(maps: PolarMaps, out_dir: Path, prefix: str) -> list[Path]:
    """Write the pictures of one view's :class:`~polargs_plugin.types.PolarMaps`, as
    ``polargs preprocess`` does: ``<prefix>_aolp.png`` (hue, DoLP as brightness), ``_dolp.png``
    and, with PC, ``_masks.png`` (specular magenta, overexposed cyan over the image),
    ``_i_diff.png``, ``_i_chro.png``, ``_target.png`` (the colour target with I_diff / I_chro
    swapped in) and ``_pri.png``.

    Args:
        maps: the view's maps (masks and CRMs may be ``None`` when PC is disabled).
        out_dir: folder to write into.
        prefix: file name prefix (the view name).

    Returns:
        The paths written.

    >>> import tempfile
    >>> maps = PolarMaps(aolp=torch.zeros(1, 4, 4), dolp=torch.full((1, 4, 4), 0.2), intensity=torch.ones(3, 4, 4))
    >>> with tempfile.TemporaryDirectory() as folder:  # PC off: no masks, no colour targets
    ...     [path.name for path in save_map_pictures(maps, Path(folder), "v0")]
    ['v0_aolp.png', 'v0_dolp.png']
    """
    maps_cpu = {name: value.detach().cpu().float() for name, value in vars(maps).items() if isinstance(value, Tensor)}
    pictures = {
        "aolp": aolp_to_rgb(maps_cpu["aolp"], maps_cpu["dolp"].clamp(0, 1), "dark"),
        "dolp": dolp_to_rgb(maps_cpu["dolp"]),
    }
    if maps.specular_mask is not None:
        specular = maps.specular_mask.cpu()
        chro = (maps.overexposed_mask & maps.extras["i_chro_valid"]).cpu()
        image = maps_cpu["intensity"]
        pictures["masks"] = _overlay(image, [(specular, _SPECULAR_TINT), (maps.overexposed_mask.cpu(), _OVEREXPOSED_TINT)])
        pictures["i_diff"] = maps_cpu["i_diff"]
        pictures["i_chro"] = maps_cpu["i_chro"]
        pictures["target"] = torch.where(specular, maps_cpu["i_diff"], torch.where(chro, maps_cpu["i_chro"], image))
        pictures["pri"] = maps_cpu["pri"]
    return [save_png(out_dir / f"{prefix}_{name}.png", picture.clamp(0, 1)) for name, picture in pictures.items()]
