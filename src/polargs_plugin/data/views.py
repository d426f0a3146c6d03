"""What the dataset readers do alike when they turn a folder's files into views.

- :class:`ViewCollector` builds a reader's views one at a time: the :class:`View` itself, GT
  normal maps brought into the OpenCV camera frame (the stored frame told from the silhouettes,
  :func:`load_normal_gt`), the Stokes scale checked against the 8-bit pictures of the first
  :data:`SCALE_CHECK_VIEWS` views, and one warning at the end when some normal maps were stored
  in another frame.
- :func:`read_mask` reads an object mask from an image's first channel.
- :func:`warn_unused_files` names, in one warning, the files a dataset holds for views its
  reader does not read (a view left out of the camera file, a Stokes component without its s0).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from polargs_plugin.data.checks import orient_normal_map, warn_image_scale
from polargs_plugin.data.imageio_utils import UINT_MAX, read_exr, read_image, read_npy
from polargs_plugin.data.resolution import prepare_view
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View

__all__ = [
    "SCALE_CHECK_VIEWS",
    "ViewCollector",
    "above_half_scale",
    "load_normal_gt",
    "read_mask",
    "read_normal_map",
    "warn_unused_files",
]

#: How many unused files :func:`warn_unused_files` names (the count is always given).
UNUSED_NAMED = 5

SCALE_CHECK_VIEWS = 3
"""Number of views whose 8-bit picture is compared with the Stokes scale."""

# Below this mean cosine between the normal map's and the silhouette's edge directions the
# frame of a normal map cannot be told.
_MIN_FRAME_AGREEMENT = 0.3


def read_normal_map(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """(3, H, W) float64 normals as stored (``.npy``/``.exr`` float, PNG coded 2 v / max - 1)."""
    if path.suffix == ".npy":
        values = read_npy(path).astype(np.float64)
    elif path.suffix == ".exr":
        values = read_exr(path).astype(np.float64)
    else:
        raw = read_image(path)
        values = raw.astype(np.float64) / UINT_MAX[raw.dtype] * 2.0 - 1.0
    if values.ndim != 3 or values.shape[2] < 3 or values.shape[:2] != shape:
        raise PolarInputError(path, f"normal map has shape {values.shape}, expected ({shape[0]}, {shape[1]}, 3)")
    if not np.isfinite(values[..., :3]).all():
        raise PolarInputError(path, "normal map has NaN or infinite values")
    return values[..., :3].transpose(2, 0, 1)


def load_normal_gt(path: Path, mask: Tensor | None, w2c: np.ndarray, shape: tuple[int, int]) -> tuple[Tensor, str]:
    """GT normals of one view in the OpenCV camera frame, and the frame they were stored in."""
    raw = read_normal_map(path, shape)
    valid = np.linalg.norm(raw, axis=0) > 0.5
    region = valid if mask is None else (mask[0].numpy() & valid)
    if not region.any():
        raise PolarInputError(path, "normal map is empty inside the object mask")
    normals, frame, score = orient_normal_map(raw, region, w2c)
    if score < _MIN_FRAME_AGREEMENT:
        raise PolarInputError(path, f"cannot tell the frame of the normal map (best: {frame}, silhouette agreement {score:.2f})")
    return torch.from_numpy(normals), frame


def above_half_scale(first: np.ndarray) -> np.ndarray:
    """Mask pixels of an integer image's first channel: valid above half of full scale."""
    return first > UINT_MAX[first.dtype] / 2


def read_mask(
    path: Path,
    shape: tuple[int, int],
    valid: Callable[[np.ndarray], np.ndarray] = above_half_scale,
    matched: str = "the Stokes",
) -> Tensor:
    """(1, H, W) bool object mask from the first channel of the image at ``path``.

    Args:
        path: the mask image.
        shape: (H, W) the mask must have.
        valid: the valid pixels of the image's first channel (its own dtype).
        matched: what ``shape`` is the size of, named when the sizes differ.
    """
    values = read_image(path)
    if values.shape[:2] != shape:
        raise PolarInputError(path, f"size {values.shape[:2]} differs from {matched} {shape}")
    first = values if values.ndim == 2 else values[..., 0]
    return torch.from_numpy(valid(first))[None]


@dataclass
class ViewCollector:
    """A reader's views, built one at a time with the checks every reader makes alike.

    Attributes:
        folder: the dataset folder; each view's ``source`` and named in the frame warning.
        check_scale: compare the 8-bit pictures of the first :data:`SCALE_CHECK_VIEWS` views with
            their Stokes and warn on a mismatch (:func:`~polargs_plugin.data.checks.warn_image_scale`).
        resolution: each view is kept at this resolution, its float images as float16
            (:func:`~polargs_plugin.data.resolution.prepare_view`), as it is added.
        views: the views added so far.
        frames: the frames the GT normal maps added so far were stored in.
    """

    folder: Path
    check_scale: bool = False
    resolution: int = 1
    views: list[View] = field(default_factory=list)
    frames: set[str] = field(default_factory=set)

    def normal_gt(self, path: Path | None, mask: Tensor | None, w2c: np.ndarray, shape: tuple[int, int]) -> Tensor | None:
        """GT normals of the next view from ``path`` (None: it has none), OpenCV camera frame."""
        if path is None:
            return None
        normals, frame = load_normal_gt(path, mask, w2c, shape)
        self.frames.add(frame)
        return normals

    def check_picture(self, pictures: Sequence[Path], stokes: np.ndarray, mask: Tensor | None) -> None:
        """Check the Stokes scale of the next view against its 8-bit picture, the first of
        ``pictures`` that exists (when checked, and when the picture is 8-bit and has the Stokes'
        size); warns at the reader's caller."""
        if not (self.check_scale and len(self.views) < SCALE_CHECK_VIEWS):
            return
        picture = next((path for path in pictures if path.is_file()), None)
        if picture is None:
            return
        image = read_image(picture)
        if image.dtype == np.uint8 and image.shape[:2] == stokes.shape[-2:]:
            warn_image_scale(str(picture), stokes, image[..., :3] if image.ndim == 3 else image,
                             None if mask is None else mask[0].numpy(), stacklevel=3)

    def add(
        self,
        name: str,
        K: np.ndarray,
        world_to_camera: np.ndarray,
        stokes: np.ndarray | Tensor,
        mask: Tensor | None = None,
        normal_gt: Tensor | None = None,
    ) -> None:
        """Append a view: K and world_to_camera as given (float64), Stokes as float32, then at
        :attr:`resolution` and compact (:func:`~polargs_plugin.data.resolution.prepare_view`)."""
        view = View(
            name=name,
            K=torch.from_numpy(K),
            world_to_camera=torch.from_numpy(world_to_camera),
            stokes=torch.as_tensor(stokes, dtype=torch.float32),
            mask=mask,
            normal_gt=normal_gt,
            source=str(self.folder),
        )
        self.views.append(prepare_view(view, self.resolution))

    def finish(self) -> list[View]:
        """The views; warns (at the reader's caller) when GT normal maps were stored in a frame
        other than OpenCV's."""
        if self.frames - {"opencv"}:
            warnings.warn(f"{self.folder}: GT normal maps stored in the {'/'.join(sorted(self.frames))} frame; converted "
                          "to the OpenCV camera frame (told from the silhouettes)", stacklevel=3)
        return self.views


def warn_unused_files(folder: Path, files: Iterable[Path], used: Collection[str], view_of: Callable[[Path], str],
                      why: str, stacklevel: int = 3) -> list[Path]:
    """Warn once about the ``files`` whose view (``view_of(file)``) is not among the ``used``
    views: data the dataset holds and the training would silently go without. Returns them.

    Args:
        folder: the dataset folder (the warning names it, and the files relative to it).
        files: the candidate files (e.g. every angle image and mask of the folder).
        used: the names of the views the reader reads.
        view_of: the view a file belongs to.
        why: why they are not read, for the message (e.g. "not listed in cameras.json").
        stacklevel: as :func:`warnings.warn`'s, to place the warning at the reader's caller.
    """
    unused = sorted(path for path in files if view_of(path) not in used)
    if unused:
        views = sorted({view_of(path) for path in unused})
        named = ", ".join(str(path.relative_to(folder)) for path in unused[:UNUSED_NAMED])
        more = f" and {len(unused) - UNUSED_NAMED} more" if len(unused) > UNUSED_NAMED else ""
        warnings.warn(f"{folder}: {len(unused)} file(s) of {len(views)} view(s) not read ({why}): {named}{more}",
                      stacklevel=stacklevel)
    return unused
