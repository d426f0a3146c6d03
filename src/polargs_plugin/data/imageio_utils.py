"""Image and array file helpers shared by the dataset readers and writers.

Every reader here returns numpy arrays (H, W, C) in **RGB(A)** order (OpenCV's BGR is converted
once, here), validates what it read and raises :class:`PolarInputError` naming the file and the
problem. Every writer is atomic (a temporary file renamed on success).

Formats: PNG/TIFF/JPEG 8 or 16 bit (OpenCV), OpenEXR (the ``OpenEXR`` package, because some
OpenCV wheels cannot read EXR), Radiance ``.hdr`` (OpenCV, RGBE: about 8 significant bits per
pixel, shared exponent, no negative values) and ``.npy``. ``OpenEXR`` is imported only when an
EXR file is read or written, so reading PNG scenes for training does not need it.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import cv2
import numpy as np
from torch import Tensor

from polargs_plugin.io import PolarInputError, atomic_path

__all__ = [
    "UINT_MAX",
    "read_image",
    "write_png",
    "read_exr",
    "write_exr",
    "read_hdr",
    "write_hdr",
    "read_npy",
    "write_npy",
    "check_finite",
    "warn_narrow_range",
    "check_stokes",
    "to_hwc",
    "linear_to_srgb",
]

UINT_MAX = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}
"""Full-scale value of each integer image dtype."""

PathLike = str | os.PathLike


def _swap_rb(array: np.ndarray) -> np.ndarray:
    """BGR(A) <-> RGB(A) for (H, W, 3|4) arrays; other shapes are returned unchanged."""
    if array.ndim == 3 and array.shape[2] in (3, 4):
        return np.ascontiguousarray(array[..., [2, 1, 0] + list(range(3, array.shape[2]))])
    return array


def warn_narrow_range(peak: int, bits: int, path: PathLike, declared: str) -> None:
    """Warn when integer images taken as ``bits`` deep (more than 8) hold values only up to 255:
    8-bit data in a wider file, which reads ``(2^bits - 1) / 255`` times too dark.

    Args:
        peak: the largest value of the images (a view's four angle images, or a raw frame).
        bits: the bit depth they are read with.
        path: the (first) file, named in the warning.
        declared: what set ``bits``, e.g. ``"cameras.json declares bit_depth 16"``.
    """
    if bits > 8 and peak <= 255:
        full = 2**bits - 1
        warnings.warn(f"{path}: values only up to {peak} of {full} ({declared}): 8-bit data in a {bits}-bit file? "
                      f"It reads {full / 255:.0f} times too dark", stacklevel=3)


def check_finite(array: np.ndarray, path: PathLike) -> np.ndarray:
    """Raise :class:`PolarInputError` when ``array`` holds NaN or inf; return it otherwise."""
    if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).sum())
        raise PolarInputError(path, f"{bad} non-finite values (NaN or inf)")
    return array


def _require_file(path: Path) -> None:
    if not path.is_file():
        raise PolarInputError(path, "file not found")


def read_image(path: PathLike) -> np.ndarray:
    """Read an 8/16-bit integer image (PNG, TIFF, JPEG) unchanged.

    Returns:
        (H, W) or (H, W, C) uint8/uint16 array, colour channels in RGB(A) order.
    """
    path = Path(path)
    _require_file(path)
    array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if array is None:
        raise PolarInputError(path, "cannot be decoded as an image")
    if array.dtype not in UINT_MAX:
        raise PolarInputError(path, f"unsupported pixel type {array.dtype} (expected uint8 or uint16)")
    return _swap_rb(array)


def write_png(path: PathLike, array: np.ndarray, bit_depth: int = 8) -> Path:
    """Write (H, W) or (H, W, C) RGB(A) as an 8/16-bit PNG, atomically.

    Float input must lie in [0, 1] and is rounded to the nearest code; integer input is written
    as is (its dtype must match ``bit_depth``).
    """
    path = Path(path)
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    array = np.asarray(array)
    if np.issubdtype(array.dtype, np.floating):
        if not np.isfinite(array).all() or array.min() < 0 or array.max() > 1:
            raise PolarInputError(path, "PNG values must be finite and in [0, 1]")
        array = np.rint(array * UINT_MAX[np.dtype(dtype)]).astype(dtype)
    elif array.dtype != dtype:
        raise PolarInputError(path, f"{array.dtype} data cannot be written as a {bit_depth}-bit PNG")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), _swap_rb(array)):
            raise PolarInputError(path, "OpenCV could not write the PNG")
    return path


def read_exr(path: PathLike) -> np.ndarray:
    """Read an OpenEXR file as float32 (H, W, C).

    Channels are taken by name: R, G, B (in that order) if present, else Y, else the single
    channel. Layer prefixes such as ``View.Combined.R`` are accepted.
    """
    import OpenEXR

    path = Path(path)
    _require_file(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: channel.pixels for name, channel in exr.channels().items()}
    except Exception as err:  # OpenEXR raises RuntimeError with no file name
        raise PolarInputError(path, f"cannot be read as OpenEXR ({err})") from None
    by_suffix = {name.rsplit(".", 1)[-1]: pixels for name, pixels in channels.items()}
    if all(c in by_suffix for c in "RGB"):
        planes = [by_suffix[c] for c in "RGB"]
    elif "Y" in by_suffix:
        planes = [by_suffix["Y"]]
    elif len(channels) == 1:
        planes = list(channels.values())
    else:
        raise PolarInputError(path, f"no R,G,B or Y channels (found {sorted(channels)})")
    array = np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1)
    return check_finite(array, path)


def write_exr(path: PathLike, array: np.ndarray) -> Path:
    """Write (H, W, 1|3) float data as a float32 EXR (Y or R, G, B channels), atomically."""
    import OpenEXR

    path = Path(path)
    array = np.asarray(array, dtype=np.float32)
    if array.ndim == 2:
        array = array[..., None]
    if array.shape[2] not in (1, 3):
        raise ValueError(f"EXR writer takes 1 or 3 channels, got shape {array.shape}")
    names = "Y" if array.shape[2] == 1 else "RGB"
    channels = {name: np.ascontiguousarray(array[..., i]) for i, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as exr:
            exr.write(str(tmp))
    return path


def read_hdr(path: PathLike) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` file as float32 (H, W, 3) RGB."""
    path = Path(path)
    _require_file(path)
    array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if array is None or array.dtype != np.float32:
        raise PolarInputError(path, "cannot be decoded as a Radiance HDR image")
    return check_finite(_swap_rb(array), path)


def write_hdr(path: PathLike, array: np.ndarray) -> Path:
    """Write non-negative (H, W, 3) RGB float data as Radiance RGBE, atomically."""
    path = Path(path)
    array = np.asarray(array, dtype=np.float32)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"HDR writer takes (H, W, 3), got shape {array.shape}")
    if not np.isfinite(array).all() or array.min() < 0:
        raise PolarInputError(path, "Radiance HDR holds only finite non-negative values")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), _swap_rb(array)):
            raise PolarInputError(path, "OpenCV could not write the HDR image")
    return path


def read_npy(path: PathLike) -> np.ndarray:
    """Load a numeric ``.npy`` array (no pickles), checking that floats are finite."""
    path = Path(path)
    _require_file(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise PolarInputError(path, f"cannot be read as .npy ({err})") from None
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == bool):
        raise PolarInputError(path, f"non-numeric dtype {array.dtype}")
    return check_finite(array, path)


def write_npy(path: PathLike, array: np.ndarray) -> Path:
    """Save an array as ``.npy``, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        np.save(tmp, np.asarray(array))
    return path


def to_hwc(tensor: Tensor) -> np.ndarray:
    """(C, H, W) tensor -> (H, W, C) numpy array."""
    return tensor.detach().cpu().numpy().transpose(1, 2, 0)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) for linear values in [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def check_stokes(planes: list[np.ndarray], paths: list[PathLike]) -> np.ndarray:
    """Stack per-file Stokes planes (each (H, W) or (H, W, C)) into (3, C, H, W) float32.

    Raises :class:`PolarInputError` naming the offending file when shapes differ or when s0 is
    zero (or negative) everywhere, which is an all-dark image.
    """
    planes = [p[..., None] if p.ndim == 2 else p for p in planes]
    for plane, path in zip(planes, paths):
        if plane.ndim != 3 or plane.shape != planes[0].shape:
            raise PolarInputError(path, f"shape {plane.shape} differs from {paths[0]} {planes[0].shape}")
    if not planes[0].max() > 0:
        raise PolarInputError(paths[0], "all-dark image: s0 is zero everywhere")
    return np.stack([p.transpose(2, 0, 1) for p in planes]).astype(np.float32)
