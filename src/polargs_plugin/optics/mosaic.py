"""Division-of-focal-plane polarization mosaics (Sony IMX250MZR mono, IMX250MYR colour).

Layout (the sensor makers' documentation; docs/conventions.md), pinned by tests against real sensor frames:

- Mono (IMX250MZR): each 2x2 super-pixel is (row, column) (0,0) = 90 deg, (0,1) = 45 deg,
  (1,0) = 135 deg, (1,1) = 0 deg.
- Colour (IMX250MYR): each of those four stride-2 sub-lattices is itself an RGGB Bayer mosaic.

Demosaicing reproduces ``polanalyser.demosaicing`` with ``COLOR_PolarMono`` / ``COLOR_PolarRGB``
exactly (polanalyser runs OpenCV's bilinear Bayer conversion): every missing sample is the mean of
its 2 (row or column) or 4 (diagonal, or cross for Bayer green) nearest same-lattice neighbours,
rounded half up for integer input as OpenCV does, and the one-pixel image border repeats its
inner neighbour. Colour first demosaics the Bayer pattern of each quarter-resolution sub-lattice,
then the polarization lattice of each colour channel. The result is RGB (polanalyser returns BGR).
Integer data on the CPU goes through OpenCV (as polanalyser does, and fast); float data and
tensors on other devices through an equivalent torch implementation, so a raw tensor on the GPU
is demosaiced there. Tests pin both paths to polanalyser.

:func:`stokes_from_raw` is the fused fast path to Stokes: a numba kernel forms (s0, s1, s2) of
each pixel from the integer interpolated samples of its 3x3 neighbourhood, so the four float
angle images are never materialised (same numbers as demosaic_polar + stokes_from_intensities).

Telling a mono frame from a colour one by the frame itself is :mod:`polargs_plugin.optics.pattern`'s.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np
import torch
from torch import Tensor

from polargs_plugin.io import PolarInputError
from polargs_plugin.optics.stokes import stokes_from_intensities
from polargs_plugin.threads import numba_scheduling

__all__ = [
    "MOSAIC_PATTERNS",
    "POLARIZER_LATTICE",
    "demosaic_polar",
    "mosaic_from_intensities",
    "stokes_from_raw",
]

MOSAIC_PATTERNS = ("mono", "rgb")
#: (row, column) offset of each polarizer angle's stride-2 sub-lattice, in 0/45/90/135 order.
POLARIZER_LATTICE = ((1, 1), (0, 1), (0, 0), (1, 0))
#: (row, column) offset of R, G (two sites) and B in each RGGB Bayer cell.
_BAYER_RED, _BAYER_BLUE = (0, 0), (1, 1)
_MIN_SIZE = {"mono": 4, "rgb": 8}


def _average(parts: list[Tensor], exact_integer: bool) -> Tensor:
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    if exact_integer:  # OpenCV: (a + b + 1) >> 1 and (a + b + c + d + 2) >> 2
        shift = len(parts).bit_length() - 1
        return torch.bitwise_right_shift(total + len(parts) // 2, shift)
    return total / len(parts)


def _inner(parity: int, size: int, shift: int = 0) -> slice:
    """Indices 1..size-2 of the given parity, shifted by ``shift`` (a neighbour's indices)."""
    start = parity if parity >= 1 else 2
    return slice(start + shift, size - 1 + shift, 2)


def _repeat_border(image: Tensor) -> Tensor:
    """Overwrite the one-pixel border with its inner neighbour, in place (as OpenCV does)."""
    image[..., :, 0] = image[..., :, 1]
    image[..., :, -1] = image[..., :, -2]
    image[..., 0, :] = image[..., 1, :]
    image[..., -1, :] = image[..., -2, :]
    return image


def _interpolate_lattice(x: Tensor, offset: tuple[int, int], exact_integer: bool) -> Tensor:
    """Fill a full (*, H, W) image from its samples on one stride-2 lattice (bilinear).

    Only the interior (rows and columns 1..size-2) is interpolated; samples on the lattice are
    kept and each other parity class gets the mean of its 2 or 4 lattice neighbours.
    """
    h, w = x.shape[-2:]
    r, c = offset
    out = x.clone()
    rows, cols = _inner(r, h), _inner(c, w)
    other_rows, other_cols = _inner(1 - r, h), _inner(1 - c, w)
    up, down = _inner(1 - r, h, -1), _inner(1 - r, h, 1)
    left, right = _inner(1 - c, w, -1), _inner(1 - c, w, 1)
    out[..., rows, other_cols] = _average([x[..., rows, left], x[..., rows, right]], exact_integer)
    out[..., other_rows, cols] = _average([x[..., up, cols], x[..., down, cols]], exact_integer)
    out[..., other_rows, other_cols] = _average(
        [x[..., up, left], x[..., up, right], x[..., down, left], x[..., down, right]], exact_integer
    )
    return _repeat_border(out)


def _interpolate_bayer_green(x: Tensor, exact_integer: bool) -> Tensor:
    """Fill green of an RGGB mosaic (*, H, W): the mean of the 4 cross neighbours at R and B."""
    h, w = x.shape[-2:]
    out = x.clone()
    for parity in (0, 1):  # R sites (even, even) and B sites (odd, odd)
        rows, cols = _inner(parity, h), _inner(parity, w)
        out[..., rows, cols] = _average(
            [
                x[..., _inner(parity, h, -1), cols],
                x[..., _inner(parity, h, 1), cols],
                x[..., rows, _inner(parity, w, -1)],
                x[..., rows, _inner(parity, w, 1)],
            ],
            exact_integer,
        )
    return _repeat_border(out)


def _demosaic_bayer_rggb(x: Tensor, exact_integer: bool) -> Tensor:
    """(*, H, W) RGGB mosaic -> (*, 3, H, W) RGB, OpenCV bilinear."""
    red = _interpolate_lattice(x, _BAYER_RED, exact_integer)
    green = _interpolate_bayer_green(x, exact_integer)
    blue = _interpolate_lattice(x, _BAYER_BLUE, exact_integer)
    return torch.stack([red, green, blue], dim=-3)


def _demosaic_polar_lattices(x: Tensor, exact_integer: bool) -> Tensor:
    """(*, H, W) polarization mosaic -> (*, 4, H, W) images at 0/45/90/135 deg."""
    return torch.stack([_interpolate_lattice(x, off, exact_integer) for off in POLARIZER_LATTICE], dim=-3)


def _as_tensor(raw: np.ndarray | Tensor, source: str) -> Tensor:
    if isinstance(raw, np.ndarray):
        if raw.dtype.kind not in "uif":
            raise PolarInputError(source, f"raw mosaic has unsupported dtype {raw.dtype}")
        return torch.from_numpy(np.ascontiguousarray(raw))
    if isinstance(raw, Tensor):
        return raw
    raise PolarInputError(source, f"raw mosaic must be a numpy array or torch tensor, got {type(raw).__name__}")


_NATIVE_BITS = {torch.uint8: 8, torch.uint16: 16}


def _full_scale(raw: Tensor, bit_depth: int | None, source: str) -> float:
    """The value of full scale of ``raw``, checking the data against it."""
    if bit_depth is not None and bit_depth not in (8, 10, 12, 14, 16):
        raise PolarInputError(source, f"unsupported bit_depth {bit_depth} (expected 8, 10, 12, 14 or 16)")
    if raw.is_floating_point():
        if not bool(torch.isfinite(raw).all()):
            raise PolarInputError(source, "raw mosaic contains non-finite values (NaN or inf)")
        full = 1.0 if bit_depth is None else float(2**bit_depth - 1)
    else:
        native = _NATIVE_BITS.get(raw.dtype)
        if bit_depth is None and native is None:
            raise PolarInputError(source, f"give bit_depth for a raw mosaic of dtype {raw.dtype}")
        if native is not None and bit_depth is not None and bit_depth > native:  # it would read 2^(bit_depth - native) times too dark
            raise PolarInputError(source, f"{native}-bit raw mosaic, but bit_depth {bit_depth} was given: it holds at most "
                                  f"{native} bits")
        bit_depth = bit_depth or native
        full = float(2**bit_depth - 1)
        if native is not None and native == bit_depth:
            return full  # the dtype cannot hold values out of range
        # torch's uint16 lacks min/max; int64 holds every other integer dtype's values.
        raw = raw.to(torch.int64)
    low, high = float(raw.min()), float(raw.max())
    if low < 0 or high > full:
        what = "[0, 1] (or give bit_depth)" if full == 1.0 else f"the {bit_depth}-bit range [0, {int(full)}]"
        raise PolarInputError(source, f"raw values span [{low:g}, {high:g}], outside {what}")
    return full


def _checked_raw(raw: np.ndarray | Tensor, pattern: str, bit_depth: int | None, source: str) -> tuple[Tensor, float]:
    """The raw frame as a tensor and its full-scale value, after every input check."""
    if pattern not in MOSAIC_PATTERNS:
        raise PolarInputError(source, f"unknown mosaic pattern {pattern!r}, expected one of {MOSAIC_PATTERNS}")
    raw = _as_tensor(raw, source)
    if raw.ndim != 2:
        raise PolarInputError(source, f"raw mosaic must be 2-D (H, W), got shape {tuple(raw.shape)}")
    h, w = raw.shape
    step = 2 if pattern == "mono" else 4
    if h % step or w % step or min(h, w) < _MIN_SIZE[pattern]:
        raise PolarInputError(
            source,
            f"{pattern} mosaic size {h}x{w} must be a multiple of {step} and at least "
            f"{_MIN_SIZE[pattern]} pixels on each side",
        )
    if raw.dtype == torch.bool or raw.is_complex():
        raise PolarInputError(source, f"raw mosaic has unsupported dtype {raw.dtype}")
    full = _full_scale(raw, bit_depth, source)
    return raw, full


def _integer_array(raw: Tensor) -> np.ndarray:
    """CPU integer raw tensor -> uint8/uint16 numpy array (the dtypes OpenCV takes)."""
    return raw.numpy() if raw.dtype in _NATIVE_BITS else raw.to(torch.int32).numpy().astype(np.uint16)


def demosaic_polar(raw: np.ndarray | Tensor, pattern: str = "mono", bit_depth: int | None = None,
                   source: str = "") -> Tensor:
    """Split and interpolate a polarization-sensor raw frame into four full-resolution images.

    Agrees with ``polanalyser.demosaicing(raw, COLOR_PolarMono | COLOR_PolarRGB)`` divided by
    full scale (colour converted from BGR to RGB).

    Args:
        raw: :math:`(H, W)` raw mosaic, numpy array or tensor. Integer data (uint8, uint16, or any
            integer dtype with ``bit_depth``) is interpolated with OpenCV's integer rounding;
            float data is taken as already in [0, 1] unless ``bit_depth`` is given.
        pattern: ``"mono"`` (IMX250MZR) or ``"rgb"`` (IMX250MYR, RGGB on each sub-lattice).
        bit_depth: bits of the raw values; default 8 for uint8, 16 for uint16 (give 12 for a
            12-bit sensor stored in uint16).
        source: file the raw frame came from, named in error messages.

    Returns:
        :math:`(4, C, H, W)` float32 in [0, 1], angles 0/45/90/135 deg along dim 0, C = 1 (mono)
        or 3 (RGB), on the device of ``raw``.

    Raises:
        PolarInputError: unknown pattern, wrong ndim, odd (mono) or non-multiple-of-4 (rgb) or
            too small size, non-finite values, values outside the bit range, bad dtype.

    Example:
        >>> raw = np.tile(np.array([[90, 45], [135, 0]], dtype=np.uint8), (2, 2))
        >>> demosaic_polar(raw)[:, 0, 1, 1] * 255
        tensor([  0.,  45.,  90., 135.])
    """
    raw, full = _checked_raw(raw, pattern, bit_depth, source)
    if raw.is_floating_point():
        angles = _demosaic_torch(raw.to(torch.float32), pattern, exact_integer=False)
    elif raw.device.type == "cpu":
        # Same numbers as the torch path (tests pin it), several times faster on the CPU.
        angles = torch.from_numpy(_demosaic_opencv(_integer_array(raw), pattern))
    else:
        # int32 holds sums of four 16-bit samples (torch's uint16 lacks arithmetic).
        angles = _demosaic_torch(raw.to(torch.int32), pattern, exact_integer=True)
    return angles.to(torch.float32).div_(full)


def _demosaic_torch(x: Tensor, pattern: str, exact_integer: bool) -> Tensor:
    """(H, W) int32 or float32 mosaic -> (4, C, H, W) of the same dtype."""
    if pattern == "mono":
        return _demosaic_polar_lattices(x, exact_integer).unsqueeze(1)
    # Bayer-demosaic each quarter-resolution sub-lattice, then put it back in place.
    colour = torch.empty((3, *x.shape), dtype=x.dtype, device=x.device)
    for row, col in POLARIZER_LATTICE:
        colour[:, row::2, col::2] = _demosaic_bayer_rggb(x[row::2, col::2], exact_integer)
    return _demosaic_polar_lattices(colour, exact_integer).transpose(0, 1)


def _demosaic_bayer_sublattices(raw: np.ndarray) -> np.ndarray:
    """(H, W) uint8/uint16 colour-polarization mosaic -> (3, H, W) RGB, still polarization-mosaicked.

    Each polarizer's stride-2 sub-lattice is an RGGB mosaic, demosaiced on its own (OpenCV).
    """
    colour = np.empty((3, *raw.shape), dtype=raw.dtype)
    for row, col in POLARIZER_LATTICE:
        rgb = cv2.cvtColor(np.ascontiguousarray(raw[row::2, col::2]), cv2.COLOR_BayerBG2RGB)
        colour[:, row::2, col::2] = rgb.transpose(2, 0, 1)
    return colour


def _demosaic_opencv(raw: np.ndarray, pattern: str) -> np.ndarray:
    """(H, W) uint8/uint16 mosaic -> (4, C, H, W) float32 levels, OpenCV's bilinear Bayer.

    A polarization lattice pair read as a Bayer mosaic: in ``BayerBG`` layout the R site is
    (0, 0) = 90 deg and the B site (1, 1) = 0 deg; in ``BayerGR`` R is (1, 0) = 135 deg and
    B is (0, 1) = 45 deg. Green (the other two lattices) is discarded.
    """
    def polar(mono: np.ndarray) -> np.ndarray:
        bg = cv2.cvtColor(mono, cv2.COLOR_BayerBG2RGB)
        gr = cv2.cvtColor(mono, cv2.COLOR_BayerGR2RGB)
        return np.stack([bg[..., 2], gr[..., 2], bg[..., 0], gr[..., 0]])  # 0, 45, 90, 135

    if pattern == "mono":
        return polar(raw)[:, None].astype(np.float32)
    colour = _demosaic_bayer_sublattices(raw)
    out = np.empty((4, 3, *raw.shape), dtype=np.float32)
    for channel in range(3):
        out[:, channel] = polar(colour[channel])
    return out


@numba.njit(parallel=True, cache=True)
def _stokes_kernel(image: np.ndarray, full: float, out: np.ndarray) -> None:  # pragma: no cover (numba)
    """Interior of (3, C, H, W) float32 Stokes ``out`` from a (C, H, W) integer polarization mosaic.

    A pixel's own value is the sample of its lattice; the means of its left/right, up/down and
    4 diagonal neighbours (rounded half up, as OpenCV does) are those of the other three. With
    POLARIZER_LATTICE (90 at (0, 0), 45 at (0, 1), 135 at (1, 0), 0 at (1, 1)), on even rows
    s1, s2 = diagonal - own, horizontal - vertical where x + y is even (90 or 0 deg) and
    vertical - horizontal, own - diagonal where it is odd; odd rows flip both signs. Written
    without per-pixel branches on memory so that LLVM vectorizes the row loop.
    """
    channels, h, w = image.shape
    full_f, twice_full = np.float32(full), np.float32(2.0 * full)
    for job in numba.prange(channels * (h - 2)):
        c, y = job // (h - 2), job % (h - 2) + 1
        up, mid, down = image[c, y - 1], image[c, y], image[c, y + 1]
        out0, out1, out2 = out[0, c, y], out[1, c, y], out[2, c, y]
        sign = np.int32(1 - 2 * (y & 1))
        for x in range(1, w - 1):
            own = np.int32(mid[x])
            horizontal = (np.int32(mid[x - 1]) + np.int32(mid[x + 1]) + 1) >> 1
            vertical = (np.int32(up[x]) + np.int32(down[x]) + 1) >> 1
            diagonal = (
                np.int32(up[x - 1]) + np.int32(up[x + 1]) + np.int32(down[x - 1]) + np.int32(down[x + 1]) + 2
            ) >> 2
            a, b = (diagonal - own) * sign, (horizontal - vertical) * sign
            odd = ((x + y) & 1) == 1
            # Integer sums are exact in float32 and one correctly rounded division follows, as in
            # demosaic_polar's level / full scale.
            out0[x] = np.float32(own + horizontal + vertical + diagonal) / twice_full
            out1[x] = np.float32(-b if odd else a) / full_f
            out2[x] = np.float32(-a if odd else b) / full_f


def stokes_from_raw(raw: np.ndarray | Tensor, pattern: str = "mono", bit_depth: int | None = None,
                    source: str = "") -> Tensor:
    """Stokes images straight from a polarization-sensor raw frame (fused demosaic + Stokes).

    Equal (to float32 rounding) to ``stokes_from_intensities(demosaic_polar(raw, pattern,
    bit_depth))``, hence to polanalyser's demosaicing + calcStokes divided by full scale. Integer
    data on the CPU runs a fused kernel that never builds the four angle images (several times
    less memory traffic); float data and tensors on other devices take the unfused path.

    Args:
        raw: :math:`(H, W)` raw mosaic, numpy array or tensor (as for :func:`demosaic_polar`).
        pattern: ``"mono"`` (IMX250MZR) or ``"rgb"`` (IMX250MYR).
        bit_depth: bits of the raw values; default 8 for uint8, 16 for uint16.
        source: file the raw frame came from, named in error messages.

    Returns:
        :math:`(3, C, H, W)` float32 Stokes (s0, s1, s2) in units of full scale, C = 1 or 3 (RGB),
        on the device of ``raw``.

    Raises:
        PolarInputError: as :func:`demosaic_polar`.

    Example:
        >>> raw = np.tile(np.array([[0, 50], [50, 100]], dtype=np.uint8), (2, 2))  # 90/45/135/0
        >>> (stokes_from_raw(raw)[:, 0, 1, 1] * 255).round()
        tensor([100., 100.,   0.])
    """
    raw, full = _checked_raw(raw, pattern, bit_depth, source)
    if raw.is_floating_point() or raw.device.type != "cpu":
        return stokes_from_intensities(demosaic_polar(raw, pattern, bit_depth, source))
    array = _integer_array(raw)
    image = array[None] if pattern == "mono" else _demosaic_bayer_sublattices(array)
    # numpy asks the kernel for transparent huge pages on large arrays (torch.empty does not):
    # first-touch page faults on the 9 output planes otherwise cost more than the kernel.
    out = torch.from_numpy(np.empty((3, image.shape[0], *array.shape), dtype=np.float32))
    with numba_scheduling():
        _stokes_kernel(image, full, out.numpy())
    # OpenCV repeats the inner neighbour on the one-pixel border (columns first, then rows);
    # Stokes are linear per pixel, so repeating them is the same.
    out[..., 0], out[..., -1] = out[..., 1], out[..., -2]
    out[..., 0, :], out[..., -1, :] = out[..., 1, :], out[..., -2, :]
    return out


def mosaic_from_intensities(intensities: Tensor, pattern: str = "mono") -> Tensor:
    """Sample four polarizer-angle images onto the sensor mosaic (inverse of the split).

    Args:
        intensities: :math:`(*, 4, C, H, W)` images at 0/45/90/135 deg; C = 1 for ``"mono"``,
            C = 3 (RGB) for ``"rgb"``; H, W even (mono) or multiples of 4 (rgb).
        pattern: ``"mono"`` or ``"rgb"``.

    Returns:
        :math:`(*, H, W)` raw mosaic with the dtype of ``intensities``.

    Example:
        >>> images = torch.tensor([0.0, 45.0, 90.0, 135.0]).reshape(4, 1, 1, 1).expand(4, 1, 2, 2)
        >>> mosaic_from_intensities(images)
        tensor([[ 90.,  45.],
                [135.,   0.]])
    """
    if pattern not in MOSAIC_PATTERNS:
        raise ValueError(f"unknown mosaic pattern {pattern!r}, expected one of {MOSAIC_PATTERNS}")
    channels = 1 if pattern == "mono" else 3
    step = 2 if pattern == "mono" else 4
    shape = tuple(intensities.shape)
    if intensities.ndim < 4 or shape[-4] != 4 or shape[-3] != channels or shape[-2] % step or shape[-1] % step:
        raise ValueError(
            f"{pattern} mosaic needs intensities of shape (..., 4, {channels}, H, W) with H, W multiples "
            f"of {step}, got {shape}"
        )
    raw = torch.empty(shape[:-4] + shape[-2:], dtype=intensities.dtype, device=intensities.device)
    for angle, (row, col) in enumerate(POLARIZER_LATTICE):
        sub = intensities[..., angle, :, row::2, col::2]  # (*, C, H/2, W/2)
        if pattern == "mono":
            raw[..., row::2, col::2] = sub[..., 0, :, :]
        else:
            cell = raw[..., row::2, col::2]
            cell[..., 0::2, 0::2] = sub[..., 0, 0::2, 0::2]
            cell[..., 0::2, 1::2] = sub[..., 1, 0::2, 1::2]
            cell[..., 1::2, 0::2] = sub[..., 1, 1::2, 0::2]
            cell[..., 1::2, 1::2] = sub[..., 2, 1::2, 1::2]
    return raw

