"""A known 3D point projects to the expected pixel through each reader's camera.

Each dataset folder is written here by hand in that dataset's own convention (not with our
writers), for one camera at (0, 0, 4) looking at the origin with world +y up in the image:
OpenCV axes right = +x, down = -y, forward = -z. The point (0.5, 0.25, 0) is then at camera
coordinates (0.5, -0.25, 4), i.e. pixel (cx + f/8, cy - f/16) with pixel centres at +0.5.
"""

import math

import cv2
import numpy as np
import OpenEXR

from polargs_plugin.data.registry import load_views

H, W, F = 24, 32, 40.0
POINT = np.array([0.5, 0.25, 0.0])
EXPECTED = np.array([W / 2 + F * 0.5 / 4, H / 2 - F * 0.25 / 4])
R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
T = np.array([0.0, 0.0, 4.0])


def _pixel(view) -> np.ndarray:
    K, w2c = view.K.numpy(), view.world_to_camera.numpy()
    x = K @ (w2c[:3, :3] @ POINT + w2c[:3, 3])
    return x[:2] / x[2]


def _stokes_planes():
    s0 = np.full((H, W, 3), 0.6, np.float32)
    return s0, 0.2 * s0, -0.1 * s0


def _idr_world_mat() -> np.ndarray:
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    P = np.eye(4)
    P[:3, :4] = K @ np.hstack([R, T[:, None]])
    return P


def test_nersp_idr_camera(tmp_path):
    for name, plane in zip(("s0", "s1", "s2"), _stokes_planes()):
        (tmp_path / name).mkdir()
        np.save(tmp_path / name / "0000.npy", plane)
    np.savez(tmp_path / "cameras.npz", world_mat_0=_idr_world_mat(), scale_mat_0=np.eye(4))
    (view,) = load_views(tmp_path)
    np.testing.assert_allclose(_pixel(view), EXPECTED, atol=1e-9)
    assert view.mask is None


def test_pandora_idr_camera_and_offset_decoding(tmp_path):
    (tmp_path / "images_stokes").mkdir()
    s0, s1, s2 = _stokes_planes()
    for suffix, image in (("s0", s0), ("s0p1", s0 + s1), ("s0p2", s0 + s2)):
        cv2.imwrite(str(tmp_path / "images_stokes" / f"01_{suffix}.hdr"), image[..., ::-1])
    np.savez(tmp_path / "cameras.npz", world_mat_01=_idr_world_mat(), scale_mat_01=np.eye(4))
    (view,) = load_views(tmp_path)
    np.testing.assert_allclose(_pixel(view), EXPECTED, atol=1e-9)
    stokes = view.stokes.mean(dim=(-1, -2)).numpy()  # (3, C)
    np.testing.assert_allclose(stokes, [[0.6] * 3, [0.12] * 3, [-0.06] * 3], atol=0.6 * 2**-7 * 2)


def test_neisf_llff_camera_looks_at_centre(tmp_path):
    s0, s1, s2 = _stokes_planes()
    for name, plane in zip(("s0", "s1", "s2"), (s0, s1, s2)):
        (tmp_path / f"images_{name}").mkdir()
        channels = {c: np.ascontiguousarray(plane[..., i]) for i, c in enumerate("RGB")}
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
            f.write(str(tmp_path / f"images_{name}" / "img_001.exr"))
    # LLFF 3x5: columns down, right, back (world vectors), position, then (H, W, f).
    block = np.array([[0, 1.0, 0, 0, H], [-1.0, 0, 0, 0, W], [0, 0, 1.0, 4.0, F]])
    np.save(tmp_path / "poses_bounds.npy", np.concatenate([block.reshape(-1), [0.0, 6.0]])[None])
    (view,) = load_views(tmp_path)
    np.testing.assert_allclose(_pixel(view), EXPECTED, atol=1e-9)
    centre = view.camera_center.numpy()
    forward = view.world_to_camera.numpy()[2, :3]
    np.testing.assert_allclose(forward, -centre / np.linalg.norm(centre), atol=1e-12)


def test_polar_folder_colmap_text(tmp_path):
    s0, s1, s2 = _stokes_planes()
    angles = {"0": (s0 + s1) / 2, "45": (s0 + s2) / 2, "90": (s0 - s1) / 2, "135": (s0 - s2) / 2}
    for angle, image in angles.items():
        cv2.imwrite(str(tmp_path / f"cap_{angle}.png"), np.rint(image[..., ::-1] * 65535).astype(np.uint16))
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"# comment\n7 PINHOLE {W} {H} {F} {F} {W / 2} {H / 2}\n")
    # R = diag(1, -1, -1) is a half turn about x: qvec (w, x, y, z) = (0, 1, 0, 0)
    (model / "images.txt").write_text("# comment\n3 0 1 0 0 0 0 4 7 cap.png\n\n")
    (view,) = load_views(tmp_path)
    assert view.name == "cap"
    np.testing.assert_allclose(_pixel(view), EXPECTED, atol=1e-9)
    aolp = 0.5 * math.atan2(-0.1, 0.2) % math.pi
    measured = 0.5 * np.arctan2(view.stokes[2].mean().item(), view.stokes[1].mean().item()) % math.pi
    assert abs(measured - aolp) < 1e-3
