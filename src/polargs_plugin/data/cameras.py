"""Camera conventions of the supported datasets, converted to and from the project's one.

The project convention (docs/conventions.md): OpenCV camera frame (x right, y down, z forward),
``K`` 3x3 with pixel centres at +0.5 (pixel (u, v) has its centre at (u + 0.5, v + 0.5)), a 4x4
``world_to_camera`` (not transposed). Everything here is float64 numpy, (3, 3) / (4, 4) matrices.

Conventions converted:

- IDR / NeuS / NeRSP / PANDORA ``cameras.npz``: P = (world_mat @ scale_mat)[:3, :4] = K [R | t]
  in OpenCV axes, split by ``cv2.decomposeProjectionMatrix`` (K normalised by K[2, 2]).
- LLFF / NeISF ``poses_bounds.npy``: the 3x4 block is camera-to-world with columns
  [down, right, backwards] (NeISF's code reads it this way, whatever its README says).
- OpenGL / Blender / NeRF camera-to-world: columns [right, up, backwards].
- Inria 3DGS: ``R`` stored as the transpose of the world-to-camera rotation, ``T`` the
  world-to-camera translation; ``world_view_transform`` is the transposed 4x4.
- COLMAP: ``qvec`` (w, x, y, z) and ``tvec`` of world-to-camera, OpenCV axes; COLMAP already puts
  pixel centres at +0.5 (the upper-left pixel's centre is (0.5, 0.5)), as we do.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from polargs_plugin.io import PolarInputError, atomic_path

__all__ = [
    "look_at",
    "project_points",
    "validate_camera",
    "decompose_projection",
    "projection_matrix",
    "IDR_PIXEL_CENTER_OFFSET",
    "load_npz",
    "idr_camera",
    "idr_world_mat",
    "write_idr_cameras",
    "llff_to_world_to_camera",
    "world_to_camera_to_llff",
    "opengl_c2w_to_world_to_camera",
    "world_to_camera_to_opengl_c2w",
    "inria_to_world_to_camera",
    "world_to_camera_to_inria",
    "intrinsics_from_fov",
    "qvec_to_rotmat",
    "rotmat_to_qvec",
    "similarity_transform",
    "camera_centers",
]

_OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0])
"""Flip of y and z: OpenGL camera axes (right, up, back) -> OpenCV (right, down, forward)."""

_ORTHONORMAL_TOL = 1e-6


def _as_rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = t
    return w2c


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera (4, 4) of an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that appears upwards in the image (camera -y).
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    right /= norm
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    return _as_rigid(R, -R @ eye)


def project_points(K: np.ndarray, world_to_camera: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) (+0.5 centres) of world points (N, 3)."""
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    uvw = cam @ K.T
    return uvw[:, :2] / uvw[:, 2:3]


def validate_camera(K: np.ndarray, world_to_camera: np.ndarray, source: str | os.PathLike) -> None:
    """Raise :class:`PolarInputError` unless K is a finite upper-triangular intrinsic matrix
    with positive focal lengths and ``world_to_camera`` a finite proper rigid transform."""
    if not (np.isfinite(K).all() and np.isfinite(world_to_camera).all()):
        raise PolarInputError(source, "camera matrix has non-finite entries")
    if K.shape != (3, 3) or world_to_camera.shape != (4, 4):
        raise PolarInputError(source, f"camera shapes {K.shape}, {world_to_camera.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-9 or np.abs(K[[1, 2, 2], [0, 0, 1]]).max() > 1e-9:
        raise PolarInputError(source, f"invalid intrinsics {K.tolist()}")
    R = world_to_camera[:3, :3]
    if (
        np.abs(R @ R.T - np.eye(3)).max() > _ORTHONORMAL_TOL
        or np.linalg.det(R) < 0
        or np.abs(world_to_camera[3] - [0, 0, 0, 1]).max() > 1e-12
    ):
        raise PolarInputError(source, "world_to_camera is not a proper rigid transform")


def decompose_projection(P: np.ndarray, source: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Split a pinhole projection P = K [R | t] (any non-zero scale) into K and world_to_camera.

    Args:
        P: (3, 4) projection matrix, OpenCV axes.
        source: file named in errors.

    Returns:
        K (3, 3) with K[2, 2] = 1 and positive focal lengths, world_to_camera (4, 4).
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4):
        raise PolarInputError(source, f"projection matrix has shape {P.shape}, expected (3, 4)")
    if not np.isfinite(P).all():
        raise PolarInputError(source, "projection matrix has non-finite entries")
    M = P[:, :3]
    det = np.linalg.det(M)
    if not abs(det) > 1e-12 * max(np.abs(M).max(), 1e-300) ** 3:
        raise PolarInputError(source, "projection matrix is singular (its 3x3 part has rank < 3)")
    if det < 0:  # P is defined up to scale; pick the sign that makes R a rotation
        P = -P
    K, R, centre_h = cv2.decomposeProjectionMatrix(P)[:3]
    # RQ leaves the sign of each axis free: force positive focal lengths and K[2, 2].
    signs = np.sign(np.diag(K))
    K = K * signs[None, :]
    R = R * signs[:, None]
    K = K / K[2, 2]
    centre = centre_h[:3, 0] / centre_h[3, 0]
    w2c = _as_rigid(R, -R @ centre)
    validate_camera(K, w2c, source)
    return K, w2c


def projection_matrix(K: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """P = K [R | t] as a (4, 4) matrix with last row [0, 0, 0, 1] (the IDR ``world_mat`` layout)."""
    P = np.eye(4)
    P[:3, :4] = K @ world_to_camera[:3, :4]
    return P


def llff_to_world_to_camera(block: np.ndarray) -> np.ndarray:
    """LLFF/NeISF 3x4 camera-to-world block (columns down, right, back, position) -> w2c (4, 4)."""
    down, right, back, position = (block[:, i] for i in range(4))
    c2w_rotation = np.stack([right, down, -back], axis=1)  # OpenCV columns: right, down, forward
    R = c2w_rotation.T
    return _as_rigid(R, -R @ position)


def world_to_camera_to_llff(world_to_camera: np.ndarray) -> np.ndarray:
    """Inverse of :func:`llff_to_world_to_camera`: w2c (4, 4) -> (3, 4) [down, right, back, position]."""
    R = world_to_camera[:3, :3]
    position = -R.T @ world_to_camera[:3, 3]
    right, down, forward = R  # rows of w2c = camera axes in world coordinates
    return np.stack([down, right, -forward, position], axis=1)


def opengl_c2w_to_world_to_camera(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/Blender camera-to-world (4, 4), columns [right, up, back] -> OpenCV w2c (4, 4)."""
    R = (c2w[:3, :3] @ _OPENCV_FROM_OPENGL).T
    return _as_rigid(R, -R @ c2w[:3, 3])


def world_to_camera_to_opengl_c2w(world_to_camera: np.ndarray) -> np.ndarray:
    """OpenCV w2c (4, 4) -> OpenGL/Blender camera-to-world (4, 4)."""
    c2w = np.eye(4)
    c2w[:3, :3] = world_to_camera[:3, :3].T @ _OPENCV_FROM_OPENGL
    c2w[:3, 3] = -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
    return c2w


def inria_to_world_to_camera(R_stored: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Inria 3DGS camera storage (R = w2c rotation transposed, T = w2c translation) -> w2c (4, 4).

    For ``world_view_transform`` (the transposed 4x4) use its transpose directly.
    """
    return _as_rigid(np.asarray(R_stored).T, T)


def world_to_camera_to_inria(world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV w2c (4, 4) -> Inria 3DGS (R stored transposed, T)."""
    return world_to_camera[:3, :3].T.copy(), world_to_camera[:3, 3].copy()


def intrinsics_from_fov(fov_x: float, fov_y: float, width: int, height: int) -> np.ndarray:
    """K of a centred pinhole (Inria 3DGS / Blender): principal point at the image centre,
    which with +0.5 pixel centres is (width / 2, height / 2)."""
    fx = width / (2 * np.tan(fov_x / 2))
    fy = height / (2 * np.tan(fov_y / 2))
    return np.array([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=np.float64)


def qvec_to_rotmat(qvec: np.ndarray) -> np.ndarray:
    """COLMAP quaternion (w, x, y, z) -> rotation (3, 3) (normalised first)."""
    w, x, y, z = np.asarray(qvec, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) -> unit quaternion (w, x, y, z) with w >= 0."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


IDR_PIXEL_CENTER_OFFSET = 0.0
"""Added to the principal point of an IDR ``cameras.npz`` K to get ours.

0: the K in IDR-style files is taken to already use +0.5 pixel centres, because the producers of
these files put the principal point in continuous image coordinates: COLMAP-derived cameras
(PANDORA, RMVP3D, NeuS preprocessing) and renderer cameras with the principal point at the image
centre W/2 (SMVP3D, Mitsuba). The IDR/NeuS/NeRSP training code casts rays through integer pixel
coordinates, half a pixel off from this; we do not reproduce that offset."""


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` file (no pickles), raising :class:`PolarInputError` if unreadable."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {key: npz[key] for key in npz.files}
    except FileNotFoundError:
        raise PolarInputError(path, "file not found") from None
    except (ValueError, OSError, EOFError) as err:
        raise PolarInputError(path, f"cannot be read as .npz ({err})") from None


def idr_camera(
    arrays: dict[str, np.ndarray],
    world_key: str,
    scale_key: str,
    path: str | os.PathLike,
    normalize: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) and world_to_camera (4, 4) of one IDR camera.

    Args:
        arrays: contents of ``cameras.npz``.
        world_key, scale_key: its keys, e.g. ``world_mat_0`` and ``scale_mat_0``.
        path: the npz file, named in errors.
        normalize: True decomposes world_mat @ scale_mat (the unit-sphere frame that IDR, NeuS,
            NeRSP and PolGS train in); False decomposes world_mat alone (the capture frame, in
            which ground-truth meshes are usually given).
    """
    keys = [world_key, scale_key] if normalize else [world_key]
    for key in keys:
        if key not in arrays:
            raise PolarInputError(path, f"missing key {key!r} (keys: {sorted(arrays)[:8]}...)")
    P = np.asarray(arrays[world_key], dtype=np.float64)
    source = f"{path}[{world_key}]"
    if P.shape not in ((4, 4), (3, 4)):
        raise PolarInputError(source, f"shape {P.shape}, expected (4, 4) or (3, 4)")
    if not np.isfinite(P).all():
        raise PolarInputError(source, "camera matrix has non-finite entries")
    if normalize:
        scale = np.asarray(arrays[scale_key], dtype=np.float64)
        if scale.shape != (4, 4) or not np.isfinite(scale).all() or abs(np.linalg.det(scale)) < 1e-300:
            raise PolarInputError(f"{path}[{scale_key}]", "scale matrix must be a finite invertible 4x4")
        P = P[:3, :4] @ scale
    K, w2c = decompose_projection(P[:3, :4], source)
    K[:2, 2] += IDR_PIXEL_CENTER_OFFSET
    return K, w2c


def idr_world_mat(K: np.ndarray, world_to_camera: np.ndarray, scale_mat: np.ndarray) -> np.ndarray:
    """``world_mat`` (4, 4) such that (world_mat @ scale_mat)[:3] = K [R | t] (inverse of :func:`idr_camera`)."""
    K_idr = K.copy()
    K_idr[:2, 2] -= IDR_PIXEL_CENTER_OFFSET
    return projection_matrix(K_idr, world_to_camera) @ np.linalg.inv(scale_mat)


def write_idr_cameras(path: str | os.PathLike, cameras: dict[str, tuple[np.ndarray, np.ndarray]], scale_mat: np.ndarray) -> None:
    """Write an IDR ``cameras.npz`` atomically: ``world_mat_<key>`` and ``scale_mat_<key>`` per camera.

    Args:
        path: the ``.npz`` file.
        cameras: {key: (K (3, 3), world_to_camera (4, 4))}, in the order to store them.
        scale_mat: (4, 4) IDR scale matrix shared by every camera (:func:`idr_world_mat`).
    """
    arrays = {}
    for key, (K, world_to_camera) in cameras.items():
        arrays[f"world_mat_{key}"] = idr_world_mat(K, world_to_camera, scale_mat)
        arrays[f"scale_mat_{key}"] = scale_mat
    with atomic_path(path) as tmp:
        np.savez(tmp, **arrays)


def camera_centers(world_to_camera: np.ndarray) -> np.ndarray:
    """(N, 3) world positions of the cameras of (N, 4, 4) world_to_camera matrices: -R^T t."""
    w2c = np.asarray(world_to_camera, dtype=np.float64)
    return -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])


def similarity_transform(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale s, rotation R, translation t) taking the points ``source`` closest to
    ``target`` in least squares, ``target ~ s R source + t`` (Umeyama 1991, no reflection).

    The frame of a structure-from-motion model is fixed only up to a similarity: mapping its
    camera centres onto known ones brings a reconstruction into the known frame, e.g. to compare
    it with a ground-truth mesh.

    Args:
        source, target: (N, 3) corresponding points, N >= 3 and not all on one line.

    Returns:
        (s, R (3, 3), t (3,)).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> points = rng.normal(size=(6, 3))
        >>> R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
        >>> s, R_found, t = similarity_transform(points, 2.0 * points @ R.T + [1.0, 2.0, 3.0])
        >>> round(s, 6), np.allclose(R_found, R), np.round(t, 6).tolist()
        (2.0, True, [1.0, 2.0, 3.0])
    """
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"need two (N, 3) point sets of one shape with N >= 3, got {source.shape} and {target.shape}")
    mu_source, mu_target = source.mean(0), target.mean(0)
    centred_source, centred_target = source - mu_source, target - mu_target
    U, S, Vt = np.linalg.svd(centred_target.T @ centred_source / len(source))
    if S[1] <= 1e-12 * max(S[0], 1e-300):
        raise ValueError("the points lie on one line (or one point): the rotation is not determined")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])  # a rotation, never a reflection
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / (centred_source**2).sum(1).mean())
    return scale, R, mu_target - scale * R @ mu_source
