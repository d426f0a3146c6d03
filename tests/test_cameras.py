"""Camera conventions: each conversion checked against hand-built geometry (docs/conventions.md).

Truth here is written independently of the code under test: a camera at a known position with
known axes, and the pixel a known 3D point must land on (pixel centres at +0.5).
"""

import math

import numpy as np
import pytest

from polargs_plugin.data import cameras as cam
from polargs_plugin.io import PolarInputError

W, H, F = 64, 48, 50.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


def _camera_on_x_axis() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera at (4, 0, 0) looking at the origin with world +z up in the image: forward = -x,
    right = forward x up = +y, down = forward x right = -z (OpenCV axes as world vectors)."""
    centre = np.array([4.0, 0.0, 0.0])
    right, down, forward = np.array([0, 1.0, 0]), np.array([0, 0, -1.0]), np.array([-1.0, 0, 0])
    return centre, np.stack([right, down, forward]), np.array([0.0, 0.3, 0.5])


def _expected_pixel(centre, axes, point):
    local = axes @ (point - centre)
    return np.array([F * local[0] / local[2] + W / 2, F * local[1] / local[2] + H / 2])


def test_look_at_matches_hand_built_camera():
    centre, axes, point = _camera_on_x_axis()
    w2c = cam.look_at(centre, [0, 0, 0], up=[0, 0, 1])
    np.testing.assert_allclose(w2c[:3, :3], axes, atol=1e-12)
    uv = cam.project_points(K, w2c, point[None])[0]
    # the point is above the axis (z = 0.5 > 0) -> above the image centre (smaller v), and at
    # world +y, which is image right -> larger u
    assert uv[1] < H / 2 and uv[0] > W / 2
    np.testing.assert_allclose(uv, _expected_pixel(centre, axes, point), atol=1e-9)


def test_principal_point_is_image_centre_with_half_pixel_centres():
    # A point on the optical axis lands on (W/2, H/2): the border between pixels W/2-1 and W/2,
    # i.e. exactly the image centre when pixel u spans [u, u+1).
    w2c = cam.look_at([0, 0, 5.0], [0, 0, 0], up=[0, 1, 0])
    uv = cam.project_points(K, w2c, np.zeros((1, 3)))[0]
    np.testing.assert_allclose(uv, [W / 2, H / 2], atol=1e-12)


@pytest.mark.parametrize("scale", [1.0, -3.7, 1e-3])
def test_idr_projection_round_trip(scale):
    centre, axes, point = _camera_on_x_axis()
    w2c = cam.look_at(centre, [0, 0, 0], up=[0, 0, 1])
    K_skew = K.copy()
    K_skew[0, 1] = 0.7
    P = scale * cam.projection_matrix(K_skew, w2c)[:3]
    K2, w2c2 = cam.decompose_projection(P, "test")
    np.testing.assert_allclose(K2, K_skew, atol=1e-9)
    np.testing.assert_allclose(w2c2, w2c, atol=1e-12)


def test_idr_scale_mat_frames_agree():
    """A normalised-frame point and its capture-frame image (S @ x) land on the same pixel."""
    centre, _, point = _camera_on_x_axis()
    w2c = cam.look_at(centre, [0, 0, 0], up=[0, 0, 1])
    S = np.diag([2.5, 2.5, 2.5, 1.0])
    S[:3, 3] = [0.1, -0.2, 0.3]
    arrays = {"world_mat_0": cam.idr_world_mat(K, w2c, S), "scale_mat_0": S}
    K_n, w2c_n = cam.idr_camera(arrays, "world_mat_0", "scale_mat_0", "c.npz", normalize=True)
    K_w, w2c_w = cam.idr_camera(arrays, "world_mat_0", "scale_mat_0", "c.npz", normalize=False)
    np.testing.assert_allclose(w2c_n, w2c, atol=1e-9)
    world_point = S[:3, :3] @ point + S[:3, 3]
    np.testing.assert_allclose(
        cam.project_points(K_w, w2c_w, world_point[None]), cam.project_points(K_n, w2c_n, point[None]), atol=1e-9
    )


def test_llff_neisf_block_from_hand_written_axes():
    # NeISF/LLFF block columns: [down, right, back, position]. Camera at (0, 0, 3) looking at the
    # origin with world +y up: right = +x, down = -y, back = +z.
    block = np.array([[0, 1.0, 0, 0], [-1.0, 0, 0, 0], [0, 0, 1.0, 3.0]])
    w2c = cam.llff_to_world_to_camera(block)
    np.testing.assert_allclose(-w2c[:3, :3].T @ w2c[:3, 3], [0, 0, 3.0], atol=1e-12)
    np.testing.assert_allclose(w2c[2, :3], [0, 0, -1.0], atol=1e-12)  # optical axis towards origin
    uv = cam.project_points(K, w2c, np.array([[0, 0, 0.0], [0, 0.5, 0], [0.5, 0, 0]]))
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-12)
    assert uv[1, 1] < H / 2 and abs(uv[1, 0] - W / 2) < 1e-9  # world up -> image up
    np.testing.assert_allclose(uv[2], [W / 2 + F * 0.5 / 3, H / 2], atol=1e-9)  # world +x -> right
    np.testing.assert_allclose(cam.world_to_camera_to_llff(w2c), block, atol=1e-12)


def test_opengl_blender_c2w():
    # Blender camera at (0, -4, 1) looking along +y with z up: columns right=+x, up=+z, back=-y.
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    c2w[:3, 3] = [0, -4.0, 1.0]
    w2c = cam.opengl_c2w_to_world_to_camera(c2w)
    uv = cam.project_points(K, w2c, np.array([[0, 0, 1.0], [0, 0, 2.0]]))
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-12)
    np.testing.assert_allclose(uv[1], [W / 2, H / 2 - F * 1 / 4], atol=1e-9)  # higher point: image up
    np.testing.assert_allclose(cam.world_to_camera_to_opengl_c2w(w2c), c2w, atol=1e-12)


def test_inria_transposed_storage_and_fov_intrinsics():
    centre, axes, point = _camera_on_x_axis()
    w2c = cam.look_at(centre, [0, 0, 0], up=[0, 0, 1])
    R_stored, T = cam.world_to_camera_to_inria(w2c)
    np.testing.assert_allclose(R_stored, axes.T, atol=1e-12)  # 3DGS keeps R transposed
    # 3DGS world_view_transform = getWorld2View2(R, T).T: its transpose is our w2c
    world_view_transform = np.eye(4)
    world_view_transform[:3, :3] = R_stored.T
    world_view_transform[:3, 3] = T
    world_view_transform = world_view_transform.T
    np.testing.assert_allclose(world_view_transform.T, cam.inria_to_world_to_camera(R_stored, T), atol=1e-12)
    fov_x, fov_y = 2 * math.atan(W / (2 * F)), 2 * math.atan(H / (2 * F))
    K_fov = cam.intrinsics_from_fov(fov_x, fov_y, W, H)
    np.testing.assert_allclose(K_fov, K, atol=1e-9)
    uv = cam.project_points(K_fov, cam.inria_to_world_to_camera(R_stored, T), point[None])[0]
    np.testing.assert_allclose(uv, _expected_pixel(centre, axes, point), atol=1e-9)


def test_colmap_quaternion_convention():
    # COLMAP qvec (w, x, y, z): 90 deg about z maps x -> y.
    q = np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(cam.qvec_to_rotmat(q) @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        np.testing.assert_allclose(cam.rotmat_to_qvec(cam.qvec_to_rotmat(q)), q, atol=1e-12)


@pytest.mark.parametrize(
    "P, problem",
    [
        (np.full((3, 4), np.nan), "non-finite"),
        (np.hstack([np.ones((3, 3)), np.ones((3, 1))]), "singular"),
        (np.zeros((3, 4)), "singular"),
        (np.ones((2, 4)), "shape"),
    ],
)
def test_bad_projection_matrices(P, problem):
    with pytest.raises(PolarInputError, match=problem) as err:
        cam.decompose_projection(P, "cams.npz[world_mat_3]")
    assert "cams.npz[world_mat_3]" in str(err.value)


def test_idr_missing_key_names_it():
    with pytest.raises(PolarInputError, match="scale_mat_2") as err:
        cam.idr_camera({"world_mat_2": np.eye(4)}, "world_mat_2", "scale_mat_2", "x/cameras.npz")
    assert "x/cameras.npz" in str(err.value)


def test_similarity_transform_recovers_a_known_similarity_and_never_reflects():
    from scipy.spatial.transform import Rotation

    from polargs_plugin.data.cameras import similarity_transform

    rng = np.random.default_rng(7)
    points = rng.normal(size=(20, 3))
    R = Rotation.random(random_state=3).as_matrix()
    target = 0.37 * points @ R.T + np.array([4.0, -1.0, 2.5])
    scale, R_found, t = similarity_transform(points, target)
    assert abs(scale - 0.37) < 1e-12 and np.allclose(R_found, R, atol=1e-12) and np.allclose(t, [4.0, -1.0, 2.5])
    noisy = target + rng.normal(scale=1e-3, size=target.shape)
    scale, R_found, t = similarity_transform(points, noisy)
    assert abs(scale - 0.37) < 1e-3 and np.allclose(R_found, R, atol=1e-2)
    mirrored = points * np.array([1.0, 1.0, -1.0])  # no rotation maps these: the best one is not a reflection
    _, R_found, _ = similarity_transform(points, mirrored)
    assert np.isclose(np.linalg.det(R_found), 1.0)
    with pytest.raises(ValueError, match="one line"):
        similarity_transform(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), rng.normal(size=(5, 3)))
    with pytest.raises(ValueError, match="N >= 3"):
        similarity_transform(points[:2], target[:2])


def test_camera_centers_are_the_eyes_of_look_at():
    from polargs_plugin.data.cameras import camera_centers

    eyes = np.array([[3.0, 0.5, 1.0], [-2.0, 1.0, 0.3], [0.1, -2.5, 2.0]])
    w2c = np.stack([cam.look_at(eye, [0.0, 0.0, 0.2]) for eye in eyes])
    np.testing.assert_allclose(camera_centers(w2c), eyes, atol=1e-12)
