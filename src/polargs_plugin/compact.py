"""Compact storage of image data: what a :class:`~polargs_plugin.types.View` keeps in memory and
what the maps cache keeps on disk, decoded to full precision when read.

A view of a real capture holds tens of millions of pixels; as float32 its Stokes alone take 36
bytes per pixel (RGB). The readers therefore keep each image in the smallest form that gives back
what was read:

=====================  =============================================  ===========================
stored                 when                                           decoded
=====================  =============================================  ===========================
:class:`AngleImages`   8/16-bit polarizer-angle images at full size    Stokes from the integer
                       (scene folders, polar folders, raw mosaics)     images, bit for bit as read
:class:`Half`          float data (EXR/HDR/npy Stokes, GT normals of   float32 (float16 rounding:
                       other formats), images averaged by              relative 2^-11 = 4.9e-4)
                       ``--resolution``
:class:`Deferred`      a scene folder's GT maps (``.npy`` files)       read from the file when used
:class:`Bits`          masks of a prepared view                       bool, as given
:class:`Plain`         a tensor given as it is (library use)          the tensor itself
=====================  =============================================  ===========================

Every stored form answers ``shape``, ``dtype``
(decoded), ``device`` and ``nbytes`` without decoding, and :meth:`decode` allocates a fresh
full-precision tensor each time it is called: callers keep the decoded tensor only while they
use it (one view at a time).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import torch
from torch import Tensor

from polargs_plugin.optics.stokes import stokes_from_intensities

__all__ = ["HALF_MAX", "HALF_RELATIVE_ERROR", "AngleImages", "Bits", "Deferred", "Half", "Plain", "Stored",
           "as_stored", "compact"]

#: Largest finite float16 value; float data beyond it is kept as float32.
HALF_MAX = 65504.0
#: Relative rounding error of float16 (half an ulp at 1: 2^-11), the tolerance of a float16 round trip.
HALF_RELATIVE_ERROR = 2.0**-11


class _Held:
    """A tensor held in memory as it is stored (what :class:`Plain` and :class:`Half` share)."""

    __slots__ = ("values",)

    def __init__(self, values: Tensor):
        self.values = values

    @property
    def shape(self) -> torch.Size:
        return self.values.shape

    @property
    def device(self) -> torch.device:
        return self.values.device

    @property
    def nbytes(self) -> int:
        return self.values.numel() * self.values.element_size()

    def all_finite(self) -> bool:
        return not self.values.is_floating_point() or bool(torch.isfinite(self.values).all())


class Plain(_Held):
    """A tensor kept as it is; :meth:`decode` returns that same tensor (no copy).

    Attributes:
        values: the tensor.
    """

    __slots__ = ()

    @property
    def dtype(self) -> torch.dtype:
        return self.values.dtype

    def decode(self) -> Tensor:
        return self.values

    def to(self, device: torch.device | str) -> Plain:
        return Plain(self.values.to(device))


class Half(_Held):
    """Float data stored as float16, decoded to ``dtype`` (default float32).

    Attributes:
        values: the float16 tensor.
        decoded_dtype: the dtype :meth:`decode` returns.
    """

    __slots__ = ("decoded_dtype",)

    def __init__(self, values: Tensor, decoded_dtype: torch.dtype = torch.float32):
        if values.dtype != torch.float16:
            raise TypeError(f"Half holds float16 values, got {values.dtype}")
        super().__init__(values)
        self.decoded_dtype = decoded_dtype

    @property
    def dtype(self) -> torch.dtype:
        return self.decoded_dtype

    def decode(self) -> Tensor:
        return self.values.to(self.decoded_dtype)

    def to(self, device: torch.device | str) -> Half:
        return Half(self.values.to(device), self.decoded_dtype)


class Bits:
    """A bool tensor packed eight values to a byte; :meth:`decode` unpacks it.

    Attributes:
        packed: (ceil(N / 8),) uint8, value ``i`` of the flattened tensor in bit ``i % 8`` of byte
            ``i // 8``.
        shape: the shape of the bool tensor.

    Example:
        >>> mask = torch.tensor([[True, False, True], [False, False, True]])
        >>> bits = Bits.pack(mask)
        >>> bits.nbytes, torch.equal(bits.decode(), mask)
        (1, True)
    """

    __slots__ = ("packed", "shape")

    def __init__(self, packed: Tensor, shape: tuple[int, ...]):
        self.shape = torch.Size(shape)
        if packed.dtype != torch.uint8 or packed.shape != ((self.shape.numel() + 7) // 8,):
            raise ValueError(f"Bits needs ({(self.shape.numel() + 7) // 8},) uint8 for shape {tuple(self.shape)}, "
                             f"got {packed.dtype} {tuple(packed.shape)}")
        self.packed = packed

    @classmethod
    def pack(cls, values: Tensor) -> Bits:
        """``values`` (bool, any shape) packed."""
        if values.dtype != torch.bool:
            raise TypeError(f"Bits packs bool tensors, got {values.dtype}")
        flat = values.reshape(-1)
        padded = torch.nn.functional.pad(flat.to(torch.uint8), (0, -flat.numel() % 8)).reshape(-1, 8)
        return cls((padded << _BIT_SHIFTS.to(values.device)).sum(1, dtype=torch.uint8), values.shape)

    @property
    def dtype(self) -> torch.dtype:
        return torch.bool

    @property
    def device(self) -> torch.device:
        return self.packed.device

    @property
    def nbytes(self) -> int:
        return self.packed.numel()

    def decode(self) -> Tensor:
        bits = (self.packed[:, None] >> _BIT_SHIFTS.to(self.packed.device)) & 1
        return bits.reshape(-1)[: self.shape.numel()].bool().reshape(self.shape)

    def all_finite(self) -> bool:
        return True

    def to(self, device: torch.device | str) -> Bits:
        return Bits(self.packed.to(device), self.shape)


_BIT_SHIFTS = torch.arange(8, dtype=torch.uint8)


class AngleImages:
    """Stokes kept as the integer polarizer-angle images they were computed from.

    :meth:`decode` gives ``stokes_from_intensities(angles / full_scale)`` in float32: the same
    numbers as reading the images into float32 and computing the Stokes at once.

    Attributes:
        angles: :math:`(4, C, H, W)` uint8 or uint16 images at 0/45/90/135 deg.
        full_scale: the level of full intensity (255, 65535, or 2^bits - 1).
    """

    __slots__ = ("angles", "full_scale", "shape")

    def __init__(self, angles: Tensor, full_scale: float):
        if angles.ndim != 4 or angles.shape[0] != 4 or angles.is_floating_point():
            raise ValueError(f"AngleImages needs (4, C, H, W) integer images, got {angles.dtype} {tuple(angles.shape)}")
        self.angles, self.full_scale = angles, float(full_scale)
        self.shape = torch.Size((3, *angles.shape[1:]))  # of the decoded Stokes

    @property
    def dtype(self) -> torch.dtype:
        return torch.float32

    @property
    def device(self) -> torch.device:
        return self.angles.device

    @property
    def nbytes(self) -> int:
        return self.angles.numel() * self.angles.element_size()

    def intensities(self) -> Tensor:
        """:math:`(4, C, H, W)` float32 angle images in [0, 1] (at full scale 1)."""
        return self.angles.to(torch.float32) / torch.tensor(self.full_scale, dtype=torch.float32)

    def decode(self) -> Tensor:
        return stokes_from_intensities(self.intensities())

    def all_finite(self) -> bool:
        return True

    def to(self, device: torch.device | str) -> AngleImages:
        return AngleImages(self.angles.to(device), self.full_scale)


class Deferred:
    """Data left in its file until it is read: :meth:`decode` calls ``load`` each time (e.g. the
    ground-truth maps of a scene folder, which training never reads).

    Attributes:
        load: returns the tensor (on the CPU), raising PolarInputError naming the file when it is bad.
        shape: the shape ``load`` returns.
        dtype: the dtype ``load`` returns.
        device: where :meth:`decode` puts the tensor.
    """

    __slots__ = ("load", "shape", "dtype", "device")

    def __init__(self, load: Callable[[], Tensor], shape: tuple[int, ...], dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu"):
        self.load, self.shape, self.dtype, self.device = load, torch.Size(shape), dtype, torch.device(device)

    @property
    def nbytes(self) -> int:
        return 0

    def decode(self) -> Tensor:
        return self.load().to(self.device)

    def all_finite(self) -> bool:
        values = self.decode()
        return not values.is_floating_point() or bool(torch.isfinite(values).all())

    def to(self, device: torch.device | str) -> "Deferred":
        return Deferred(self.load, self.shape, self.dtype, device)

    def then(self, transform: Callable[[Tensor], Tensor], shape: tuple[int, ...]) -> Deferred:
        """The data ``transform``-ed when read (e.g. resampled), of the new ``shape`` (picklable
        when ``transform`` and ``load`` are)."""
        return Deferred(partial(_transformed, transform, self.load), shape, self.dtype, self.device)


def _transformed(transform: Callable[[Tensor], Tensor], load: Callable[[], Tensor]) -> Tensor:
    return transform(load())


Stored = Plain | Half | Bits | AngleImages | Deferred
"""Any stored form: ``shape``, ``dtype``, ``device``, ``nbytes``, ``decode()``, ``all_finite()``, ``to(device)``."""


def as_stored(value: Tensor | Stored) -> Stored:
    """``value`` as a stored form: a stored form as it is, a tensor as :class:`Plain`."""
    if isinstance(value, (Plain, Half, Bits, AngleImages, Deferred)):
        return value
    if isinstance(value, Tensor):
        return Plain(value)
    raise TypeError(f"expected a tensor or a stored form (Plain, Half, Bits, AngleImages, Deferred), got {type(value).__name__}")


def compact(value: Tensor | Stored) -> Stored:
    """The smallest faithful form of ``value``: bool tensors become :class:`Bits`; float32/64
    tensors whose values float16 holds (finite, magnitude at most :data:`HALF_MAX`) become
    :class:`Half` (decoded to their own dtype); other tensors (integer, larger floats) and stored
    forms stay as they are."""
    stored = as_stored(value)
    if isinstance(stored, Plain) and stored.dtype == torch.bool:
        return Bits.pack(stored.values)
    if not isinstance(stored, Plain) or not stored.values.is_floating_point() or stored.dtype == torch.float16:
        return stored
    values = stored.values
    if values.numel() and not bool((values.abs() <= HALF_MAX).all()):  # also False for NaN
        return stored
    return Half(values.to(torch.float16), values.dtype)
