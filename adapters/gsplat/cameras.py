"""gsplat cameras (``viewmats``, ``Ks``) <-> :class:`polargs_plugin.View`.

gsplat's ``rasterization(..., viewmats, Ks, width, height)`` takes per camera a 4x4
world-to-camera matrix in the OpenCV frame (x right, y down, z forward; column vectors, *not*
transposed) and a 3x3 pinhole K. That is this project's convention exactly:

- frame and matrix layout: gsplat ``docs/source/conventions/data_conventions.rst`` and
  ``cuda/_torch_impl.py::_world_to_cam`` (``means_c = R @ means + t`` with R, t the top rows of
  ``viewmats``);
- pixel centres at +0.5: the projection is ``means2d = K[:2] @ x_cam / z`` with no offset
  (``cuda/_torch_impl.py::_persp_proj``), and the rasterizer evaluates pixel (column j, row i)
  at ``(j + 0.5, i + 0.5)`` (``cuda/csrc/RasterizeToPixels3DGSFwd.cu``: ``px = (float)j + 0.5f``,
  ``_torch_impl.py::accumulate``: ``pixel_coords = ... + 0.5``); ``gsplat.utils.depth_to_points``
  back-projects pixel x through ``(x - cx + 0.5) / fx``. So a point projecting to
  ``u = fx x / z + cx`` lights the pixel ``floor(u)`` in both, and K is copied unchanged
  (checked against gsplat 1.5.3 in tests/test_adapter_gsplat.py).

gsplat's ``simple_trainer.py`` hands the trainer ``data["camtoworld"]`` ([B, 4, 4]) and
``data["K"]``; its ``viewmats`` are ``torch.linalg.inv(camtoworlds)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from polargs_plugin.types import View

__all__ = ["view_from_gsplat", "gsplat_cameras"]


def _single(tensor: Tensor, shape: tuple[int, int], what: str) -> Tensor:
    """``tensor`` as one (r, c) matrix, accepting a leading camera dimension of size 1."""
    if tensor.dim() == 3 and tensor.shape[0] == 1:
        tensor = tensor[0]
    if tuple(tensor.shape) != shape:
        raise ValueError(f"{what} must be {shape} or (1, {shape[0]}, {shape[1]}) (one camera), got {tuple(tensor.shape)}")
    return tensor.detach().to(torch.float64)


def view_from_gsplat(
    viewmats: Tensor,
    Ks: Tensor,
    stokes: Tensor,
    *,
    name: str,
    mask: Tensor | None = None,
    source: str = "",
) -> View:
    """A :class:`View` of one gsplat camera with the view's polarimetric data.

    Args:
        viewmats: (1, 4, 4) or (4, 4) world-to-camera, OpenCV, as passed to gsplat's
            ``rasterization`` (``torch.linalg.inv(data["camtoworld"])`` in simple_trainer).
        Ks: (1, 3, 3) or (3, 3) intrinsics as passed to ``rasterization`` (``data["K"]``).
        stokes: (3, C, H, W) Stokes of the view at the trainer's resolution (the image size
            is taken from it).
        name: unique view name (the hooks look their per-view maps up by it).
        mask: optional (1, H, W) bool object mask.
        source: where the data came from, for error messages.

    Returns:
        The View, cameras float64 on the Stokes' device. K is unchanged: gsplat and this
        project both put pixel centres at +0.5 (module docstring).

    Raises:
        ValueError: on wrong shapes or a viewmat whose last row is not (0, 0, 0, 1).
    """
    w2c = _single(viewmats, (4, 4), "viewmats")
    K = _single(Ks, (3, 3), "Ks")
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device=w2c.device)
    if not torch.allclose(w2c[3], bottom, atol=1e-6):
        raise ValueError(f"view '{name}': viewmats last row must be (0, 0, 0, 1), got {w2c[3].tolist()}")
    if stokes.dim() != 4 or stokes.shape[0] != 3:
        raise ValueError(f"view '{name}': stokes must be (3, C, H, W), got {tuple(stokes.shape)}")
    device = stokes.device
    return View(name=name, K=K.to(device), world_to_camera=w2c.to(device), stokes=stokes, mask=mask, source=source)


def gsplat_cameras(view: View, device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """The gsplat camera tensors of a view (inverse of :func:`view_from_gsplat`).

    Args:
        view: the view.
        device: where to put them (default: the view's camera device).

    Returns:
        ``(viewmats (1, 4, 4), Ks (1, 3, 3))`` float32, ready for ``rasterization(...,
        viewmats, Ks, view.width, view.height)``.
    """
    device = view.K.device if device is None else device
    viewmats = view.world_to_camera.to(device=device, dtype=torch.float32)[None]
    Ks = view.K.to(device=device, dtype=torch.float32)[None]
    return viewmats.contiguous(), Ks.contiguous()
