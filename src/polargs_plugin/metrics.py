"""Geometry metrics: DTU-style Chamfer distance with F-score, and normal mean angular error.

Chamfer protocol (docs/evaluation.md): both meshes are sampled area-uniformly (seeded); with
views given, the evaluation is restricted to the observed object (predicted points culled to
the dilated object silhouettes, GT points kept where some view sees them); nearest-neighbour
distances are exact (:mod:`polargs_plugin.nearest`: the same floats as scipy's cKDTree).
accuracy = mean distance pred -> GT, completeness = mean distance GT -> pred, chamfer = their
mean. As in the DTU script, distances above ``max_dist`` are dropped from the means (not
clipped); the same means without the cap are reported as ``*_uncapped``.
F-score at ``fscore_threshold`` uses all points. The signed distance of the predicted points to
the GT surface (outside positive) tells a mesh that sits inside from one that sits outside.
Where the views carry ground-truth depth maps, the GT points are also sorted by how the training
views see them (:mod:`polargs_plugin.data.visibility`: seen by many views, by few, only at
grazing angles): the uncapped completeness of each class and the uncapped Chamfer over the GT
surface some view sees (``chamfer_visible``) show lost surface that the cap hides, and the share
of each class's GT samples farther than ``missing_dist`` from the prediction (``missing_by_visibility``)
how much of it is gone. Views without
their own GT depth maps (or normals) get the ones ray-cast from the GT mesh (:func:`with_mesh_maps`).
Distances are in the meshes' own units; bring the prediction into the ground truth's frame and
scale first.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import cv2
import numpy as np
import open3d as o3d
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt
from torch import Tensor

from polargs_plugin.data.visibility import (
    CLASS_NAMES,
    UNSEEN,
    VisibilityClasses,
    classify_counts,
    depth_map_counts,
)
from polargs_plugin.nearest import SampleIndex
from polargs_plugin.types import View

__all__ = [
    "MAX_DIST_FRACTION",
    "FSCORE_FRACTION",
    "MISSING_FRACTION",
    "REGIONS",
    "sample_surface",
    "sample_surface_with_faces",
    "cull_to_masks",
    "mesh_silhouettes",
    "mesh_maps",
    "with_mesh_maps",
    "RAY_CAST_SOURCE",
    "in_object_region",
    "visible_from_views",
    "signed_distances",
    "chamfer_distance",
    "visible_surface_figures",
    "normal_angle_errors",
    "normal_mae",
    "CONTOUR_BANDS_PX",
    "depth_jumps",
    "contour_distance",
    "normal_errors_by_contour_distance",
]

# Defaults relative to the ground-truth bounding-box diagonal, so that they mean the same on
# any scale: DTU drops distances >= 20 mm on objects whose box diagonal is ~400-500 mm (~5 %);
# the F-score threshold is a tenth of that (2-2.5 mm on DTU; ~0.017 on a unit-radius sphere).
MAX_DIST_FRACTION = 0.05
FSCORE_FRACTION = 0.005
#: A GT sample farther than this fraction of the GT bounding-box diagonal from the prediction is
#: "missing" (``missing_by_visibility``): well beyond the F-score threshold, below the outlier cap.
MISSING_FRACTION = 0.02

#: Evaluation regions of :func:`chamfer_distance` (docs/evaluation.md "Protocol"):
#: "all" = whole meshes; "masks" = predicted points culled to the views' dilated masks (DTU /
#: NeuS culling); "object" = predicted points culled to the dilated silhouettes of the GT mesh
#: (the object) and GT points kept only where some view sees them (default of `polargs eval`).
REGIONS = ("all", "masks", "object")

#: The source of GT maps that :func:`with_mesh_maps` ray-cast from the GT mesh (the metrics'
#: ``visibility_classes["source"]`` and ``normal_source``; a dataset's own maps are
#: "ground-truth depth maps" / "ground-truth normal maps").
RAY_CAST_SOURCE = "ray-cast from the ground-truth mesh"

MeshLike = o3d.geometry.TriangleMesh | tuple[np.ndarray, np.ndarray]


def _mesh_arrays(mesh: MeshLike) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    else:
        vertices, triangles = mesh
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"mesh must be vertices (V, 3) and triangles (F, 3), got {vertices.shape}, {triangles.shape}")
    if len(triangles) == 0:
        raise ValueError("mesh has no triangles")
    return vertices, triangles


def sample_surface(mesh: MeshLike, num: int, seed: int = 0) -> np.ndarray:
    """Sample ``num`` points uniformly by area on a triangle mesh.

    Args:
        mesh: open3d TriangleMesh or (vertices (V, 3), triangles (F, 3)).
        num: number of points.
        seed: random seed (the result depends only on the mesh, ``num`` and ``seed``).

    Returns:
        (num, 3) float64 points.
    """
    return sample_surface_with_faces(mesh, num, seed)[0]


def sample_surface_with_faces(mesh: MeshLike, num: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_surface`'s points (the same ones) and the triangle each lies on: ((num, 3), (num,))."""
    vertices, triangles = _mesh_arrays(mesh)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = areas.sum()
    if not total > 0:
        raise ValueError("mesh has zero surface area")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(triangles), size=int(num), p=areas / total)
    # Uniform barycentrics: fold the unit square onto the triangle (r1 + r2 <= 1).
    r1, r2 = rng.random(int(num)), rng.random(int(num))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    a, b, c = a[face], b[face], c[face]  # gathered once: the random gathers are the slow part
    return a + r1[:, None] * (b - a) + r2[:, None] * (c - a), face


def _face_normals(mesh: MeshLike, faces: np.ndarray) -> np.ndarray:
    """(N,) unit normals of the triangles ``faces`` of ``mesh`` (their own orientation)."""
    vertices, triangles = _mesh_arrays(mesh)
    corners = vertices[triangles[faces]]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)


def cull_to_masks(
    points: np.ndarray,
    views: Sequence[View],
    dilation_px: int = 2,
    masks: Sequence[np.ndarray] | None = None,
    require_seen: bool = False,
) -> np.ndarray:
    """Which points survive DTU-style mask culling.

    A point is kept if, in every view, it is either outside the image (or behind the camera)
    or inside the object mask dilated by a disk of radius ``dilation_px`` pixels.

    Args:
        points: (N, 3) world points.
        views: views with ``mask`` (1, H, W) bool, ``K`` (pixel centres at +0.5), ``world_to_camera``.
        dilation_px: dilation radius (DTU: 24 px at 1600x1200; NeuS: 50 px).
        masks: optional (H, W) bool masks to use instead of ``view.mask`` (one per view), e.g.
            :func:`mesh_silhouettes` of the ground truth.
        require_seen: also drop points that are inside no view's image.

    Returns:
        (N,) bool keep mask.
    """
    points = np.asarray(points, dtype=np.float64)
    keep = np.ones(len(points), dtype=bool)
    seen = np.zeros(len(points), dtype=bool)
    if masks is not None and len(masks) != len(views):
        raise ValueError(f"cull_to_masks: {len(views)} views but {len(masks)} masks")
    for index, view in enumerate(views):
        # a dropped point stays dropped: project only the points still kept (3-4x less work)
        todo = np.flatnonzero(keep)
        if len(todo) == 0:
            break
        if masks is not None:
            mask = np.asarray(masks[index], dtype=np.uint8)
        elif view.mask is None:
            raise ValueError(f"cull_to_masks: view {view.name!r} has no mask")
        else:
            mask = view.mask[0].detach().cpu().numpy().astype(np.uint8)
        if dilation_px > 0:
            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilation_px + 1, 2 * dilation_px + 1))
            mask = cv2.dilate(mask, disk)
        height, width = mask.shape
        w2c = view.world_to_camera.detach().cpu().numpy().astype(np.float64)
        K = view.K.detach().cpu().numpy().astype(np.float64)
        cam = points[todo] @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        u = np.floor(K[0, 0] * cam[:, 0] / zs + K[0, 1] * cam[:, 1] / zs + K[0, 2])
        v = np.floor(K[1, 1] * cam[:, 1] / zs + K[1, 2])
        inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        ui = np.clip(u, 0, width - 1).astype(np.int64)
        vi = np.clip(v, 0, height - 1).astype(np.int64)
        keep[todo] = ~inside | (mask[vi, ui] > 0)
        seen[todo] |= inside
    return keep & seen if require_seen else keep


def _nn_distances(query: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(Q,) distance from each of the (Q, 3) ``query`` points to the nearest of the (N, 3) ``target``
    points: exact, the same floats as scipy's ``cKDTree.query``, on the thread policy's threads.

    :class:`~polargs_plugin.nearest.SampleIndex` instead of cKDTree: cKDTree's box leaves make a
    query far from a surface's samples search hundreds of leaves (85 s instead of 1 s for the
    demo's 250k predicted points, many of them inside the GT sphere; see polargs_plugin.nearest).
    """
    return SampleIndex.build(target).query(query)[0]


def _raycasting_scene(mesh: MeshLike) -> o3d.t.geometry.RaycastingScene:
    vertices, triangles = _mesh_arrays(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene


def _camera(view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w2c = view.world_to_camera.detach().cpu().numpy().astype(np.float64)
    K = view.K.detach().cpu().numpy().astype(np.float64)
    return K, w2c, -w2c[:3, :3].T @ w2c[:3, 3]


def _pixel_rays(view: View) -> np.ndarray:
    """(H * W, 6) float32 rays (camera centre, world direction) through the pixel centres, row by
    row; each direction has camera z 1, so a hit's ray parameter t is its camera-z depth."""
    K, w2c, centre = _camera(view)
    u, v = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T
    dirs = rays_cam @ w2c[:3, :3]  # R^T d for row vectors
    return np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], 1).astype(np.float32)


def _first_hit_depths(scene: o3d.t.geometry.RaycastingScene, view: View) -> np.ndarray:
    """(H, W) camera-z depth of the first hit along each pixel-centre ray, inf where none."""
    t_hit = scene.cast_rays(o3d.core.Tensor(_pixel_rays(view)))["t_hit"].numpy()
    return t_hit.astype(np.float64).reshape(view.height, view.width)


def _seen_hits(
    mesh: MeshLike, views: Sequence[View], occluder: MeshLike | None = None
) -> Iterator[tuple[dict[str, np.ndarray], np.ndarray]]:
    """Per view: the pixel-centre rays' hits on ``mesh`` (open3d ``cast_rays``' arrays, flat, row
    by row) and the (H, W) bool pixels where ``mesh`` itself is seen: hit, and, with ``occluder``,
    nothing of it in front (beyond 1e-4 x its bounding-box diagonal)."""
    scene = _raycasting_scene(mesh)
    blocker = tolerance = None
    if occluder is not None:
        blocker = _raycasting_scene(occluder)
        vertices, _ = _mesh_arrays(occluder)
        tolerance = 1e-4 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    for view in views:
        hits = {key: value.numpy() for key, value in scene.cast_rays(o3d.core.Tensor(_pixel_rays(view))).items()}
        depth = hits["t_hit"].astype(np.float64).reshape(view.height, view.width)
        seen = np.isfinite(depth)
        if blocker is not None:
            seen &= ~(_first_hit_depths(blocker, view) < depth - tolerance)
        yield hits, seen


def mesh_silhouettes(mesh: MeshLike, views: Sequence[View], occluder: MeshLike | None = None) -> list[np.ndarray]:
    """(H, W) bool silhouette of ``mesh`` in each view (ray cast through the pixel centres).

    With ``occluder`` (the whole scene, e.g. the object and the floor it stands on), a pixel
    counts only where nothing of the occluder lies in front of ``mesh`` (beyond 1e-4 x its
    bounding-box diagonal): the pixels where ``mesh`` itself is seen.
    """
    return [seen for _, seen in _seen_hits(mesh, views, occluder)]


def _vertex_normals(mesh: MeshLike) -> np.ndarray:
    """(V, 3) unit vertex normals: the mesh's own (an open3d mesh read from a file that has them),
    else the area-weighted means of the normals of the triangles around each vertex."""
    vertices, triangles = _mesh_arrays(mesh)
    if isinstance(mesh, o3d.geometry.TriangleMesh) and mesh.has_vertex_normals():
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    else:
        corners = vertices[triangles]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # 2 x area x normal
        normals = np.zeros_like(vertices)
        for i in range(3):
            np.add.at(normals, triangles[:, i], cross)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


def mesh_maps(
    mesh: MeshLike, views: Sequence[View], occluder: MeshLike | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ground-truth maps of ``mesh`` in each view, ray cast through the pixel centres: (depth
    (H, W) float32, camera z; normals (3, H, W) float32, unit, camera frame, facing the camera),
    both 0 where the view does not see ``mesh`` (missed, or hidden by ``occluder``: the pixels of
    :func:`mesh_silhouettes`). The normals are the vertex normals (:func:`_vertex_normals`)
    interpolated at the hit, turned to the camera's side of the hit triangle, as the bundled
    scenes' generator renders its GT normal maps."""
    _, triangles = _mesh_arrays(mesh)
    vertex_normals = _vertex_normals(mesh)
    out = []
    for view, (hits, seen) in zip(views, _seen_hits(mesh, views, occluder)):
        rotation = view.world_to_camera.detach().cpu().numpy().astype(np.float64)[:3, :3]
        flat = seen.reshape(-1)
        depth = np.where(flat, hits["t_hit"], 0.0).astype(np.float32).reshape(view.height, view.width)
        uv = hits["primitive_uvs"][flat].astype(np.float64)
        corners = vertex_normals[triangles[hits["primitive_ids"][flat].astype(np.int64)]]  # (M, 3, 3)
        normal = (1.0 - uv[:, :1] - uv[:, 1:]) * corners[:, 0] + uv[:, :1] * corners[:, 1] + uv[:, 1:] * corners[:, 2]
        dirs = _pixel_rays(view)[flat, 3:].astype(np.float64)
        away = np.einsum("ij,ij->i", hits["primitive_normals"][flat].astype(np.float64), dirs) > 0
        normal[away] *= -1  # a triangle seen from its back
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        image = np.zeros((view.height * view.width, 3))
        image[flat] = normal @ rotation.T
        out.append((depth, np.ascontiguousarray(image.T.reshape(3, view.height, view.width), dtype=np.float32)))
    return out


def _maps_source(kind: str, given: int, total: int) -> str:
    """Where an evaluation's GT ``kind`` maps came from, ``given`` of ``total`` views having their own."""
    if given == total:
        return f"ground-truth {kind} maps"
    if given == 0:
        return RAY_CAST_SOURCE
    return f"ground-truth {kind} maps ({given} of {total} views), else {RAY_CAST_SOURCE}"


def with_mesh_maps(
    views: Sequence[View], mesh: MeshLike, occluder: MeshLike | None = None, depth: bool = True, normals: bool = False
) -> tuple[list[View], dict[str, str]]:
    """The views, each one without a GT depth map (``depth``) or GT normals (``normals``) given the
    one :func:`mesh_maps` ray-casts from the GT ``mesh`` (hidden by ``occluder``, e.g. the whole
    scene with its floor), so that a dataset with a GT mesh and cameras but no GT maps gets the
    visible-surface figures and the normal MAE. Views that have their maps are kept as they are.

    Returns:
        ``(views, sources)``; ``sources`` has ``"depth"`` / ``"normals"`` (those asked for): where
        the maps came from, ``"ground-truth depth maps"`` (every view had its own),
        :data:`RAY_CAST_SOURCE` (none had) or a mix, as the metrics record it
        (``visibility_classes["source"]`` of :func:`chamfer_distance`).

    Raises:
        ValueError: none of the views it ray-casts for sees ``mesh`` (another frame?).
    """
    views = list(views)
    wanted = {"depth": ("depth_gt", "depth", depth), "normals": ("normal_gt", "normal", normals)}
    missing = {kind: {i for i, v in enumerate(views) if asked and v.stored(field) is None}  # stored: not decoded
               for kind, (field, _, asked) in wanted.items()}
    sources = {kind: _maps_source(word, len(views) - len(missing[kind]), len(views))
               for kind, (_, word, asked) in wanted.items() if asked}
    todo = sorted(missing["depth"] | missing["normals"])
    seen_any = False
    for index, (depth_map, normal_map) in zip(todo, mesh_maps(mesh, [views[i] for i in todo], occluder)):
        view = views[index]
        seen_any = seen_any or bool(depth_map.any())
        changes = {}
        if index in missing["depth"]:
            changes["depth_gt"] = torch.from_numpy(depth_map)[None].to(view.device)
        if index in missing["normals"]:
            changes["normal_gt"] = torch.from_numpy(normal_map).to(view.device)
        views[index] = view.replaced(**changes)
    if todo and not seen_any:
        raise ValueError(f"with_mesh_maps: none of the {len(todo)} views without GT maps sees the ground-truth mesh "
                         "(cameras and mesh in different frames?)")
    return views, sources


def in_object_region(
    points: np.ndarray, gt: MeshLike, views: Sequence[View], dilation_px: int = 2, occluder: MeshLike | None = None
) -> np.ndarray:
    """(N,) bool: the predicted ``points`` (N, 3) that region "object" keeps: seen by some view, and
    inside the GT mesh's silhouette (:func:`mesh_silhouettes`, less what ``occluder`` hides there)
    dilated by ``dilation_px`` pixels in every view that sees them (:func:`cull_to_masks`). So a
    reconstructed occluder in front of the object is left out, as the object's hidden part is."""
    return cull_to_masks(points, views, dilation_px, masks=mesh_silhouettes(gt, views, occluder), require_seen=True)

def visible_from_views(
    points: np.ndarray, views: Sequence[View], occluder: MeshLike, tolerance: float | None = None
) -> np.ndarray:
    """Which points some view sees: inside its image, in front of it and not hidden by ``occluder``.

    A point is hidden in a view when the ray from the camera centre towards it hits
    ``occluder`` more than ``tolerance`` before reaching it (exact ray casting, no depth maps).

    Args:
        points: (N, 3) world points, usually samples of ``occluder`` itself.
        views: cameras (``K``, ``world_to_camera``, image size).
        occluder: mesh that can hide points (the GT, or the whole scene with floor).
        tolerance: None = 1e-4 x the occluder's bounding-box diagonal.

    Returns:
        (N,) bool.
    """
    points = np.asarray(points, dtype=np.float64)
    vertices, _ = _mesh_arrays(occluder)
    if tolerance is None:
        tolerance = 1e-4 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    scene = _raycasting_scene(occluder)
    seen = np.zeros(len(points), dtype=bool)
    for view in views:
        todo = np.flatnonzero(~seen)
        if len(todo) == 0:
            break
        K, w2c, centre = _camera(view)
        cam = points[todo] @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        u = K[0, 0] * cam[:, 0] / zs + K[0, 1] * cam[:, 1] / zs + K[0, 2]
        v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
        inside = front & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
        idx = todo[inside]
        if len(idx) == 0:
            continue
        offset = points[idx] - centre
        length = np.linalg.norm(offset, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, offset.shape), offset / length[:, None]], 1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        seen[idx] = ~(t_hit < length - tolerance)
    return seen


def signed_distances(points: np.ndarray, mesh: MeshLike) -> np.ndarray:
    """Exact distance of each point to ``mesh``, positive on the side its triangles face.

    For an outward-oriented closed GT mesh (the bundled scenes' ``gt_mesh.ply``) positive means
    outside the object, negative inside. The closest point comes from open3d's
    ``RaycastingScene.compute_closest_points`` (float32: about 1e-7 relative).

    Args:
        points: (N, 3).
        mesh: triangle mesh.

    Returns:
        (N,) float64.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.zeros(0)
    result = _raycasting_scene(mesh).compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    closest = result["points"].numpy().astype(np.float64)
    normals = result["primitive_normals"].numpy().astype(np.float64)
    offset = points - closest
    distance = np.linalg.norm(offset, axis=1)
    sign = np.sign(np.einsum("ij,ij->i", offset, normals))
    return distance * np.where(sign == 0, 1.0, sign)


def chamfer_distance(
    pred: MeshLike,
    gt: MeshLike,
    num_samples: int = 1_000_000,
    seed: int = 0,
    max_dist: float | None = None,
    fscore_threshold: float | None = None,
    cull_views: Sequence[View] | None = None,
    cull_dilation_px: int = 2,
    units: str = "scene units",
    region: str | None = None,
    occluder: MeshLike | None = None,
    progress: Callable[[str], None] | None = None,
    visibility_classes: VisibilityClasses | None = None,
    visibility_source: str = "ground-truth depth maps",
    missing_dist: float | None = None,
) -> dict[str, float | int | str | bool]:
    """DTU-style Chamfer distance, F-score and signed distance between a predicted and a GT mesh.

    Args:
        pred, gt: open3d TriangleMesh or (vertices (V, 3), triangles (F, 3)), same frame and units.
        num_samples: area-uniform samples per mesh (before culling).
        seed: sampling seed (GT uses ``seed``, prediction ``seed + 1``).
        max_dist: distances above this are dropped from accuracy/completeness (DTU: 20 mm).
            None = ``MAX_DIST_FRACTION`` x GT bounding-box diagonal.
        fscore_threshold: distance under which a point counts as matched.
            None = ``FSCORE_FRACTION`` x GT bounding-box diagonal.
        cull_views: views (cameras, and masks for region "masks") for the region restriction.
        cull_dilation_px: mask / silhouette dilation radius for culling, in pixels.
        units: label of the distance unit, copied to the output.
        region: one of :data:`REGIONS`; None = "masks" when ``cull_views`` is given, else "all".
            "object" culls the predicted points to the dilated silhouettes of ``gt`` less what
            ``occluder`` hides (and to the images: a point no camera sees is dropped;
            :func:`in_object_region`) and keeps the GT points that some view sees
            (:func:`visible_from_views`, hidden by ``occluder``).
        occluder: geometry that hides the GT object for region "object" (e.g. the whole scene with
            its floor); None = ``gt`` itself.
        progress: called with the name of each step before it starts (for progress bars).
        visibility_classes: thresholds of the visibility classes (None: the defaults of
            :class:`~polargs_plugin.data.visibility.VisibilityClasses`); used when every view of
            ``cull_views`` has a ground-truth depth map.
        visibility_source: where those depth maps came from, recorded as
            ``visibility_classes["source"]`` (:func:`with_mesh_maps` gives views without their
            own the ones ray-cast from the GT mesh, and says so).
        missing_dist: a seen GT sample farther than this from the prediction counts as missing
            (``missing_by_visibility``). None = ``MISSING_FRACTION`` x GT bounding-box diagonal.

    Returns:
        dict (distances in ``units``):

        - accuracy, completeness, chamfer: means of the distances <= max_dist (NaN if all were
          dropped); accuracy_uncapped, completeness_uncapped, chamfer_uncapped: the same means
          over all points; accuracy_outliers, completeness_outliers: the fractions of
          predicted / GT points the cap dropped;
        - precision, recall, fscore at fscore_threshold;
        - signed_distance_median, signed_distance_mean: signed distance of the predicted points
          to the GT surface (:func:`signed_distances`, outside positive), inside_fraction: the
          fraction of predicted points with a negative one;
        - max_dist, fscore_threshold, units, region, culled, num_pred_points and num_gt_points
          (after the region restriction), pred_kept_fraction, gt_kept_fraction, seed;
        - with depth maps on every view (:func:`visible_surface_figures`): visible_fraction (of the
          GT samples, seen by some view in its depth map), completeness_visible (uncapped, over
          those), chamfer_visible = (accuracy_uncapped + completeness_visible) / 2,
          visibility_shares and completeness_by_visibility ({many, few, grazing}: each class's
          share of the seen GT samples and its uncapped completeness, NaN for an empty class),
          missing_by_visibility (per class, the share of its GT samples farther than missing_dist
          from the predicted samples, NaN for an empty class), missing_dist, visibility_classes
          (the thresholds and the depth maps' ``source``).
    """
    step = progress or (lambda name: None)
    region = _resolve_region(region, cull_views)
    max_dist, fscore_threshold, missing_dist = _distance_thresholds(gt, max_dist, fscore_threshold, missing_dist)

    step("sampling")
    gt_points, gt_faces = sample_surface_with_faces(gt, num_samples, seed)
    pred_points = sample_surface(pred, num_samples, seed + 1)
    num_gt_total, num_pred_total = len(gt_points), len(pred_points)
    with_depth = bool(cull_views) and all(v.depth_gt is not None for v in cull_views)
    all_gt_points = gt_points
    pred_points, gt_kept = _restrict_to_region(
        pred_points, gt_points, region, gt, cull_views, cull_dilation_px, occluder, step
    )
    gt_points = gt_points[gt_kept]

    step("nearest neighbours")
    to_gt = _nn_distances(pred_points, gt_points)
    to_pred_all = _nn_distances(all_gt_points, pred_points) if with_depth else None
    to_pred = to_pred_all[gt_kept] if with_depth else _nn_distances(gt_points, pred_points)
    step("signed distance")
    signed = signed_distances(pred_points, gt)
    figures = _distance_figures(to_gt, to_pred, signed, max_dist, fscore_threshold)
    if with_depth:
        step("visibility classes")
        codes = _visibility_codes(all_gt_points, _face_normals(gt, gt_faces), cull_views, visibility_classes)
        figures.update(visible_surface_figures(figures["accuracy_uncapped"], to_pred_all, codes, visibility_classes,
                                               visibility_source, missing_dist))
    return {
        **figures,
        "max_dist": max_dist,
        "fscore_threshold": fscore_threshold,
        "units": units,
        "region": region,
        "culled": region != "all",
        "num_pred_points": int(len(pred_points)),
        "num_gt_points": int(len(gt_points)),
        "pred_kept_fraction": len(pred_points) / num_pred_total,
        "gt_kept_fraction": len(gt_points) / num_gt_total,
        "seed": int(seed),
    }


def _resolve_region(region: str | None, cull_views: Sequence[View] | None) -> str:
    """The region of :func:`chamfer_distance` (its default when None); ValueError if impossible."""
    region = ("masks" if cull_views is not None else "all") if region is None else region
    if region not in REGIONS:
        raise ValueError(f"region must be one of {REGIONS}, got {region!r}")
    if region != "all" and not cull_views:
        raise ValueError(f"region {region!r} needs views (cull_views)")
    return region


def _distance_thresholds(gt: MeshLike, max_dist: float | None, fscore_threshold: float | None,
                         missing_dist: float | None) -> tuple[float, float, float]:
    """(max_dist, fscore_threshold, missing_dist), each given or its fraction of the GT
    bounding-box diagonal."""
    gt_vertices, _ = _mesh_arrays(gt)
    diagonal = float(np.linalg.norm(gt_vertices.max(0) - gt_vertices.min(0)))
    missing_dist = MISSING_FRACTION * diagonal if missing_dist is None else float(missing_dist)
    max_dist = MAX_DIST_FRACTION * diagonal if max_dist is None else float(max_dist)
    fscore_threshold = FSCORE_FRACTION * diagonal if fscore_threshold is None else float(fscore_threshold)
    if not (max_dist > 0 and fscore_threshold > 0):
        raise ValueError(f"max_dist and fscore_threshold must be positive, got {max_dist}, {fscore_threshold}")
    return max_dist, fscore_threshold, missing_dist


def _restrict_to_region(
    pred_points: np.ndarray,
    gt_points: np.ndarray,
    region: str,
    gt: MeshLike,
    cull_views: Sequence[View] | None,
    cull_dilation_px: int,
    occluder: MeshLike | None,
    step: Callable[[str], None],
) -> tuple[np.ndarray, np.ndarray]:
    """(the predicted samples of ``region``, (N,) bool: which GT samples it keeps) (see
    :func:`chamfer_distance`); ValueError when none is left."""
    gt_kept = np.ones(len(gt_points), dtype=bool)
    if region == "masks":
        step("culling to the view masks")
        pred_points = pred_points[cull_to_masks(pred_points, cull_views, cull_dilation_px)]
    elif region == "object":
        step("culling to the object silhouettes")
        pred_points = pred_points[in_object_region(pred_points, gt, cull_views, cull_dilation_px, occluder)]
        step("GT visibility")
        gt_kept = visible_from_views(gt_points, cull_views, gt if occluder is None else occluder)
        if not gt_kept.any():
            raise ValueError("chamfer_distance: no view sees the ground-truth mesh (cameras and mesh in different frames?)")
    if len(pred_points) == 0:
        raise ValueError("chamfer_distance: every predicted point lies outside the masks")
    return pred_points, gt_kept


def _visibility_codes(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                      classes: VisibilityClasses | None) -> np.ndarray:
    """(N,) visibility class codes of GT samples from the views' GT depth maps."""
    classes = classes or VisibilityClasses()
    return classify_counts(*depth_map_counts(points, normals, views, classes), classes)


def visible_surface_figures(
    accuracy_uncapped: float, to_pred: np.ndarray, codes: np.ndarray, classes: VisibilityClasses | None = None,
    source: str = "ground-truth depth maps", missing_dist: float | None = None,
) -> dict[str, object]:
    """The visible-surface figures of :func:`chamfer_distance` from the uncapped accuracy, every GT
    sample's distance to the prediction ``to_pred`` (N,) and its visibility class code (N,)
    (:func:`polargs_plugin.data.visibility.classify_counts`); ``source``: where the depth maps
    the codes come from; with ``missing_dist``, also each class's share of samples farther than
    it (``missing_by_visibility``)."""
    classes = classes or VisibilityClasses()
    seen = codes != UNSEEN
    completeness = float(to_pred[seen].mean()) if seen.any() else math.nan

    def class_mean(code: int, values: np.ndarray) -> float:
        members = codes == code
        return float(values[members].mean()) if members.any() else math.nan

    missing = {} if missing_dist is None else {
        "missing_by_visibility": {name: class_mean(code, to_pred > missing_dist) for code, name in enumerate(CLASS_NAMES)},
        "missing_dist": float(missing_dist)}
    return {
        "visible_fraction": float(seen.mean()),
        "completeness_visible": completeness,
        "chamfer_visible": (accuracy_uncapped + completeness) / 2,
        "visibility_shares": {name: float((codes == code).sum() / max(1, seen.sum())) for code, name in enumerate(CLASS_NAMES)},
        "completeness_by_visibility": {name: class_mean(code, to_pred) for code, name in enumerate(CLASS_NAMES)},
        **missing,
        "visibility_classes": {"many_views": classes.many_views, "grazing_deg": classes.grazing_deg,
                               "source": source},
    }


def _distance_figures(
    to_gt: np.ndarray, to_pred: np.ndarray, signed: np.ndarray, max_dist: float, fscore_threshold: float
) -> dict[str, float]:
    """Accuracy, completeness, Chamfer (capped at ``max_dist`` and uncapped), precision, recall,
    F-score and the signed-distance figures of :func:`chamfer_distance`."""

    def kept_mean(d: np.ndarray) -> float:
        kept = d[d <= max_dist]
        return float(kept.mean()) if len(kept) else math.nan

    accuracy, completeness = kept_mean(to_gt), kept_mean(to_pred)
    accuracy_all, completeness_all = float(to_gt.mean()), float(to_pred.mean())
    precision = float((to_gt < fscore_threshold).mean())
    recall = float((to_pred < fscore_threshold).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "accuracy": accuracy,
        "completeness": completeness,
        "chamfer": (accuracy + completeness) / 2,
        "accuracy_uncapped": accuracy_all,
        "completeness_uncapped": completeness_all,
        "chamfer_uncapped": (accuracy_all + completeness_all) / 2,
        "precision": precision,
        "recall": recall,
        "fscore": fscore,
        "accuracy_outliers": float((to_gt > max_dist).mean()),
        "completeness_outliers": float((to_pred > max_dist).mean()),
        "signed_distance_median": float(np.median(signed)),
        "signed_distance_mean": float(signed.mean()),
        "inside_fraction": float((signed < 0).mean()),
    }


def normal_angle_errors(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Angles between predicted and ground-truth normals at the masked pixels.

    Both normal maps are renormalised; a zero-length normal (no geometry rendered) has dot
    product 0 with anything and so counts as 90 degrees.

    Args:
        pred: (3, H, W) normals (any length), same frame as ``gt``.
        gt: (3, H, W) normals.
        mask: (1, H, W) bool pixels to evaluate.

    Returns:
        (M,) float64 angles in degrees, M = number of masked pixels.
    """
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[0] != 3:
        raise ValueError(f"normal maps must both be (3, H, W), got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if mask.shape != (1, *pred.shape[1:]):
        raise ValueError(f"mask must be (1, H, W) = {(1, *pred.shape[1:])}, got {tuple(mask.shape)}")
    sel = mask[0].to(torch.bool)
    p = F.normalize(pred.detach().to(torch.float64)[:, sel], dim=0)
    g = F.normalize(gt.detach().to(torch.float64)[:, sel], dim=0)
    return torch.rad2deg(torch.arccos((p * g).sum(0).clamp(-1.0, 1.0)))


def normal_mae(
    pred: Sequence[Tensor] | Tensor,
    gt: Sequence[Tensor] | Tensor,
    masks: Sequence[Tensor] | Tensor,
) -> float:
    """Normal mean angular error in degrees: averaged per view, then over views (NeISF protocol).

    Args:
        pred: V predicted normal maps (3, H, W) (a list or a (V, 3, H, W) tensor).
        gt: V ground-truth normal maps (3, H, W), same frame as ``pred``.
        masks: V bool masks (1, H, W).

    Returns:
        mean angular error in degrees.

    Raises:
        ValueError: if the counts differ, nothing is given, or a mask is empty.
    """
    if not (len(pred) == len(gt) == len(masks)) or len(pred) == 0:
        raise ValueError(f"normal_mae needs matching non-empty lists, got {len(pred)}, {len(gt)}, {len(masks)}")
    per_view = []
    for i, (p, g, m) in enumerate(zip(pred, gt, masks)):
        if not bool(m.any()):
            raise ValueError(f"normal_mae: mask of view {i} is empty; nothing to evaluate")
        per_view.append(float(normal_angle_errors(p, g, m).mean()))
    return float(np.mean(per_view))


# Upper ends (pixels) of the contour-distance bands of :func:`normal_errors_by_contour_distance`;
# the last band is everything beyond the last value. The first two pixels hold the screen-space
# dilation's and the mask's blur; beyond eight a pixel lies on the open surface.
CONTOUR_BANDS_PX: tuple[float, ...] = (2.0, 4.0, 8.0)


def depth_jumps(depth: np.ndarray, ratio: float = 0.05) -> np.ndarray:
    """(H, W) bool: both pixels of every 4-neighbour pair whose depths differ by more than
    ``ratio`` times the nearer one (an occlusion contour inside the object). 0 = no depth; a
    pair with such a pixel is the silhouette's, not a jump.

    >>> depth_jumps(np.array([[0.0, 2.0, 2.0, 3.0, 3.0]])).astype(int).tolist()
    [[0, 0, 1, 1, 0]]
    """
    jump = np.zeros(depth.shape, bool)
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1], np.s_[1:])):
        near = np.minimum(depth[a], depth[b])
        rel = (near > 0) & (np.abs(depth[b] - depth[a]) > ratio * near)
        jump[a] |= rel
        jump[b] |= rel
    return jump


def contour_distance(mask: np.ndarray, depth: np.ndarray | None = None, jump_ratio: float = 0.05) -> np.ndarray:
    """(H, W) float64 Euclidean distance in pixels from each pixel of ``mask`` to the object's
    nearest contour: the nearest pixel outside the mask (the silhouette; an adjacent pixel is 1
    away) or, with ``depth``, the nearest pixel of a :func:`depth_jumps` pair (0 on one). 0 outside
    the mask. The image border is not a contour (an object cut by the frame has none there).
    """
    mask = np.asarray(mask, bool)
    if not (~mask).any():
        inside = np.full(mask.shape, np.inf)
    else:
        inside = distance_transform_edt(mask)
    if depth is not None:
        jump = depth_jumps(np.asarray(depth, np.float64), jump_ratio) & mask
        if jump.any():
            inside = np.minimum(inside, distance_transform_edt(~jump))
    return np.where(mask, inside, 0.0)


def normal_errors_by_contour_distance(
    pred: Sequence[Tensor],
    gt: Sequence[Tensor],
    masks: Sequence[Tensor],
    depths: Sequence[Tensor] | None = None,
    bands: Sequence[float] = CONTOUR_BANDS_PX,
) -> list[dict[str, float]]:
    """Normal angular error by distance to the nearest contour, pooled over the views' pixels.

    Where the error sits tells a renderer's or a model's trouble at silhouettes and occlusion
    edges (splats seen edge-on, the screen-space dilation) from trouble on the open surface.

    Args:
        pred, gt, masks: as :func:`normal_mae` (V views of (3, H, W), (3, H, W), (1, H, W)).
        depths: optional V ground-truth depth maps (1, H, W) whose jumps count as contours
            (:func:`contour_distance`).
        bands: increasing upper ends in pixels; band k holds the pixels at a distance in
            (bands[k-1], bands[k]] (the first from 0), the last band those beyond ``bands[-1]``.

    Returns:
        one dict a band: ``low``, ``high`` (inf for the last), ``mae_deg`` (mean over its pixels;
        nan where it has none) and ``share`` (its fraction of all evaluated pixels).

    Raises:
        ValueError: mismatched counts, no views, bands not increasing and positive, or no pixel
            to evaluate.
    """
    if not (len(pred) == len(gt) == len(masks)) or len(pred) == 0 or (depths is not None and len(depths) != len(pred)):
        raise ValueError("normal_errors_by_contour_distance needs matching non-empty lists of views")
    edges = [0.0, *[float(b) for b in bands]]
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise ValueError(f"bands must be positive and increasing, got {tuple(bands)}")
    distances, errors = [], []
    for i, (p, g, m) in enumerate(zip(pred, gt, masks)):
        depth = None if depths is None else depths[i][0].detach().cpu().numpy()
        inside = m[0].detach().cpu().numpy().astype(bool)
        distances.append(contour_distance(inside, depth)[inside])
        errors.append(normal_angle_errors(p, g, m).cpu().numpy())
    distance, error = np.concatenate(distances), np.concatenate(errors)
    if error.size == 0:
        raise ValueError("normal_errors_by_contour_distance: every mask is empty; nothing to evaluate")
    out = []
    for k, low in enumerate(edges):
        high = edges[k + 1] if k + 1 < len(edges) else math.inf
        sel = ((distance > low) | (k == 0)) & (distance <= high)
        out.append({
            "low": low, "high": high, "share": float(sel.mean()),
            "mae_deg": float(error[sel].mean()) if sel.any() else math.nan,
        })
    return out
