"""The reference Gaussian rasterizer: plain tensors in, :class:`~polargs_plugin.types.RenderOut` out.

Pipeline: projection (EWA, differentiable) -> :func:`~.binning.bin_gaussians` (no grad, one
sort) -> compositing, either the exact pure-torch two-pass path (:mod:`.composite_torch`, any
device) or the compiled CPU kernel (:mod:`.composite_numba`, same rule, hand-written backward).
The compositing rule is stated in :mod:`.composite_torch`. The projection and SH colour are
:func:`~.projection.project_gaussians` and :func:`~polargs_plugin.geometry.eval_sh` (torch, the
reference and the CUDA path) or, on the numba path, the compiled
:func:`~.projection_numba.project_numba` (same outputs, hand-written backward).
"""

from __future__ import annotations

from typing import Literal, get_args

import torch
from torch import Tensor

from ...geometry import depth_from_plane, eval_sh, plane_distances
from ...types import RenderOut
from .binning import DEFAULT_TILE_SIZE, TileBins, bin_gaussians, tile_centres
from .composite_torch import Composite, composite_torch, pixel_depth
from .projection import DEFAULT_EPS2D, Projection, dilated_ray_depth_data, project_gaussians

__all__ = ["rasterize", "resolve_backend", "CompositeOrder", "check_order", "parse_order_and_tile"]

Backend = Literal["auto", "torch", "numba"]
ProjectionPath = Literal["auto", "torch", "numba"]
CompositeOrder = Literal["center", "ray"]
RAY_KEY_CHUNK = 1 << 20  # (tile, Gaussian) pairs whose ray-order keys the torch path computes at once


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "numba"]:
    """The compositing path ``backend`` selects on ``device``.

    "auto" picks the Numba kernel on CPU (about 4x faster per iteration than the torch path,
    see bench/rasterizer.py) when numba imports, else the torch path; on CUDA always torch.
    """
    if backend not in ("auto", "torch", "numba"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'numba', got {backend!r}")
    if backend == "numba" and device.type != "cpu":
        raise ValueError(f"backend='numba' runs on CPU tensors only, got device {device}")
    if backend == "auto":
        if device.type != "cpu":
            return "torch"
        try:
            from . import composite_numba  # noqa: F401
        except ImportError:
            return "torch"
        return "numba"
    return backend


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    world_to_camera: Tensor,
    width: int,
    height: int,
    *,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 100.0,
    tile_size: int = DEFAULT_TILE_SIZE,
    eps2d: float = DEFAULT_EPS2D,
    backend: Backend = "auto",
    projection: ProjectionPath = "auto",
    with_plane_depth: bool = True,
    order: CompositeOrder = "center",
) -> RenderOut:
    """Render N 3D Gaussians into one pinhole camera.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) rotations, wxyz (normalised here).
        scales: (N, 3) positive scales (standard deviations along the Gaussian's axes).
        opacities: (N,) in (0, 1).
        colors: (N, 3) RGB, or (N, K, 3) SH coefficients with K = (d + 1)^2, d <= 3, evaluated
            at the direction from the camera centre to each mean (3DGS convention: + 0.5,
            clamped at 0).
        K: (3, 3) intrinsics, pixel centres at +0.5.
        world_to_camera: (4, 4) OpenCV world-to-camera transform.
        width, height: image size in pixels.
        background: optional (3,) colour composited behind the Gaussians.
        near, far: Gaussians whose mean camera z is outside [near, far] are culled.
        tile_size: tile edge in pixels for binning.
        eps2d: low-pass dilation added to each screen covariance's diagonal (pixels^2; vanilla
            3DGS's 0.3). It widens every footprint by a fixed number of pixels, so at low
            resolution it is a larger share of the object (docs/evaluation.md "Depth bias").
        backend: "torch" (exact reference, CPU or CUDA), "numba" (compiled CPU kernel) or
            "auto" (numba on CPU when available, torch otherwise).
        projection: how the numba path projects and evaluates SH: "auto"/"numba" with the
            compiled kernel of :mod:`.projection_numba` ("auto" falls back to torch when K or
            world_to_camera require grad, which that kernel does not give), "torch" with
            :func:`~.projection.project_gaussians` + :func:`~polargs_plugin.geometry.eval_sh` and their autograd
            graph (the path before the compiled projection, kept for comparison; same results to
            float rounding). The torch compositing path always projects in torch.
        with_plane_depth: also composite each Gaussian's plane distance and return
            ``plane_depth`` (one more blended channel and a few image-sized operations, ~0.6 ms a
            view at 128x128 on one core: a trainer without L_dn passes False).
        order: the front-to-back order within a tile. "center" (vanilla 3DGS): by the camera z
            of each Gaussian's mean, one order for the whole image. "ray": by the camera z at
            which the ray through the tile's centre meets each Gaussian's maximum density (a
            flat splat's plane), so that of two overlapping splats the one the ray meets first
            is composited first; the Gaussian is first thickened by the dilation ``eps2d``
            (:func:`~.projection.dilated_ray_depth_data`), so that a splat seen edge-on beside
            the ray is sorted near its centre, not where the ray crosses its plane. Exact per
            pixel with ``tile_size=1``, a few pixels' worth of approximation at small tiles. On
            a curved surface covered by tangent splats, "center" composites the splat nearer
            the camera on top of its neighbours, which shows every colour displaced towards the
            far side of its splat; training then recesses the surface to put the colours back
            (docs/evaluation.md "Depth bias").

    Returns:
        :class:`RenderOut`:

        - color (3, H, W), with ``background`` composited behind when given;
        - depth (1, H, W) expected camera z normalised by alpha (0 where alpha = 0); a
          Gaussian's depth at a pixel is the camera z of its maximum-density point on the
          pixel's ray (see :mod:`.projection`), so flat splats render their plane;
        - median_depth (1, H, W) depth of the Gaussian where transmittance first drops below
          0.5 (0 where it never does);
        - normal (3, H, W) camera-frame shortest axes flipped to face the camera centre
          (n . mean_cam < 0, which is n_z < 0 near the optical axis), composited with the
          colour weights, not renormalised;
        - alpha (1, H, W);
        - plane_depth (1, H, W) PGSR's unbiased plane depth (None with ``with_plane_depth``
          False): the camera z where each pixel's ray meets the plane n . x = -d of the
          composited normal n and plane distance d (each Gaussian's d = -n_i . mean_cam: its
          plane's distance to the camera centre),
          0 where the ray does not meet it; exact for flat splats on a plane, and its gradient
          takes no per-pixel ray-Gaussian depth (L_dn uses it);
        - means2d (N, 2) projected means in pixels; after backward ``.grad`` holds dL/dmeans2d
          (when the inputs require grad);
        - radii (N,) int64 opacity-aware screen radius in pixels (larger half-width of the box
          bounding alpha >= 1/255), 0 = culled by near/far or off-screen.
    """
    _check_gaussians(means, quats, scales, opacities, colors)
    check_order(order)
    path = resolve_backend(backend, means.device)
    camera_grad = K.requires_grad or world_to_camera.requires_grad
    _check_projection(projection, path, camera_grad)
    if path == "numba" and projection != "torch" and not camera_grad:
        from .projection_numba import project_numba

        proj, colors = project_numba(
            means, quats, scales, opacities, colors, K, world_to_camera, width, height, near, far, eps2d
        )
    else:
        proj = project_gaussians(means, quats, scales, opacities, K, world_to_camera, width, height, near, far, eps2d)
        colors = _view_colors(colors, means, world_to_camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()

    bins = bin_gaussians(means2d.detach(), proj.extents, proj.depths.detach(), width, height, tile_size)
    if order == "ray":
        keys = dilated_ray_depth_data(means.detach(), quats.detach(), scales.detach(), K, world_to_camera.detach(),
                                      near, far, eps2d)
        if path == "numba":
            from .composite_numba import ray_ordered_numba

            bins = ray_ordered_numba(bins, keys)
        else:
            bins = ray_ordered(bins, keys)
    distances = plane_distances(proj.normals, means, world_to_camera) if with_plane_depth else None
    if path == "numba":
        from .composite_numba import composite_numba

        comp = composite_numba(proj, opacities, colors, bins, width, height, distances)
    else:
        comp = composite_torch(proj, opacities, colors, bins, width, height, distances)
    return _render_out(comp, proj, bins, background, K.to(means) if with_plane_depth else None)


@torch.no_grad()
def ray_ordered(bins: TileBins, keys: tuple[Tensor, Tensor, Tensor]) -> TileBins:
    """``bins`` with each tile's list sorted front to back by the camera z at which the ray
    through the tile's centre passes each Gaussian's maximum density
    (:func:`~.composite_torch.pixel_depth` of ``keys`` = (ray_coeffs, ray_offsets, depth_bounds),
    :func:`~.projection.dilated_ray_depth_data`); ties keep the lists' mean-depth order.
    Gradients do not depend on the order's choice (it is discrete), so both compositing paths
    take the re-sorted lists as they are."""
    ray_coeffs, ray_offsets, depth_bounds = keys
    counts = bins.tile_offsets[1:] - bins.tile_offsets[:-1]
    tile = torch.repeat_interleave(torch.arange(counts.shape[0], device=counts.device), counts)
    centre = tile_centres(bins, ray_coeffs.dtype)[tile]
    cx, cy = centre[:, 0], centre[:, 1]
    g = bins.gauss_ids
    # in chunks: the gathered (pairs, 3, 3) coefficients would be 36 bytes a pair at once
    key = torch.empty_like(cx)
    for first in range(0, g.shape[0], RAY_KEY_CHUNK):
        part = slice(first, first + RAY_KEY_CHUNK)
        ids = g[part]
        key[part] = pixel_depth(ray_coeffs[ids], ray_offsets[ids], depth_bounds[ids], cx[part], cy[part])
    by_key = torch.argsort(key, stable=True)
    by_tile = by_key[torch.argsort(tile[by_key], stable=True)]
    return bins._replace(gauss_ids=g[by_tile].contiguous())


def parse_order_and_tile(spec: str, where: str) -> tuple[str, int]:
    """'ORDER:TILE' (e.g. "ray:1") -> (order, tile size); ValueError naming ``where`` otherwise.

    >>> parse_order_and_tile("ray:4", "--render")
    ('ray', 4)
    """
    order, _, tile = spec.partition(":")
    try:
        check_order(order, f"the order in {where}")
        size = int(tile)
    except ValueError as err:
        raise ValueError(f"{where} wants ORDER:TILE (e.g. ray:1), got {spec!r}: {err}") from err
    if size < 1:
        raise ValueError(f"the tile size in {where} must be >= 1, got {spec!r}")
    return order, size


def check_order(order: str, where: str = "order") -> None:
    """ValueError naming ``where`` unless ``order`` is one of :data:`CompositeOrder`."""
    if order not in get_args(CompositeOrder):
        raise ValueError(f"{where} must be one of {get_args(CompositeOrder)}, got {order!r}")


def _check_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor) -> None:
    """ValueError naming the shapes unless they are those :func:`rasterize` documents."""
    n = means.shape[0]
    if means.shape != (n, 3) or quats.shape != (n, 4) or scales.shape != (n, 3) or opacities.shape != (n,):
        raise ValueError(
            "expected means (N,3), quats (N,4), scales (N,3), opacities (N,); got "
            f"{tuple(means.shape)}, {tuple(quats.shape)}, {tuple(scales.shape)}, {tuple(opacities.shape)}"
        )
    if colors.shape[0] != n or colors.shape[-1] != 3 or colors.dim() not in (2, 3):
        raise ValueError(f"colors must be (N,3) or (N,K,3) with N={n}, got {tuple(colors.shape)}")


def _check_projection(projection: ProjectionPath, path: str, camera_grad: bool) -> None:
    """ValueError unless ``projection`` is possible with compositing ``path`` (see :func:`rasterize`)."""
    if projection not in ("auto", "torch", "numba"):
        raise ValueError(f"projection must be 'auto', 'torch' or 'numba', got {projection!r}")
    if projection == "numba" and path != "numba":
        raise ValueError("projection='numba' needs the numba compositing path (backend 'numba'/'auto' on CPU)")
    if projection == "numba" and camera_grad:
        raise ValueError("projection='numba' gives no gradient to K / world_to_camera; use projection='torch'")


def _view_colors(colors: Tensor, means: Tensor, world_to_camera: Tensor) -> Tensor:
    """Per-Gaussian RGB: ``colors`` (N, 3) as they are, (N, K, 3) SH evaluated towards the camera."""
    if colors.dim() != 3:
        return colors
    w2c = world_to_camera.to(means)
    camera_center = -w2c[:3, :3].T @ w2c[:3, 3]
    return eval_sh(colors, means - camera_center)


def _render_out(
    comp: Composite, proj: Projection, bins: TileBins, background: Tensor | None, plane_K: Tensor | None
) -> RenderOut:
    """The composited sums as a :class:`RenderOut`; the plane depth with intrinsics ``plane_K``."""
    color = comp.color
    if background is not None:
        color = color + (1.0 - comp.alpha) * background.to(color).reshape(3, 1, 1)
    # Covered pixels have alpha >= 1/255, so the clamp only turns 0/0 into 0.
    depth = comp.depth / comp.alpha.clamp_min(1e-6)
    radius = torch.ceil(proj.extents.max(dim=-1).values)
    radii = torch.where(bins.visible, radius, torch.zeros_like(radius)).long()
    return RenderOut(
        color=color,
        depth=depth,
        normal=comp.normal,
        alpha=comp.alpha,
        median_depth=comp.median_depth,
        plane_depth=None if plane_K is None else depth_from_plane(comp.distance, comp.normal, plane_K),
        means2d=proj.means2d,
        radii=radii,
    )
