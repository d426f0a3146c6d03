"""Mesh extraction by TSDF fusion of rendered depth maps (open3d tensor VoxelBlockGrid, CPU).

Every view contributes its rendered camera-z depth and colour; pixels outside the object mask,
below an alpha threshold, non-finite or beyond ``depth_trunc`` are ignored. The fused surface is
extracted by marching cubes and, by default, reduced to its largest connected cluster (floaters
left by stray Gaussians are discarded).

Pixel centres: open3d's tensor TSDF kernel reads, for a voxel projecting to (u, v), the pixel
(floor(u), floor(v)); pixel (i, j) thus spans [i, i + 1) x [j, j + 1) with its centre at
(i + 0.5, j + 0.5), the package's convention (docs/conventions.md), so ``K`` is passed unchanged.
(open3d's legacy ``PinholeCameraIntrinsic`` / ``create_from_depth_image`` put pixel centres at
integers instead and would need cx - 0.5, cy - 0.5.) tests/test_mesh.py pins this with a tilted
plane, whose fused surface is biased by half a pixel's depth change if the convention is off.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
from torch import Tensor

from polargs_plugin.io import PolarInputError, atomic_path

__all__ = [
    "MESH_PRESETS",
    "canonical_mesh_order",
    "mesh_settings",
    "tsdf_fuse",
    "keep_largest_cluster",
    "write_mesh",
    "read_mesh",
]

# TSDF settings in scene units. "paper": the PolarGS paper (voxel 0.008, SDF truncation 0.04,
# depth truncation 10). "synthetic": the bundled synthetic scenes (objects of radius ~1, cameras
# at distance 2.6-3, 40 degree field of view, 128 px): voxel = radius / 128, about 0.5-0.7 of a
# pixel's footprint on the object (much finer voxels turn the nearest-pixel depth lookup into a
# staircase that falls apart into fragments); SDF truncation = 4 voxels (the 2DGS / PGSR ratio);
# depth truncation 6 = farthest object point (distance + radius) with a wide margin.
MESH_PRESETS: dict[str, dict[str, float]] = {
    "paper": {"voxel_size": 0.008, "sdf_trunc": 0.04, "depth_trunc": 10.0},
    "synthetic": {"voxel_size": 1.0 / 128.0, "sdf_trunc": 4.0 / 128.0, "depth_trunc": 6.0},
}


def mesh_settings(
    preset: str = "synthetic",
    voxel_size: float | None = None,
    sdf_trunc: float | None = None,
    depth_trunc: float | None = None,
) -> dict[str, float]:
    """TSDF settings from a preset with optional overrides.

    Overriding only ``voxel_size`` rescales ``sdf_trunc`` so that it keeps the preset's
    truncation-to-voxel ratio.

    Returns:
        dict with ``voxel_size``, ``sdf_trunc`` and ``depth_trunc`` (scene units).
    """
    if preset not in MESH_PRESETS:
        raise ValueError(f"unknown mesh preset {preset!r}; choose one of {sorted(MESH_PRESETS)}")
    base = MESH_PRESETS[preset]
    out = dict(base)
    if voxel_size is not None:
        out["voxel_size"] = float(voxel_size)
        out["sdf_trunc"] = float(voxel_size) * base["sdf_trunc"] / base["voxel_size"]
    if sdf_trunc is not None:
        out["sdf_trunc"] = float(sdf_trunc)
    if depth_trunc is not None:
        out["depth_trunc"] = float(depth_trunc)
    _check_lengths(**out)
    return out


def _check_lengths(**lengths: float) -> None:
    for key, value in lengths.items():
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{key} must be a positive number, got {value}")


def _numpy(x: Tensor | np.ndarray, dtype: type) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def keep_largest_cluster(
    mesh: o3d.geometry.TriangleMesh, min_fraction: float = 1.0, spared: np.ndarray | None = None,
    spared_share: float = 0.9,
) -> o3d.geometry.TriangleMesh:
    """Drop small connected pieces (in place; returns ``mesh``).

    Args:
        mesh: triangle mesh.
        min_fraction: keep every connected component with at least this fraction of the
            largest component's triangles; 1.0 keeps only the largest (one of them on a tie).
        spared: optional (V,) bool per vertex of ``mesh``: a smaller component stays when at
            least ``spared_share`` of its triangles' corners are spared vertices (e.g. vertices
            inside every view's mask).
        spared_share: that share, in (0, 1].
    """
    if len(mesh.triangles) == 0:
        return mesh
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    # min_fraction >= 1 keeps exactly one component even when several tie for the largest.
    small = np.ones_like(counts, dtype=bool) if min_fraction >= 1 else counts < min_fraction * counts.max()
    small[int(np.argmax(counts))] = False
    if spared is not None and small.any():
        spared = np.asarray(spared, dtype=bool)
        if spared.shape != (len(mesh.vertices),):
            raise ValueError(f"keep_largest_cluster: spared must be ({len(mesh.vertices)},), got {spared.shape}")
        # share over the components' triangle corners: a vertex counts once per triangle it is in
        corners = spared[np.asarray(mesh.triangles)].sum(axis=1)
        share = np.bincount(labels, weights=corners, minlength=len(counts)) / (3.0 * counts)
        small &= share < spared_share
    mesh.remove_triangles_by_mask(small[labels])
    mesh.remove_unreferenced_vertices()
    return mesh


def tsdf_fuse(
    depths: Sequence[Tensor] | Tensor,
    colors: Sequence[Tensor] | Tensor,
    Ks: Sequence[Tensor] | Tensor,
    world_to_cameras: Sequence[Tensor] | Tensor,
    masks: Sequence[Tensor | None] | Tensor | None = None,
    voxel_size: float = MESH_PRESETS["synthetic"]["voxel_size"],
    sdf_trunc: float = MESH_PRESETS["synthetic"]["sdf_trunc"],
    depth_trunc: float = MESH_PRESETS["synthetic"]["depth_trunc"],
    keep_largest: bool | float = True,
    alphas: Sequence[Tensor] | Tensor | None = None,
    alpha_threshold: float | None = None,
    min_views: int = 1,
    incidences: Sequence[Tensor] | Tensor | None = None,
    max_trunc_scale: float = 1.0,
    progress: bool = False,
) -> o3d.geometry.TriangleMesh:
    """Fuse per-view depth and colour into a triangle mesh (open3d VoxelBlockGrid on CPU).

    Args:
        depths: V maps (1, H, W) camera-z depth; 0, negative or non-finite = no measurement.
        colors: V images (3, H, W) linear RGB in [0, 1] (become vertex colours).
        Ks: V intrinsics (3, 3), pixel centres at +0.5.
        world_to_cameras: V rigid transforms (4, 4), OpenCV camera frame.
        masks: optional V bool masks (1, H, W) (an entry may be None); depth is zeroed outside.
        voxel_size: TSDF voxel edge (scene units).
        sdf_trunc: SDF truncation distance (scene units).
        depth_trunc: depths beyond this are ignored (scene units).
        keep_largest: True keeps only the largest connected cluster of triangles; a number f
            in (0, 1] keeps every cluster with at least f times its triangles (scenes of several
            separate objects); False keeps everything.
        alphas: optional V accumulated opacities (1, H, W), used with ``alpha_threshold``.
        alpha_threshold: depth is zeroed where alpha < threshold (GOF uses 0.5).
        min_views: voxels integrated from fewer views than this are not meshed.
        incidences: optional V maps (1, H, W) of the cosine between each pixel's surface normal
            and its viewing ray (e.g. from the rendered normals), used with ``max_trunc_scale``.
        max_trunc_scale: with ``incidences``, each pixel's SDF truncation is ``sdf_trunc``
            times 1/cos, capped at this and rounded to a multiple of 0.5 (1 disables). The SDF
            a view measures runs along its rays, 1/cos times the distance from the surface, so
            a fixed truncation gives a grazing view a band only ``sdf_trunc * cos`` thick around
            the surface, often thinner than a voxel; the scaled truncation keeps the band's
            thickness, and the stored TSDF values the same scale, at every incidence.
        progress: show a tqdm progress bar over the views.

    Returns:
        open3d (legacy) TriangleMesh with vertex colours and normals; empty if nothing valid
        was observed.
    """
    num = len(depths)
    _check_fusion_inputs(num, colors, Ks, world_to_cameras, masks, alphas, alpha_threshold)
    _check_lengths(voxel_size=voxel_size, sdf_trunc=sdf_trunc, depth_trunc=depth_trunc)
    _check_incidences(num, incidences, max_trunc_scale)
    grid = _voxel_grid(voxel_size)
    trunc_multiplier = float(sdf_trunc) / float(voxel_size)
    integrated = 0
    from tqdm import tqdm

    for i in tqdm(range(num), desc="TSDF fusion", unit="view", disable=not progress):
        view = _measured_view(i, depths, colors, masks, alphas, alpha_threshold, depth_trunc)
        if view is None:
            continue  # open3d refuses a frame that touches no block
        scales = _trunc_scales(i, incidences, max_trunc_scale, view[0].shape)
        _integrate(grid, i, *view, Ks[i], world_to_cameras[i], voxel_size, trunc_multiplier, depth_trunc, scales)
        integrated += 1

    if integrated == 0:
        return o3d.geometry.TriangleMesh()

    # Voxel weights count integrations; open3d meshes voxels with weight > threshold.
    mesh = grid.extract_triangle_mesh(weight_threshold=float(min_views) - 0.5).to_legacy()
    if keep_largest is not False:
        keep_largest_cluster(mesh, 1.0 if keep_largest is True else float(keep_largest))
    mesh.compute_vertex_normals()
    return mesh


def _check_fusion_inputs(num: int, colors, Ks, world_to_cameras, masks, alphas, alpha_threshold) -> None:
    """ValueError unless every per-view sequence of :func:`tsdf_fuse` has ``num`` entries."""
    for name, seq in (("colors", colors), ("Ks", Ks), ("world_to_cameras", world_to_cameras)):
        if len(seq) != num:
            raise ValueError(f"tsdf_fuse: {num} depth maps but {len(seq)} {name}")
    if masks is not None and len(masks) != num:
        raise ValueError(f"tsdf_fuse: {num} depth maps but {len(masks)} masks")
    if alpha_threshold is not None and (alphas is None or len(alphas) != num):
        raise ValueError("tsdf_fuse: alpha_threshold needs one alpha map per depth map")


def _check_incidences(num: int, incidences, max_trunc_scale: float) -> None:
    """ValueError unless ``max_trunc_scale`` >= 1 and, when it is above 1, there is one incidence map per view."""
    if not (np.isfinite(max_trunc_scale) and max_trunc_scale >= 1.0):
        raise ValueError(f"tsdf_fuse: max_trunc_scale must be a number >= 1, got {max_trunc_scale}")
    if max_trunc_scale > 1.0 and (incidences is None or len(incidences) != num):
        raise ValueError("tsdf_fuse: max_trunc_scale > 1 needs one incidence map per depth map")


# Truncation scales are rounded to this step: each distinct scale costs one integration pass.
_TRUNC_SCALE_STEP = 0.5


def _trunc_scales(i: int, incidences, max_trunc_scale: float, shape: tuple[int, int]) -> np.ndarray | None:
    """View ``i``'s per-pixel truncation scale (H, W): 1/|cos| capped at ``max_trunc_scale``, rounded
    to a multiple of 0.5; None when ``max_trunc_scale`` is 1 (no incidence-aware truncation)."""
    if max_trunc_scale <= 1.0:
        return None
    cosine = _numpy(incidences[i], np.float64)
    if cosine.shape != (1, *shape):
        raise ValueError(f"tsdf_fuse: incidence {i} must be (1, {shape[0]}, {shape[1]}), got {cosine.shape}")
    # A non-finite cosine (no normal) gets the widest band, as a grazing pixel would.
    cosine = np.nan_to_num(np.abs(cosine[0]), nan=0.0, posinf=0.0, neginf=0.0)
    scale = np.minimum(1.0 / np.maximum(cosine, 1e-6), max_trunc_scale)
    return np.maximum(np.round(scale / _TRUNC_SCALE_STEP) * _TRUNC_SCALE_STEP, 1.0)


def _voxel_grid(voxel_size: float) -> o3d.t.geometry.VoxelBlockGrid:
    """An empty CPU voxel block grid holding TSDF, weight and colour."""
    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=(1, 1, 3),
        voxel_size=float(voxel_size),
        block_resolution=8,
        block_count=10_000,  # initial capacity; the CPU hash map grows as needed
        device=o3c.Device("CPU:0"),
    )


def _measured_view(
    i: int, depths, colors, masks, alphas, alpha_threshold: float | None, depth_trunc: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """View ``i``'s (depth (H, W) with 0 where not measured, colour (3, H, W), invalid (H, W)),
    or None when no pixel is measured; ValueError naming a map of the wrong shape."""
    depth = _numpy(depths[i], np.float32)
    if depth.ndim != 3 or depth.shape[0] != 1:
        raise ValueError(f"tsdf_fuse: depth {i} must be (1, H, W), got {depth.shape}")
    depth = depth[0].copy()
    height, width = depth.shape
    color = _numpy(colors[i], np.float32)
    if color.shape != (3, height, width):
        raise ValueError(f"tsdf_fuse: colour {i} must be (3, {height}, {width}), got {color.shape}")
    invalid = ~np.isfinite(depth) | (depth <= 0) | (depth > depth_trunc)
    if masks is not None and masks[i] is not None:
        mask = _numpy(masks[i], bool)
        if mask.shape != (1, height, width):
            raise ValueError(f"tsdf_fuse: mask {i} must be (1, {height}, {width}), got {mask.shape}")
        invalid |= ~mask[0]
    if alpha_threshold is not None:
        alpha = _numpy(alphas[i], np.float32)
        if alpha.shape != (1, height, width):
            raise ValueError(f"tsdf_fuse: alpha {i} must be (1, {height}, {width}), got {alpha.shape}")
        invalid |= alpha[0] < alpha_threshold
    if invalid.all():
        return None
    depth[invalid] = 0.0
    return depth, color, invalid


def _integrate(
    grid: o3d.t.geometry.VoxelBlockGrid,
    i: int,
    depth: np.ndarray,
    color: np.ndarray,
    invalid: np.ndarray,
    K: Tensor | np.ndarray,
    world_to_camera: Tensor | np.ndarray,
    voxel_size: float,
    trunc_multiplier: float,
    depth_trunc: float,
    trunc_scales: np.ndarray | None = None,
) -> None:
    """Integrate view ``i`` (:func:`_measured_view`) into ``grid``; with ``trunc_scales``
    (:func:`_trunc_scales`), once per distinct scale, each pass with only that scale's pixels.

    A voxel reads the one pixel it projects to, so each view still updates a voxel at most once
    and the voxel weights still count views."""
    extrinsic = _numpy(world_to_camera, np.float64)
    if extrinsic.shape != (4, 4):
        raise ValueError(f"tsdf_fuse: world_to_camera {i} must be (4, 4), got {extrinsic.shape}")
    depth_image = _depth_image(depth)
    color_image = o3d.t.geometry.Image(
        o3c.Tensor(np.ascontiguousarray(np.clip(np.nan_to_num(color), 0.0, 1.0).transpose(1, 2, 0)))
    )
    # The integration kernel reads pixel floor(u), floor(v) of the projection (u, v), i.e.
    # pixel (u, v) spans [u, u + 1): the package's +0.5 pixel-centre K applies unchanged.
    k = _numpy(K, np.float64)
    if k.shape != (3, 3):
        raise ValueError(f"tsdf_fuse: K {i} must be (3, 3), got {k.shape}")
    intrinsic = o3c.Tensor(np.ascontiguousarray(k))
    extrinsic = o3c.Tensor(np.ascontiguousarray(extrinsic))
    # open3d allocates blocks within the truncation distance of each pixel's 3D point; when a
    # pixel covers more than that, blocks between neighbouring pixels would stay unallocated
    # and the mesh would come out in fragments. Touch at least one pixel footprint.
    footprint = float(depth[~invalid].max()) / float(min(k[0, 0], k[1, 1]))
    widest = 1.0 if trunc_scales is None else float(trunc_scales[~invalid].max())
    # Blocks for every pass at once: a pass over a handful of pixels may touch no block of its own.
    blocks = grid.compute_unique_block_coordinates(
        depth_image, intrinsic, extrinsic, 1.0, float(depth_trunc),
        trunc_voxel_multiplier=max(trunc_multiplier * widest, 2.0 * footprint / float(voxel_size)),
    )
    scales = [1.0] if trunc_scales is None else np.unique(trunc_scales[~invalid]).tolist()
    for scale in scales:
        # With one scale the pass is the whole view: no masked copy of the depth.
        image = depth_image if len(scales) == 1 else _depth_image(np.where(trunc_scales == scale, depth, 0.0))
        grid.integrate(
            blocks, image, color_image, intrinsic, intrinsic, extrinsic, 1.0, float(depth_trunc),
            trunc_voxel_multiplier=trunc_multiplier * scale,
        )


def _depth_image(depth: np.ndarray) -> o3d.t.geometry.Image:
    """An open3d float32 depth image (H, W, 1) of ``depth`` (H, W)."""
    return o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth[..., None], dtype=np.float32)))


def write_mesh(path: str | os.PathLike, mesh: o3d.geometry.TriangleMesh) -> Path:
    """Write ``mesh`` atomically (format from the suffix, e.g. .ply); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise PolarInputError(path, "open3d could not write the mesh (unsupported suffix?)")
    return path


def read_mesh(path: str | os.PathLike) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh; raises PolarInputError if it is missing, unreadable, empty or has
    vertices that are not finite (a NaN vertex would poison every distance measured to it)."""
    path = Path(path)
    if not path.is_file():
        raise PolarInputError(path, "mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise PolarInputError(path, "not a readable triangle mesh (no triangles)")
    vertices = np.asarray(mesh.vertices)
    bad = int((~np.isfinite(vertices).all(axis=1)).sum())
    if bad:
        raise PolarInputError(path, f"{bad} of {len(vertices)} vertices are not finite (NaN or inf); "
                              "remove them (and their triangles) before evaluating")
    return mesh


def canonical_mesh_order(path: Path) -> None:
    """Rewrite a mesh with its vertices sorted by position and its triangles sorted (orientation kept).

    open3d's TSDF hash map lists the same surface in a different order from one run to the next,
    and the evaluation's area-uniform sampling (fixed seed) then draws other points: the Chamfer
    figures of two identical trainings would differ in the third digit. In a canonical order the
    same model gives the same figures, which is what a resumed run is checked against.
    """
    mesh = read_mesh(path)
    vertices = np.asarray(mesh.vertices)
    triangles = np.asarray(mesh.triangles)
    if len(vertices) == 0:
        return
    order = np.lexsort(vertices.T[::-1])  # x, then y, then z
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    tri = rank[triangles]
    shift = np.argmin(tri, axis=1)  # rotate each triangle to start at its smallest index (same orientation)
    tri = np.take_along_axis(tri, (shift[:, None] + np.arange(3)) % 3, axis=1)
    tri = tri[np.lexsort(tri.T[::-1])]
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices[order]), o3d.utility.Vector3iVector(tri))
    if mesh.has_vertex_normals():
        out.compute_vertex_normals()  # summed over triangles: recomputed in the canonical order
    if mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[order])
    write_mesh(path, out)
