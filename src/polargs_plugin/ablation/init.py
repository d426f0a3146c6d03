"""Initial points for the ablation runs: sparse SfM points from the known poses (``init sfm``).

:func:`sfm_points` is the paper's initialisation as far as a reference run needs it: SIFT
features on the s0/2 images (8-bit sRGB pictures, as a COLMAP run would see them), exhaustive
matching with geometric verification (pycolmap, the ``sfm`` extra), then every verified match
triangulated with the views' KNOWN cameras (linear DLT) and kept when it lies in front of both
cameras, reprojects within ``max_reprojection_px`` in both, and is seen under at least
``min_angle_deg``. Poses are not re-estimated (they are the dataset's ground truth), so the
points sit in the dataset's frame. Textureless regions get no points, as in real use; the caller
falls back to the visual hull when too few points come out (:data:`MIN_SFM_POINTS`); :func:`initial_points`
chooses between the three initialisations of :data:`~polargs_plugin.ablation.spec.INITS`.
"""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from polargs_plugin.ablation.spec import Cell

__all__ = ["MIN_SFM_POINTS", "initial_points", "sfm_points"]

#: SfM initialisation falls back to the visual hull below this many points.
MIN_SFM_POINTS = 100


def _picture(view) -> np.ndarray:
    """(H, W, 3) uint8 sRGB picture of the training colour s0/2."""
    image = view.image.detach().float().cpu().clamp(0, 1).numpy()
    if image.shape[0] == 1:
        image = np.repeat(image, 3, axis=0)
    srgb = np.where(image <= 0.0031308, 12.92 * image, 1.055 * np.power(image, 1 / 2.4) - 0.055)
    return np.round(np.moveaxis(srgb, 0, -1) * 255).astype(np.uint8)


def _triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of N correspondences (pixel coordinates, +0.5 centres)."""
    rows = np.stack([x1[:, :1] * P1[2] - P1[0], x1[:, 1:2] * P1[2] - P1[1],
                     x2[:, :1] * P2[2] - P2[0], x2[:, 1:2] * P2[2] - P2[1]], axis=1)  # (N, 4, 4)
    _, _, vt = np.linalg.svd(rows)
    X = vt[:, -1]
    return X[:, :3] / X[:, 3:4]


def sfm_points(views, max_reprojection_px: float = 1.5, min_angle_deg: float = 2.0):
    """Sparse points triangulated from SIFT matches with the views' known cameras.

    Args:
        views: the training views (K, world_to_camera, s0/2 image; masks, when present, drop
            matches outside them).
        max_reprojection_px: largest reprojection error kept, in both views.
        min_angle_deg: smallest triangulation angle kept.

    Returns:
        ``(points (N, 3) float32, colours (N, 3) float32 in [0, 1])``, N possibly 0.

    Raises:
        NotImplementedError: pycolmap (the ``sfm`` extra) is not installed.
    """
    import torch

    try:
        import pycolmap
    except ImportError as err:  # the caller records the fallback
        raise NotImplementedError(f"pycolmap is not installed (pip install polargs_plugin[sfm]): {err}") from None
    names = [f"{i:04d}.png" for i in range(len(views))]
    points, colors = [], []
    with tempfile.TemporaryDirectory() as tmp:
        index, keypoints, pairs = _matches(pycolmap, Path(tmp), views, names)
        for pair_id, geometry in pairs:
            matches = np.asarray(geometry.inlier_matches)
            if len(matches) == 0:
                continue
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            vi, vj = views[index[id1]], views[index[id2]]
            # COLMAP keypoints: pixel (0, 0) spans [0, 1) with its centre at 0.5, as ours
            x1, x2 = keypoints[id1][matches[:, 0]], keypoints[id2][matches[:, 1]]
            X, keep = _triangulated(vi, vj, x1, x2, max_reprojection_px, min_angle_deg)
            if not keep.any():
                continue
            points.append(X[keep])
            col = np.clip(x1[keep, 0].astype(int), 0, vi.width - 1)
            row = np.clip(x1[keep, 1].astype(int), 0, vi.height - 1)
            colors.append(vi.image.detach().float().cpu().clamp(0, 1).expand(3, -1, -1).numpy()[:, row, col].T)
    if not points:
        return torch.zeros(0, 3), torch.zeros(0, 3)
    return torch.from_numpy(np.concatenate(points)).float(), torch.from_numpy(np.concatenate(colors)).float()


def _matches(pycolmap, tmp: Path, views, names: list[str]):
    """SIFT features of every view and their exhaustive two-view matches (COLMAP's database in
    ``tmp``): (image id -> view index, image id -> (K, 2) keypoints, [(pair id, two-view geometry)])."""
    import cv2
    import torch

    (tmp / "images").mkdir()
    for name, view in zip(names, views):
        cv2.imwrite(str(tmp / "images" / name), cv2.cvtColor(_picture(view), cv2.COLOR_RGB2BGR))
    database = tmp / "database.db"
    threads = max(1, torch.get_num_threads())  # the run's thread budget, not every core
    extraction, matching = pycolmap.FeatureExtractionOptions(), pycolmap.FeatureMatchingOptions()
    extraction.num_threads = matching.num_threads = threads
    with contextlib.suppress(AttributeError):
        pycolmap.logging.minloglevel = 2  # errors only: glog writes to the terminal directly
    pycolmap.extract_features(database, tmp / "images", image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE"),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(database))
    try:
        index = {image.image_id: names.index(image.name) for image in db.read_all_images()}
        keypoints = {image_id: np.asarray(db.read_keypoints(image_id))[:, :2] for image_id in index}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    return index, keypoints, list(zip(pair_ids, geometries))


def _triangulated(vi, vj, x1: np.ndarray, x2: np.ndarray, max_reprojection_px: float, min_angle_deg: float):
    """Points triangulated from matched pixels ``x1`` of ``vi`` and ``x2`` of ``vj``, and which to
    keep: in front of both cameras, reprojected within ``max_reprojection_px``, inside the masks,
    seen under at least ``min_angle_deg``."""
    Pi = vi.K.double().cpu().numpy() @ vi.world_to_camera.double().cpu().numpy()[:3]
    Pj = vj.K.double().cpu().numpy() @ vj.world_to_camera.double().cpu().numpy()[:3]
    X = _triangulate(Pi, Pj, x1.astype(np.float64), x2.astype(np.float64))
    keep = np.ones(len(X), dtype=bool)
    for P, x, view in ((Pi, x1, vi), (Pj, x2, vj)):
        h = np.c_[X, np.ones(len(X))] @ P.T
        keep &= h[:, 2] > 1e-9
        proj = h[:, :2] / np.where(np.abs(h[:, 2:]) > 1e-12, h[:, 2:], 1e-12)
        keep &= np.linalg.norm(proj - x, axis=1) <= max_reprojection_px
        if view.mask is not None:
            col = np.clip(x[:, 0].astype(int), 0, view.width - 1)
            row = np.clip(x[:, 1].astype(int), 0, view.height - 1)
            keep &= view.mask[0].cpu().numpy()[row, col]
    ci, cj = vi.camera_center.double().cpu().numpy(), vj.camera_center.double().cpu().numpy()
    a, b = X - ci, X - cj
    cos = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    keep &= cos <= np.cos(np.deg2rad(min_angle_deg))
    return X, keep


def initial_points(cell: Cell, views, config):
    """(init_points for the Trainer or None for its default visual hull, record for the summary)."""
    import torch

    info: dict[str, Any] = {"init": cell.init, "init_used": cell.init, "init_note": None}
    if cell.init == "hull":
        info["init_points"] = config.num_init_points
        return None, info
    if cell.init == "random":
        from polargs_plugin.backends.reference.model import init_points_in_box

        points = init_points_in_box(views, config.num_init_points, torch.Generator().manual_seed(cell.seed))
        info["init_points"] = int(points[0].shape[0])
        return points, info
    try:
        points, colors = sfm_points(views)
        count = int(points.shape[0])
        if count >= MIN_SFM_POINTS:
            info["init_points"] = count
            return (points, colors), info
        note = f"SfM found {count} points (< {MIN_SFM_POINTS})"
    except NotImplementedError as err:
        note = f"SfM unavailable ({err})"
    print(f"init: {note}; falling back to the visual hull", flush=True)
    info.update(init_used="hull", init_note=note + "; fell back to the visual hull", init_points=config.num_init_points)
    return None, info
