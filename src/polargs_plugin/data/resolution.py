"""Reading a dataset at a lower resolution (``--resolution``), and keeping its views compact.

``resolution`` has the meaning of the upstream trainers' ``-r``: 1, 2, 4 or 8 divides the image
size (``round(W / r)`` x ``round(H / r)``); a number above 8 is a target width (the height keeps
the aspect ratio, rounded). Everything that is measured per pixel is resampled together, so that
pixel centres stay where the cameras put them (docs/conventions.md: pixel (u, v) has its centre
at (u + 0.5, v + 0.5)):

- the new pixel u' covers the old interval [u' / s, (u' + 1) / s) with s = W' / W (rows alike,
  with H' / H): its Stokes are the exact area average of the old pixels over that interval
  (Stokes are linear in the light, so averaging them is averaging the light);
- masks and ground-truth maps take the old pixel that holds the new pixel's centre (nearest);
- K is scaled about the image origin: K' = diag(W'/W, H'/H, 1) K, which maps the old centre
  (u' + 0.5) / s of a new pixel to u' + 0.5.

:func:`prepare_view` resamples a view this way and stores its float images as float16
(:mod:`polargs_plugin.compact`); the readers call it on each view as they read it, so the
full-size float images of only one view exist at a time.
"""

from __future__ import annotations

from functools import partial

import torch
from torch import Tensor

from polargs_plugin.compact import Deferred, compact
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View

__all__ = [
    "DIVISORS",
    "area_resize",
    "check_resolution",
    "nearest_resize",
    "prepare_view",
    "resample_view",
    "scale_intrinsics",
    "target_size",
]

#: ``--resolution`` values that divide the size; any value above the largest is a target width.
DIVISORS = (1, 2, 4, 8)


def check_resolution(resolution: int) -> int:
    """``resolution`` when it is 1, 2, 4, 8 or above 8, else ValueError saying what it may be."""
    if isinstance(resolution, bool) or not isinstance(resolution, int) or not (
            resolution in DIVISORS or resolution > DIVISORS[-1]):
        raise ValueError(f"resolution must be 1, 2, 4 or 8 (divide the size) or a target width above 8 pixels, "
                         f"got {resolution!r}")
    return resolution


def target_size(width: int, height: int, resolution: int) -> tuple[int, int]:
    """(W', H') of images of ``width`` x ``height`` read at ``resolution``.

    Raises:
        ValueError: a bad ``resolution``, or a target width above ``width`` (no upsampling).
    """
    check_resolution(resolution)
    if resolution in DIVISORS:
        return max(1, round(width / resolution)), max(1, round(height / resolution))
    if resolution > width:
        raise ValueError(f"resolution {resolution} is a target width above the images' width {width} "
                         f"(use at most {width}, or 1 for the full size)")
    return resolution, max(1, round(height * resolution / width))


def _area_along(values: Tensor, new: int, dim: int) -> Tensor:
    """Exact area average of float64 ``values`` along ``dim`` onto ``new`` equal cells.

    The integral of the piecewise-constant row is piecewise linear: it is read at each cell's
    edges from the cumulative sum, so a cell edge inside an old pixel takes that pixel's share."""
    old = values.shape[dim]
    if old == new:
        return values
    moved = values.movedim(dim, -1)
    cumulative = torch.nn.functional.pad(moved.cumsum(-1), (1, 0))  # integral at the old pixel edges
    edges = torch.arange(new + 1, dtype=torch.int64) * old  # cell edges in units of 1 / new old pixels
    whole, part = edges // new, (edges % new).to(torch.float64) / new
    inside = moved[..., whole.clamp(max=old - 1)]
    integral = cumulative[..., whole] + part * inside
    return ((integral[..., 1:] - integral[..., :-1]) * (new / old)).movedim(-1, dim)


def area_resize(image: Tensor, size: tuple[int, int]) -> Tensor:
    """(..., H, W) float -> (..., H', W') exact area average, ``size`` = (W', H'); float32.

    Computed in float64 one leading slice at a time (no large float64 temporary)."""
    width, height = size
    flat = image.reshape(-1, *image.shape[-2:])
    out = torch.empty((flat.shape[0], height, width), dtype=torch.float32, device=image.device)
    for index, plane in enumerate(flat):
        out[index] = _area_along(_area_along(plane.to(torch.float64), width, 1), height, 0)
    return out.reshape(*image.shape[:-2], height, width)


def _nearest_index(old: int, new: int, device: torch.device) -> Tensor:
    """Old pixel holding the centre (i + 0.5) * old / new of each new pixel i."""
    return ((2 * torch.arange(new, dtype=torch.int64, device=device) + 1) * old) // (2 * new)


def nearest_resize(image: Tensor, size: tuple[int, int]) -> Tensor:
    """(..., H, W) -> (..., H', W'): each new pixel takes the old pixel holding its centre (any dtype)."""
    width, height = size
    rows = _nearest_index(image.shape[-2], height, image.device)
    cols = _nearest_index(image.shape[-1], width, image.device)
    return image.index_select(-2, rows).index_select(-1, cols)


def scale_intrinsics(K: Tensor, old_size: tuple[int, int], new_size: tuple[int, int]) -> Tensor:
    """K of the images resampled from ``old_size`` to ``new_size`` (both (W, H)): its first row
    times W'/W, its second times H'/H (pixel centres at +0.5 stay pixel centres)."""
    scale = torch.tensor([new_size[0] / old_size[0], new_size[1] / old_size[1], 1.0], dtype=K.dtype, device=K.device)
    return K * scale[:, None]


def resample_view(view: View, resolution: int) -> View:
    """``view`` at ``resolution`` (module docstring); the view itself when the size is unchanged.

    Raises:
        PolarInputError: naming the view's source: a bad ``resolution`` or a target width above
            the view's width.
    """
    old = (view.width, view.height)
    try:
        new = target_size(*old, resolution)
    except ValueError as err:
        raise PolarInputError(view.source or view.name, str(err)) from None
    if new == old:
        return view
    changes = {"stokes": area_resize(view.stokes, new), "K": scale_intrinsics(view.K, old, new)}
    for name in ("mask", "normal_gt", "depth_gt"):
        stored = view.stored(name)
        if isinstance(stored, Deferred):  # still in its file: resampled when read
            changes[name] = stored.then(partial(nearest_resize, size=new), (*stored.shape[:-2], new[1], new[0]))
        elif stored is not None:
            changes[name] = nearest_resize(stored.decode(), new)
    return view.replaced(**changes)


def prepare_view(view: View, resolution: int = 1) -> View:
    """``view`` at ``resolution`` with its float images stored as float16 where float16 holds them
    and its mask as bits (:func:`polargs_plugin.compact.compact`); integer angle images stay as they are."""
    view = resample_view(view, resolution)
    return view.replaced(**{name: compact(view.stored(name)) for name in ("stokes", "mask", "normal_gt", "depth_gt")
                            if view.stored(name) is not None})
