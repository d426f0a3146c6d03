"""Telling a mono polarization frame (Sony IMX250MZR) from a colour one (IMX250MYR) by the frame itself.

:func:`mosaic_colour_evidence` measures how strongly a raw frame shows the Bayer colour structure
inside the polarizer super-pixels (its docstring says how); :func:`classify_mosaic` and
:func:`check_mosaic_pattern` turn that into a verdict, so that a mono IMX250MZR frame read as
colour (or the reverse) is an error instead of silently wrong images. The mosaic layouts and
demosaicing are :mod:`polargs_plugin.optics.mosaic`'s.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from polargs_plugin.io import PolarInputError
from polargs_plugin.optics.mosaic import MOSAIC_PATTERNS, POLARIZER_LATTICE, _as_tensor, _full_scale

__all__ = [
    "EVIDENCE_BLOCK",
    "EVIDENCE_Z",
    "MONO_BELOW",
    "RGB_ABOVE",
    "mosaic_colour_evidence",
    "classify_mosaic",
    "check_mosaic_pattern",
]

#: Side, in pixels of one polarizer sub-lattice, of the blocks :func:`mosaic_colour_evidence` tests
#: (6 sub-lattice pixels = 12x12 raw pixels = 3x3 Bayer cells of each sub-lattice).
EVIDENCE_BLOCK = 6
#: A block "shows colour" when its coherent Bayer chroma exceeds this many times what the block's
#: own incoherent high-frequency content (noise, texture, edges) gives a mono frame (about 1).
EVIDENCE_Z = 10.0
#: Below this fraction of bright blocks showing colour a frame is mono (real IMX250MZR frames: 0).
MONO_BELOW = 0.05
#: Above this fraction a frame is colour (IMX250MYR raw frames are not white-balanced: nearly all).
RGB_ABOVE = 0.3


def mosaic_colour_evidence(raw: np.ndarray | Tensor, bit_depth: int | None = None, source: str = "") -> float | None:
    """How strongly a raw polarization frame shows the Bayer colour structure of an IMX250MYR.

    On a colour sensor each polarizer's stride-2 sub-lattice is an RGGB Bayer mosaic, so inside
    every sub-lattice the samples carry the colour differences at the Bayer's modulation
    frequencies: with ``x(i, j)`` the sub-lattice image, the 2x2 operators
    ``a = (x00 - x01 - x10 + x11) / 4 (-1)^(i+j)``, ``b = (x00 + x01 - x10 - x11) / 4 (-1)^i`` and
    ``c = (x00 - x01 + x10 - x11) / 4 (-1)^j`` (evaluated at every position) equal the smooth
    chroma ``(R - 2G + B) / 4``, ``(R - B) / 4``, ``(R - B) / 4`` of a colour frame at every phase,
    whereas on a mono frame they are the image's high frequencies with alternating signs. Over a
    block, the mean of each operator (the *coherent* part) is therefore about the chroma on a
    colour frame and close to zero on a mono frame, while the spread around the mean (noise,
    texture, edges) is there on both. Per block of :data:`EVIDENCE_BLOCK` sub-lattice pixels,
    summed over the three operators and the four polarizer sub-lattices,
    ``z = n^2 coherent^2 / incoherent`` is about 1 without colour (a chi-square mean; edges reach
    ~3) and large on colour; the evidence is the fraction of bright blocks (mean above 10 % of
    the brightest block, and some high-frequency content: a perfectly flat block tells nothing)
    with ``z >`` :data:`EVIDENCE_Z`. Constants and linear ramps cancel in every operator; the
    incoherent part has a floor of the quantisation noise.

    Measured (tests/test_optics_mosaic.py): real IMX250MZR crops (polanalyser) 0.00; the bundled
    synthetic scenes written as mono mosaics 0.00-0.14, as RGB mosaics 0.09-0.9 (near-grey views
    are low: a colour mosaic of a grey, white-balanced scene has no colour structure to find).

    Args:
        raw: (H, W) raw frame (numpy or tensor, integer or float as for :func:`demosaic_polar`).
        bit_depth: as for :func:`demosaic_polar` (only the noise floor depends on it).
        source: file named in errors.

    Returns:
        The fraction in [0, 1], or None when the frame is too small or too dark (fewer than 4
        bright blocks) to tell. Frames over 768 pixels on a side are sampled on a grid of 8x8
        tiles of 96x96 (about 0.1 s for a 2448x2048 frame).

    Example:
        >>> from polargs_plugin.optics.mosaic import mosaic_from_intensities
        >>> g = torch.Generator().manual_seed(0)
        >>> scene = torch.tensor([0.7, 0.3, 0.1]).reshape(1, 3, 1, 1) + 0.1 * torch.rand(4, 3, 96, 96, generator=g)
        >>> mosaic_colour_evidence(mosaic_from_intensities(scene, "rgb"))  # an orange scene, colour sensor
        1.0
        >>> mosaic_colour_evidence(mosaic_from_intensities(scene.mean(1, keepdim=True)))  # mono sensor
        0.0
    """
    tensor = _as_tensor(raw, source)
    if tensor.ndim != 2:
        raise PolarInputError(source, f"raw mosaic must be 2-D (H, W), got shape {tuple(tensor.shape)}")
    full = _full_scale(tensor, bit_depth, source)
    array = tensor.detach().cpu().to(torch.float64 if tensor.dtype == torch.float64 else torch.float32).numpy()
    level = np.float32(255.0 / full)  # 8-bit levels: the quantisation floor does not depend on the data's scale
    height, width = array.shape
    # Large frames: a regular grid of at most _TILES x _TILES tiles (offsets multiples of 4 keep
    # both the polarizer and the Bayer phase), about 0.6 Mpixel whatever the sensor size.
    rows = _tile_starts(height)
    cols = _tile_starts(width)
    z_parts, lum_parts, energy_parts = [], [], []
    for r in rows:
        for c in cols:
            tile = array if len(rows) == len(cols) == 1 else array[r : r + _TILE, c : c + _TILE]
            z, lum, energy = _block_evidence(tile * level)
            z_parts.append(z.ravel())
            lum_parts.append(lum.ravel())
            energy_parts.append(energy.ravel())
    z, luminance, energy = np.concatenate(z_parts), np.concatenate(lum_parts), np.concatenate(energy_parts)
    if z.size == 0:
        return None
    # informative blocks: bright, and with some high-frequency content at all (a flat block, with
    # neither noise nor colour, cannot tell)
    informative = (luminance > 0.1 * luminance.max()) & (energy > 4 * _FLOOR)
    if int(informative.sum()) < 4:
        return None
    return float(np.mean(z[informative] > EVIDENCE_Z))


_TILE, _TILES = 96, 8
_FLOOR = 0.25  # quantisation noise of the 12 operators of a block: 12 x (4 samples / 16) x 1/12 level^2


def _tile_starts(size: int) -> list[int]:
    if size <= _TILE * _TILES:
        return [0]
    step = (size - _TILE) / (_TILES - 1)
    return [int(round(k * step)) // 4 * 4 for k in range(_TILES)]


def _block_evidence(array: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block of EVIDENCE_BLOCK sub-lattice pixels: z (see mosaic_colour_evidence), mean level,
    energy of the operators (level^2)."""
    n = EVIDENCE_BLOCK
    h, w = array.shape[0] // 2 - 1, array.shape[1] // 2 - 1
    hb, wb = max(h // n, 0), max(w // n, 0)
    if hb < 1 or wb < 1:
        return np.zeros((0,)), np.zeros((0,)), np.zeros((0,))
    coherent = np.zeros((hb, wb), np.float64)
    total = np.zeros((hb, wb), np.float64)
    luminance = np.zeros((hb, wb), np.float64)

    def blocks(values: np.ndarray) -> np.ndarray:
        return values[: hb * n, : wb * n].reshape(hb, n, wb, n).mean(axis=(1, 3), dtype=np.float64)

    for row, col in POLARIZER_LATTICE:
        sub = array[row::2, col::2][: h + 1, : w + 1]
        x00, x01, x10, x11 = sub[:-1, :-1], sub[:-1, 1:], sub[1:, :-1], sub[1:, 1:]
        si = np.where(np.arange(h) % 2 == 0, 1.0, -1.0).astype(sub.dtype)[:, None]
        sj = np.where(np.arange(w) % 2 == 0, 1.0, -1.0).astype(sub.dtype)[None, :]
        luminance += blocks(x00)
        for operator in ((x00 - x01 - x10 + x11) * (si * sj), (x00 + x01 - x10 - x11) * si, (x00 - x01 + x10 - x11) * sj):
            operator = operator * np.float32(0.25)
            coherent += blocks(operator) ** 2
            total += blocks(operator * operator)
    incoherent = np.maximum(total - coherent, _FLOOR)
    return n * n * coherent / incoherent, luminance, total


def classify_mosaic(evidence: float | None) -> str | None:
    """``"mono"``, ``"rgb"`` or None (cannot tell) from :func:`mosaic_colour_evidence`.

    Example:
        >>> classify_mosaic(0.0), classify_mosaic(0.9), classify_mosaic(0.2), classify_mosaic(None)
        ('mono', 'rgb', None, None)
    """
    if evidence is None:
        return None
    if evidence < MONO_BELOW:
        return "mono"
    if evidence > RGB_ABOVE:
        return "rgb"
    return None


def pattern_mismatch(evidence: float | None, pattern: str) -> str | None:
    """The problem when a frame with this evidence is read as ``pattern``, or None when it fits
    (or cannot be told). Used by readers to refuse a mono frame read as colour and the reverse."""
    found = classify_mosaic(evidence)
    if found is None or found == pattern:
        return None
    percent = f"{100 * evidence:.0f} %"
    if found == "mono":
        return (
            f"read as a colour (IMX250MYR) mosaic, but it looks like a mono (IMX250MZR) frame: {percent} of its "
            f"bright 12x12 blocks show the 2x2 Bayer colour structure inside the polarizer super-pixels (a colour "
            f"frame shows over {100 * RGB_ABOVE:.0f} %); read it as mono (--pattern mono), or skip this check "
            "(--no-pattern-check) if it is a colour frame of a grey, white-balanced scene"
        )
    return (
        f"read as a mono (IMX250MZR) mosaic, but it looks like a colour (IMX250MYR) frame: {percent} of its "
        f"bright 12x12 blocks show the 2x2 Bayer colour structure inside the polarizer super-pixels (a mono "
        f"frame shows under {100 * MONO_BELOW:.0f} %); read it as rgb (--pattern rgb), or skip this check "
        "(--no-pattern-check)"
    )


def check_mosaic_pattern(raw: np.ndarray | Tensor, pattern: str, bit_depth: int | None = None, source: str = "") -> str:
    """The pattern to read ``raw`` with: ``pattern`` checked against the frame, or detected.

    Args:
        raw: (H, W) raw frame.
        pattern: ``"mono"`` or ``"rgb"`` (checked: a frame that clearly shows the other layout
            raises), or ``"auto"`` (detected; raises when the frame cannot tell).
        bit_depth: as for :func:`demosaic_polar`.
        source: file named in errors.

    Returns:
        ``"mono"`` or ``"rgb"``.

    Raises:
        PolarInputError: naming ``source``: the frame contradicts ``pattern``, or ``"auto"`` and
            the frame is ambiguous (grey colour scene, too dark, too small).

    Example:
        >>> from polargs_plugin.optics.mosaic import mosaic_from_intensities
        >>> g = torch.Generator().manual_seed(0)
        >>> scene = torch.tensor([0.7, 0.3, 0.1]).reshape(1, 3, 1, 1) + 0.1 * torch.rand(4, 3, 96, 96, generator=g)
        >>> check_mosaic_pattern(mosaic_from_intensities(scene, "rgb"), "auto")
        'rgb'
        >>> check_mosaic_pattern(mosaic_from_intensities(scene.mean(1, keepdim=True)), "rgb", source="f.png")
        Traceback (most recent call last):
        ...
        polargs_plugin.io.PolarInputError: f.png: read as a colour (IMX250MYR) mosaic, but it looks like a mono ...
    """
    if pattern not in (*MOSAIC_PATTERNS, "auto"):
        raise PolarInputError(source, f"unknown mosaic pattern {pattern!r}, expected one of {(*MOSAIC_PATTERNS, 'auto')}")
    evidence = mosaic_colour_evidence(raw, bit_depth, source)
    if pattern == "auto":
        found = classify_mosaic(evidence)
        if found is None:
            what = "too small or too dark" if evidence is None else f"{100 * evidence:.0f} % of its bright blocks show Bayer colour structure"
            raise PolarInputError(
                source,
                f"cannot tell a mono (IMX250MZR) from a colour (IMX250MYR) mosaic ({what}; mono < "
                f"{100 * MONO_BELOW:.0f} %, colour > {100 * RGB_ABOVE:.0f} %); give the pattern (--pattern mono or rgb)",
            )
        return found
    problem = pattern_mismatch(evidence, pattern)
    if problem is not None:
        raise PolarInputError(source, problem)
    return pattern
