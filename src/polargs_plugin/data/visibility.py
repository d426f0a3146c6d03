"""Which views see a surface point, and how: the visibility classes of the evaluation.

A point of the ground-truth surface is seen **well** by a view when the view sees it (inside the
image, in front of the camera, not hidden) at an incidence angle below :attr:`VisibilityClasses.grazing_deg`
(the angle between the surface normal and the direction to the camera), and **at a grazing angle**
when the view sees it at a larger one. Each seen point falls in one class:

- ``many``: seen well by at least :attr:`VisibilityClasses.many_views` views;
- ``few``: seen well by 1 to ``many_views - 1`` views;
- ``grazing``: seen by some view, but by none of them well (only at grazing angles).

Two sources of "the view sees it": the views' ground-truth depth maps (:func:`depth_map_counts`,
what the evaluation uses: the training views' own record of the surface at pixel resolution) and
exact ray casting against the scene's mesh (:func:`triangle_visibility`, the generator's per-view
ground truth). docs/evaluation.md gives the reasons for the thresholds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from polargs_plugin.types import View

__all__ = [
    "CLASS_NAMES",
    "UNSEEN",
    "VisibilityClasses",
    "classify_counts",
    "class_fractions",
    "depth_map_counts",
    "seen_in_depth_map",
    "triangle_visibility",
    "triangle_counts",
    "incidence_cosines",
]

#: The classes, in the order of their codes 0, 1, 2 (:func:`classify_counts`).
CLASS_NAMES: tuple[str, ...] = ("many", "few", "grazing")
#: Class code of a point that no view sees.
UNSEEN = -1


@dataclass(frozen=True)
class VisibilityClasses:
    """Thresholds of the visibility classes (module docstring).

    Attributes:
        many_views: views that must see a point well for class ``many`` (default 4: PatchMatch
            compares a reference view with several sources and keeps a depth that two of them
            confirm, so a surface seen well by four views or more is what multi-view stereo needs).
        grazing_deg: incidence angle (degrees) from which a view sees a point at a grazing angle
            (default 70: the surface is foreshortened three times, cos 70 deg = 0.34, and a pixel
            spans three pixel widths of it).
    """

    many_views: int = 4
    grazing_deg: float = 70.0

    def __post_init__(self) -> None:
        if self.many_views < 2:
            raise ValueError(f"many_views must be >= 2, got {self.many_views}")
        if not 0.0 < self.grazing_deg < 90.0:
            raise ValueError(f"grazing_deg must be in (0, 90), got {self.grazing_deg}")

    @property
    def grazing_cos(self) -> float:
        """cos(grazing_deg): a view whose incidence cosine is below it sees at a grazing angle."""
        return math.cos(math.radians(self.grazing_deg))


def classify_counts(well: np.ndarray, grazing: np.ndarray, classes: VisibilityClasses = VisibilityClasses()) -> np.ndarray:
    """(N,) int8 class codes (0 many, 1 few, 2 grazing, :data:`UNSEEN`) from the number of views
    that see each point well (``well``, (N,)) and at a grazing angle (``grazing``, (N,))."""
    well, grazing = np.asarray(well), np.asarray(grazing)
    codes = np.full(well.shape, UNSEEN, dtype=np.int8)
    codes[(well == 0) & (grazing > 0)] = 2
    codes[(well > 0) & (well < classes.many_views)] = 1
    codes[well >= classes.many_views] = 0
    return codes


def class_fractions(codes: np.ndarray, weights: np.ndarray | None = None) -> dict[str, float]:
    """Share of each class among the seen points (weighted, e.g. by triangle area); NaN when none is seen."""
    codes = np.asarray(codes)
    weights = np.ones(codes.shape) if weights is None else np.asarray(weights, dtype=np.float64)
    seen = weights[codes != UNSEEN].sum()
    return {name: float(weights[codes == code].sum() / seen) if seen > 0 else math.nan
            for code, name in enumerate(CLASS_NAMES)}


def incidence_cosines(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N,) |cos| of the angle between each normal and the direction from its point to ``centre``
    (the sign of the normal does not matter: a mesh's orientation is not always known)."""
    offset = np.asarray(centre, np.float64)[None, :] - points
    return np.abs(np.einsum("ij,ij->i", normals, offset)) / np.maximum(np.linalg.norm(offset, axis=1), 1e-12)


def _camera(view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, world_to_camera, camera centre) of a view, float64."""
    K = view.K.detach().cpu().numpy().astype(np.float64)
    w2c = view.world_to_camera.detach().cpu().numpy().astype(np.float64)
    return K, w2c, view.camera_center.detach().cpu().numpy().astype(np.float64)


def _seen_in_depth_map(cam: np.ndarray, K: np.ndarray, depth: np.ndarray, tolerance_px: float) -> np.ndarray:
    """(N,) bool: the camera-frame points ``cam`` (N, 3) lie on the surface of the depth map ``depth``
    (H, W; 0 = no surface): in front of the camera, inside the image, and between the depths of
    the (up to) four pixels whose centres surround their projection, within ``tolerance_px`` pixel
    footprints, widened by their spread. The bracket, not one pixel's depth, so that a surface seen
    at a grazing angle (its depth changes by several footprints from pixel to pixel) still passes,
    up to its silhouette, while a point hidden behind another surface (beyond every neighbour and
    their spread) does not."""
    height, width = depth.shape
    z = cam[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    x = K[0, 0] * cam[:, 0] / zs + K[0, 1] * cam[:, 1] / zs + K[0, 2] - 0.5  # pixel-centre coordinates
    y = K[1, 1] * cam[:, 1] / zs + K[1, 2] - 0.5
    inside = front & (x > -0.5) & (x < width - 0.5) & (y > -0.5) & (y < height - 0.5)
    low = np.full(len(z), np.inf)
    high = np.full(len(z), -np.inf)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = np.clip(x0 + dx, 0, width - 1), np.clip(y0 + dy, 0, height - 1)
            d = depth[yi, xi]
            valid = d > 0
            low = np.where(valid, np.minimum(low, d), low)
            high = np.where(valid, np.maximum(high, d), high)
    # the spread of the neighbours' depths widens the bracket by itself: a point between a surface's
    # last pixel centre and its silhouette (seen at a grazing angle) lies up to one such step beyond it
    tolerance = tolerance_px * zs / K[0, 0] + np.where(np.isfinite(high), high - low, 0.0)
    return inside & (low - tolerance <= z) & (z <= high + tolerance)


def seen_in_depth_map(points: np.ndarray, view: View, tolerance_px: float = 1.0) -> np.ndarray:
    """(N,) bool: which world points (N, 3) the view sees, by its ground-truth depth map (the test
    of :func:`depth_map_counts`: on the depth map's surface within ``tolerance_px`` footprints).

    Raises:
        ValueError: the view has no ground-truth depth map.
    """
    if view.depth_gt is None:
        raise ValueError(f"depth_map_counts: view {view.name!r} has no ground-truth depth map")
    K, w2c, _ = _camera(view)
    cam = np.asarray(points, dtype=np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    return _seen_in_depth_map(cam, K, view.depth_gt[0].detach().cpu().numpy().astype(np.float64), tolerance_px)


def depth_map_counts(
    points: np.ndarray,
    normals: np.ndarray,
    views: Sequence[View],
    classes: VisibilityClasses = VisibilityClasses(),
    tolerance_px: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """How many views see each point well and how many at a grazing angle, from the views'
    ground-truth depth maps (``View.depth_gt``, camera z, 0 where the object is not seen).

    Args:
        points: (N, 3) world points on the ground-truth surface.
        normals: (N, 3) their unit normals (either orientation).
        views: views with ``depth_gt``, ``K`` (pixel centres at +0.5) and ``world_to_camera``.
        classes: the grazing threshold.
        tolerance_px: depth tolerance in pixel footprints (depth / f_x) around the depths of
            the surrounding pixels.

    Returns:
        ``(well (N,) int16, grazing (N,) int16)``; :func:`classify_counts` turns them into classes.

    Raises:
        ValueError: a view without a depth map, or shapes that do not fit.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.shape != normals.shape or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points and normals must both be (N, 3), got {points.shape} and {normals.shape}")
    well = np.zeros(len(points), dtype=np.int16)
    grazing = np.zeros(len(points), dtype=np.int16)
    for view in views:
        seen = seen_in_depth_map(points, view, tolerance_px)
        steep = incidence_cosines(points[seen], normals[seen], view.camera_center.detach().cpu().numpy()) >= classes.grazing_cos
        index = np.flatnonzero(seen)
        well[index[steep]] += 1
        grazing[index[~steep]] += 1
    return well, grazing


def triangle_visibility(
    vertices: np.ndarray,
    triangles: np.ndarray,
    cameras: Sequence[tuple[np.ndarray, np.ndarray, int, int]],
    occluder: "object",
    tolerance: float | None = None,
) -> np.ndarray:
    """Exact per-view visibility of triangles: (V, F) bool, True where view v sees the centroid of
    triangle f, from its front side, inside its image and not hidden (a ray cast from the camera
    centre against ``occluder`` reaches it).

    Args:
        vertices: (P, 3) world vertices; triangles: (F, 3) indices, counter-clockwise seen from
            outside (their front side is the side their geometric normal points to).
        cameras: per view ``(K (3, 3), world_to_camera (4, 4), width, height)``.
        occluder: an open3d ``RaycastingScene`` holding every surface that can hide a triangle
            (the whole scene, a floor included).
        tolerance: distance before the centroid at which a hit counts as hiding it; None: 1e-4 x
            the vertices' bounding-box diagonal.
    """
    import open3d as o3d

    vertices = np.asarray(vertices, np.float64)
    corners = vertices[np.asarray(triangles, np.int64)]
    centroid = corners.mean(axis=1)
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if tolerance is None:
        tolerance = 1e-4 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    out = np.zeros((len(cameras), len(centroid)), dtype=bool)
    for index, (K, w2c, width, height) in enumerate(cameras):
        K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        cam = centroid @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.where(cam[:, 2] > 1e-9, cam[:, 2], 1.0)
        u = K[0, 0] * cam[:, 0] / z + K[0, 1] * cam[:, 1] / z + K[0, 2]
        v = K[1, 1] * cam[:, 1] / z + K[1, 2]
        facing = np.einsum("ij,ij->i", face, centre[None, :] - centroid) > 0
        todo = np.flatnonzero((cam[:, 2] > 1e-9) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & facing)
        if len(todo) == 0:
            continue
        offset = centroid[todo] - centre
        length = np.linalg.norm(offset, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, offset.shape), offset / length[:, None]], 1).astype(np.float32)
        t_hit = occluder.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        out[index, todo] = ~(t_hit < length - tolerance)
    return out


def triangle_counts(
    vertices: np.ndarray,
    triangles: np.ndarray,
    visibility: np.ndarray,
    centres: Sequence[np.ndarray],
    classes: VisibilityClasses = VisibilityClasses(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle, how many views see it well and how many at a grazing angle, from the exact
    per-view ``visibility`` (V, F) of :func:`triangle_visibility` and the camera ``centres``; with the
    triangles' areas: ``(well (F,), grazing (F,), area (F,))`` (:func:`classify_counts`,
    :func:`class_fractions` with the areas as weights)."""
    corners = np.asarray(vertices, np.float64)[np.asarray(triangles, np.int64)]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(2 * area, 1e-300)[:, None]
    centroid = corners.mean(axis=1)
    visibility = np.asarray(visibility, dtype=bool)
    if visibility.shape != (len(centres), len(corners)):
        raise ValueError(f"visibility has shape {visibility.shape}, expected ({len(centres)}, {len(corners)})")
    well = np.zeros(len(corners), dtype=np.int16)
    grazing = np.zeros(len(corners), dtype=np.int16)
    for seen, centre in zip(visibility, centres):
        steep = incidence_cosines(centroid, normals, centre) >= classes.grazing_cos
        well += seen & steep
        grazing += seen & ~steep
    return well, grazing, area
