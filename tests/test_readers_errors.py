"""Bad input to the readers raises PolarInputError naming the file and the problem."""

import math

import cv2
import numpy as np
import pytest
import torch

from polargs_plugin.data import cameras as cam
from polargs_plugin.data.colmap import read_colmap_model
from polargs_plugin.data.imageio_utils import read_exr, write_exr
from polargs_plugin.data.neisf import read_neisf, write_neisf
from polargs_plugin.data.nersp import read_nersp, write_nersp
from polargs_plugin.data.pandora import read_pandora, write_pandora
from polargs_plugin.data.polar_folder import read_polar_folder, write_polar_folder
from polargs_plugin.data.registry import load_views
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import View

H, W = 8, 12


def _views(count=2) -> list[View]:
    """Cameras on a ring looking at the origin; random physically valid Stokes (DoLP <= 1)."""
    rng = np.random.default_rng(0)
    views = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        w2c = cam.look_at([3 * math.cos(angle), 3 * math.sin(angle), 1.0], [0, 0, 0])
        s0 = rng.uniform(0.2, 0.9, (3, H, W))
        rho, phi = rng.uniform(0, 1, (3, H, W)), rng.uniform(0, math.pi, (3, H, W))
        stokes = np.stack([s0, s0 * rho * np.cos(2 * phi), s0 * rho * np.sin(2 * phi)])
        K = torch.tensor([[10.0, 0, W / 2], [0, 10.0, H / 2], [0, 0, 1]], dtype=torch.float64)
        views.append(View(f"v{i}", K, torch.from_numpy(w2c), torch.from_numpy(stokes).float()))
    return views


def _raises(path_part: str, problem: str, fn, *args, **kwargs):
    with pytest.raises(PolarInputError, match=problem) as err:
        fn(*args, **kwargs)
    assert path_part in err.value.path, err.value.path
    return err.value


@pytest.fixture
def polar(tmp_path):
    write_polar_folder(_views(), tmp_path)
    return tmp_path


def test_missing_angle_image(polar):
    (polar / "images" / "v1_90.png").unlink()
    _raises("v1_90", "missing the 90-degree image", read_polar_folder, polar)


def test_missing_angle_image_in_per_angle_folders(tmp_path):
    write_polar_folder(_views(), tmp_path, per_angle_folders=True)
    (tmp_path / "images" / "45" / "v0.png").unlink()
    _raises("45/v0", "missing the 45-degree image", read_polar_folder, tmp_path)


def test_size_mismatch_between_angles(polar):
    cv2.imwrite(str(polar / "images" / "v0_45.png"), np.full((H + 2, W, 3), 1000, np.uint16))
    _raises("v0_45.png", "differs from v0_0.png", read_polar_folder, polar)


def test_dtype_mismatch_between_angles(polar):
    cv2.imwrite(str(polar / "images" / "v0_135.png"), np.full((H, W, 3), 10, np.uint8))
    _raises("v0_135.png", "uint8 image differs", read_polar_folder, polar)


def test_all_dark_angle_images(polar):
    for angle in (0, 45, 90, 135):
        cv2.imwrite(str(polar / "images" / f"v1_{angle}.png"), np.zeros((H, W, 3), np.uint16))
    _raises("v1_0.png", "all-dark", read_polar_folder, polar)


def test_unreadable_image(polar):
    (polar / "images" / "v0_0.png").write_bytes(b"not a png")
    _raises("v0_0.png", "cannot be decoded", read_polar_folder, polar)


def test_unknown_or_missing_mosaic_pattern(tmp_path):
    views = [View(v.name, v.K, v.world_to_camera, v.stokes[:, :1]) for v in _views()]
    write_polar_folder(views, tmp_path, mode="raw", pattern="mono")
    _raises("raw", "unknown mosaic pattern 'bayer'", read_polar_folder, tmp_path, pattern="bayer")
    _raises("raw", "unknown mosaic pattern None", read_polar_folder, tmp_path)


def test_all_dark_raw_mosaic(tmp_path):
    views = [View(v.name, v.K, v.world_to_camera, v.stokes[:, :1]) for v in _views()]
    write_polar_folder(views, tmp_path, mode="raw", pattern="mono")
    cv2.imwrite(str(tmp_path / "raw" / "v0.png"), np.zeros((H, W), np.uint16))
    _raises("v0.png", "all-dark", read_polar_folder, tmp_path, pattern="mono")


def test_colmap_distortion_and_missing_model(polar):
    cameras = polar / "sparse" / "0" / "cameras.txt"
    lines = cameras.read_text().splitlines()
    lines[1] = lines[1].replace("PINHOLE", "OPENCV") + " 0.1 0 0 0"  # k1 = 0.1
    cameras.write_text("\n".join(lines) + "\n")
    _raises("camera 1", "non-zero distortion", read_colmap_model, polar / "sparse" / "0")
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (polar / "sparse" / "0" / name).unlink()
    _raises(str(polar), "no COLMAP model", read_polar_folder, polar)


def test_nersp_nan_stokes(tmp_path):
    write_nersp(_views(), tmp_path)
    array = np.load(tmp_path / "s1" / "0001.npy")
    array[2, 3, 1] = np.nan
    np.save(tmp_path / "s1" / "0001.npy", array)
    _raises("s1/0001.npy", "non-finite", read_nersp, tmp_path)


def test_nersp_all_dark(tmp_path):
    write_nersp(_views(), tmp_path)
    np.save(tmp_path / "s0" / "0000.npy", np.zeros((H, W, 3), np.float32))
    _raises("s0/0000.npy", "all-dark", read_nersp, tmp_path)


def test_nersp_stokes_size_mismatch(tmp_path):
    write_nersp(_views(), tmp_path)
    np.save(tmp_path / "s2" / "0000.npy", np.zeros((H, W + 1, 3), np.float32))
    _raises("s2/0000.npy", "differs from", read_nersp, tmp_path)


def _edit_npz(path, **changes):
    arrays = dict(np.load(path))
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    np.savez(path, **arrays)


def test_cameras_npz_missing_key(tmp_path):
    write_nersp(_views(), tmp_path)
    _edit_npz(tmp_path / "cameras.npz", world_mat_1=None)
    _raises("cameras.npz", "missing key 'world_mat_1'", read_nersp, tmp_path)


@pytest.mark.parametrize(
    "matrix, problem", [(np.full((4, 4), np.inf), "non-finite"), (np.zeros((4, 4)), "singular")]
)
def test_cameras_npz_bad_matrix(tmp_path, matrix, problem):
    write_pandora(_views(), tmp_path)
    _edit_npz(tmp_path / "cameras.npz", world_mat_02=matrix)
    _raises("cameras.npz[world_mat_02]", problem, read_pandora, tmp_path)


def test_neisf_inf_exr_and_missing_image(tmp_path):
    write_neisf(_views(), tmp_path)
    path = tmp_path / "images_s2" / "img_002.exr"
    array = read_exr(path)
    array[0, 0, 0] = np.inf
    write_exr(path, array)
    _raises("images_s2/img_002.exr", "non-finite", read_neisf, tmp_path)
    (tmp_path / "images_s0" / "img_002.exr").unlink()
    _raises("images_s0", "1 EXR files for 2 poses", read_neisf, tmp_path)


def test_neisf_bad_pose(tmp_path):
    write_neisf(_views(), tmp_path)
    poses = np.load(tmp_path / "poses_bounds.npy")
    poses[1, :3] = 0  # first row of the rotation block: not a rotation any more
    np.save(tmp_path / "poses_bounds.npy", poses)
    _raises("poses_bounds.npy[row 1]", "rigid", read_neisf, tmp_path)


def test_corrupt_exr(tmp_path):
    write_neisf(_views(), tmp_path)
    (tmp_path / "images_s1" / "img_001.exr").write_bytes(b"garbage")
    _raises("images_s1/img_001.exr", "OpenEXR", read_neisf, tmp_path)


def test_pandora_hdr_size_mismatch(tmp_path):
    write_pandora(_views(), tmp_path)
    cv2.imwrite(str(tmp_path / "images_stokes" / "01_s0p2.hdr"), np.ones((H, W + 4, 3), np.float32))
    _raises("01_s0p2.hdr", "differs from", read_pandora, tmp_path)


def test_unknown_folder_lists_what_was_looked_for(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    err = _raises(str(tmp_path), "no known dataset format", load_views, tmp_path)
    for marker in ("cameras.json", "poses_bounds.npy", "images_stokes", "s0/*.npy", "raw/"):
        assert marker in err.problem
