"""Cameras of the graphdeco (Inria 3DGS) family <-> :class:`View`.

graphdeco, GOF, PGSR, GaussianPro and 2DGS store a camera as ``R`` (the world-to-camera rotation
*transposed*, i.e. camera-to-world), ``T`` (world-to-camera translation), ``FoVx`` / ``FoVy`` in
radians and the image size; ``world_view_transform`` is the transposed 4x4 world-to-camera.
They keep no K: the principal point is the image centre, which with this project's pixel
centres at +0.5 is (W / 2, H / 2). Axes are OpenCV in both, so no axis flip is involved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from polargs_plugin.data.cameras import intrinsics_from_fov, inria_to_world_to_camera, world_to_camera_to_inria
from polargs_plugin.types import View

__all__ = ["GraphdecoCamera", "view_from_graphdeco", "graphdeco_from_view", "world_view_transform"]

# A principal point further than this (pixels) from the centre cannot be expressed by a FoV camera.
_CENTRE_TOLERANCE_PX = 1e-3


@dataclass
class GraphdecoCamera:
    """The camera fields a graphdeco-family trainer stores.

    Attributes:
        R: (3, 3) float64, the world-to-camera rotation transposed (camera-to-world rotation).
        T: (3,) float64 world-to-camera translation.
        FoVx, FoVy: horizontal and vertical field of view in radians.
        image_width, image_height: image size in pixels.
    """

    R: np.ndarray
    T: np.ndarray
    FoVx: float
    FoVy: float
    image_width: int
    image_height: int

    @property
    def world_view_transform(self) -> Tensor:
        """(4, 4) float32 transposed world-to-camera, as the trainers store it."""
        return world_view_transform(self.R, self.T)


def world_view_transform(R: np.ndarray, T: np.ndarray) -> Tensor:
    """graphdeco's ``world_view_transform``: the (4, 4) world-to-camera, transposed, float32."""
    return torch.from_numpy(inria_to_world_to_camera(np.asarray(R), np.asarray(T)).T.copy()).float()


def _to_numpy(value: Any) -> np.ndarray:
    if isinstance(value, Tensor):
        return value.detach().cpu().double().numpy()
    return np.asarray(value, dtype=np.float64)


def view_from_graphdeco(
    camera: Any,
    stokes: Tensor,
    *,
    mask: Tensor | None = None,
    name: str | None = None,
    source: str = "",
) -> View:
    """A :class:`View` of a graphdeco-family camera object with the view's polarimetric data.

    Args:
        camera: an object with ``R`` (camera-to-world rotation, i.e. w2c rotation transposed),
            ``T``, ``FoVx``, ``FoVy``, ``image_width``, ``image_height`` and (unless ``name``
            is given) ``image_name``.
        stokes: (3, C, H, W) Stokes of the view, H x W = the camera's image size.
        mask: optional (1, H, W) bool object mask.
        name: view name (default ``camera.image_name``).
        source: where the data came from, for error messages.

    Returns:
        The View: K from the FoVs (centred principal point), world_to_camera = [R^T | T].
    """
    width, height = int(camera.image_width), int(camera.image_height)
    if tuple(stokes.shape[-2:]) != (height, width):
        raise ValueError(
            f"view '{name or camera.image_name}': Stokes are {tuple(stokes.shape[-2:])} (H, W) but the "
            f"trainer's camera is {height}x{width}; load the polarimetric data at the trainer's resolution"
        )
    K = intrinsics_from_fov(float(camera.FoVx), float(camera.FoVy), width, height)
    w2c = inria_to_world_to_camera(_to_numpy(camera.R), _to_numpy(camera.T))
    return View(
        name=str(name if name is not None else camera.image_name),
        K=torch.from_numpy(K),
        world_to_camera=torch.from_numpy(w2c),
        stokes=stokes,
        mask=mask,
        source=source,
    )


def graphdeco_from_view(view: View) -> GraphdecoCamera:
    """The graphdeco camera fields of a view (inverse of :func:`view_from_graphdeco`).

    Raises:
        ValueError: when the view's K has skew or a principal point off the image centre,
            which a FoV camera cannot express.
    """
    K = view.K.double().cpu().numpy()
    off_centre = max(abs(K[0, 2] - view.width / 2), abs(K[1, 2] - view.height / 2))
    if abs(K[0, 1]) > 1e-9 or off_centre > _CENTRE_TOLERANCE_PX:
        raise ValueError(
            f"view '{view.name}': K has skew {K[0, 1]:g} / principal point {K[0, 2]:g}, {K[1, 2]:g} "
            f"off the image centre ({view.width / 2:g}, {view.height / 2:g}); a graphdeco camera stores FoV only"
        )
    R, T = world_to_camera_to_inria(view.world_to_camera.double().cpu().numpy())
    return GraphdecoCamera(
        R=R,
        T=T,
        FoVx=2 * math.atan(view.width / (2 * K[0, 0])),
        FoVy=2 * math.atan(view.height / (2 * K[1, 1])),
        image_width=view.width,
        image_height=view.height,
    )
