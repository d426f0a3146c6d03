"""Scene folder writer/reader: exact round trip, validation errors, atomic writing."""

from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest
import torch

import polargs_plugin.data.scene_format as scene_format
from polargs_plugin.data.scene_format import (
    CAMERAS_FILE,
    FORMAT_VERSION,
    is_scene_folder,
    read_gt_mesh,
    read_scene,
    read_scene_folder,
    write_scene,
)
from polargs_plugin.io import PolarInputError
import scene_cache


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("glossy_plane_sphere", num_views=8, width=48, height=48, seed=1)


@pytest.fixture(scope="module")
def written(scene, tmp_path_factory):
    return write_scene(scene, tmp_path_factory.mktemp("scene") / "glossy")


@pytest.fixture
def copy(written, tmp_path):
    """A private copy of the written folder that a test may damage."""
    return shutil.copytree(written, tmp_path / "copy")


def aolp_dolp(stokes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    s = stokes.double().mean(dim=1)
    return torch.remainder(0.5 * torch.atan2(s[2], s[1]), math.pi), torch.hypot(s[1], s[2]) / s[0].clamp(min=1e-9)


# --- round trip ----------------------------------------------------------------------------


def test_read_back_equals_written(scene, written):
    views = read_scene_folder(written)
    assert [v.name for v in views] == [v.name for v in scene.views]
    for got, want in zip(views, scene.views):
        assert got.K.dtype == torch.float64 and got.world_to_camera.dtype == torch.float64
        assert torch.allclose(got.K, want.K, atol=1e-6, rtol=0)
        assert torch.allclose(got.world_to_camera, want.world_to_camera, atol=1e-6, rtol=0)
        assert torch.equal(got.mask, want.mask)
        assert torch.equal(got.normal_gt, want.normal_gt) and torch.equal(got.depth_gt, want.depth_gt)
        assert torch.allclose(got.stokes, want.stokes, atol=1e-6)
        aolp_got, dolp_got = aolp_dolp(got.stokes)
        aolp_want, dolp_want = aolp_dolp(want.stokes)
        sel = dolp_want > 0.05
        assert sel.any()
        diff = torch.remainder(aolp_got - aolp_want, math.pi)
        assert torch.minimum(diff, math.pi - diff)[sel].max() < 1e-4
        assert got.source == str(written)


def test_read_scene_round_trips_ground_truth(scene, written):
    back = read_scene(written)
    assert back.name == scene.name and back.meta["seed"] == 1 and back.meta["azimuth_model"] == "perspective"
    for name in ("angle_images", "diffuse_gt", "specular_gt", "highlight_masks", "overexposed_masks"):
        for got, want in zip(getattr(back, name), getattr(scene, name)):
            assert got.shape == want.shape and got.dtype == want.dtype
            assert torch.allclose(got.float(), want.float(), atol=1e-7), name
    assert np.allclose(back.mesh_vertices, scene.mesh_vertices, atol=1e-6)
    assert np.array_equal(back.mesh_triangles, scene.mesh_triangles)
    assert np.array_equal(back.object_triangles, scene.object_triangles)
    full = read_gt_mesh(written, object_only=False)
    assert len(full.triangles) == len(scene.mesh_triangles)
    obj = read_gt_mesh(written)  # gt_mesh.ply: the evaluation ground truth, object only
    assert len(obj.triangles) == int(scene.object_triangles.sum()) == len(scene.object_mesh()[1])
    if scene.name == "glossy_plane_sphere":
        assert len(obj.triangles) < len(full.triangles)  # no floor
        assert np.linalg.norm(np.asarray(obj.vertices) - [0, 0, 0.5], axis=1).max() < 0.5 + 1e-6


def test_png_bit_depth_and_channel_order(written):
    header = json.loads((written / CAMERAS_FILE).read_text())
    assert header["format_version"] == FORMAT_VERSION and header["bit_depth"] == 8
    raw = cv2.imread(str(written / "polar" / "view_000_000.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw.shape == (48, 48, 3)
    view = read_scene_folder(written)[0]
    # The sphere is red: in RGB order channel 0 dominates on the object; cv2 stores it last (BGR).
    red_object = view.mask[0] & (view.image[0] > 2 * view.image[2])
    assert red_object.sum() > 20
    assert np.all(raw[..., 2][red_object.numpy()] >= raw[..., 0][red_object.numpy()])


def test_sixteen_bit_round_trip(tmp_path, synthetic_scene):
    scene = synthetic_scene("bumpy_mixed", num_views=2, width=24, height=20, quantize_bits=16, noise_std=0.0)
    folder = write_scene(scene, tmp_path / "s16")
    raw = cv2.imread(str(folder / "polar" / "view_001_135.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (20, 24, 3)
    for got, want in zip(read_scene_folder(folder), scene.views):
        assert torch.allclose(got.stokes, want.stokes, atol=1e-6)
    assert is_scene_folder(folder) and not is_scene_folder(tmp_path)


# --- validation ---------------------------------------------------------------------------------


def _edit_cameras(folder, edit):
    path = folder / CAMERAS_FILE
    header = json.loads(path.read_text())
    edit(header)
    path.write_text(json.dumps(header))
    return path


def _expect(folder, path, *words):
    with pytest.raises(PolarInputError) as info:
        read_scene_folder(folder)
    assert info.value.path == str(path)
    for word in words:
        assert word in info.value.problem
    return info.value


def test_missing_angle_image(copy):
    path = copy / "polar" / "view_003_090.png"
    path.unlink()
    _expect(copy, path, "missing", "90 deg")


def test_size_mismatch_between_angles(copy):
    path = copy / "polar" / "view_002_045.png"
    cv2.imwrite(str(path), np.full((40, 48, 3), 9, np.uint8))
    _expect(copy, path, "differs", "view_002_000.png")


def test_dtype_mismatch_between_angles(copy):
    path = copy / "polar" / "view_002_135.png"
    cv2.imwrite(str(path), np.full((48, 48, 3), 900, np.uint16))
    _expect(copy, path, "uint16", "differs")


def test_size_mismatch_with_cameras(copy):
    for angle in (0, 45, 90, 135):
        cv2.imwrite(str(copy / "polar" / f"view_000_{angle:03d}.png"), np.full((30, 30, 3), 9, np.uint8))
    _expect(copy, copy / "polar" / "view_000_000.png", "30x30", "48x48")


def test_all_dark_image(copy):
    path = copy / "polar" / "view_005_000.png"
    cv2.imwrite(str(path), np.zeros((48, 48, 3), np.uint8))
    _expect(copy, path, "dark")


@pytest.mark.parametrize("sub,field,bad", [("depth", "depth_gt", np.nan), ("normals", "normal_gt", np.inf)])
def test_non_finite_ground_truth(copy, sub, field, bad):
    """GT maps stay in their files until read (training never reads them): their values are
    checked then, the error naming the file."""
    path = copy / sub / "view_004.npy"
    array = np.load(path)
    array.flat[17] = bad
    np.save(path, array)
    views = read_scene_folder(copy)
    assert views[4].nbytes == views[4].stored("stokes").nbytes + views[4].stored("mask").nbytes
    with pytest.raises(PolarInputError) as info:
        getattr(views[4], field)
    assert info.value.path == str(path) and "NaN or infinite" in info.value.problem


def test_ground_truth_shape_mismatch(copy):
    path = copy / "depth" / "view_001.npy"
    np.save(path, np.ones((48, 47), np.float32))
    _expect(copy, path, "shape")


def test_unreadable_angle_image(copy):
    path = copy / "polar" / "view_001_045.png"
    path.write_bytes(b"not a png")
    _expect(copy, path, "unreadable")


@pytest.mark.parametrize(
    "key,value,words",
    [
        ("K", [[50.0, 0, 24], [0, float("nan"), 24], [0, 0, 1]], ("non-finite",)),
        ("K", [[0.0, 0, 24], [0, 0.0, 24], [0, 0, 1]], ("singular",)),
        ("K", [[50.0, 0], [0, 50.0]], ("shape",)),
        ("world_to_camera", [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 3], [0, 0, 0, 1]], ("rotation",)),
        ("world_to_camera", [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("inf")], [0, 0, 0, 1]], ("non-finite",)),
        ("world_to_camera", [[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]], ("proper rotation",)),
    ],
)
def test_bad_camera_matrices(copy, key, value, words):
    def edit(header):
        header["views"][2][key] = value

    path = _edit_cameras(copy, edit)
    _expect(copy, path, "view_002", key, *words)


@pytest.mark.parametrize(
    "edit,words",
    [
        (lambda h: h.update(format_version=FORMAT_VERSION + 1), ("format_version",)),
        (lambda h: h.update(format="something-else"), ("not a polargs-scene",)),
        (lambda h: h.update(width=0), ("width",)),
        (lambda h: h.update(views=[]), ("no views",)),
        (lambda h: h["views"][1].update(name=h["views"][0]["name"]), ("duplicate",)),
        (lambda h: h["views"][1].update(name="../escape"), ("bad view name",)),
    ],
)
def test_bad_cameras_header(copy, edit, words):
    path = _edit_cameras(copy, edit)
    _expect(copy, path, *words)


def test_missing_cameras_and_folder(copy, tmp_path):
    (copy / CAMERAS_FILE).unlink()
    _expect(copy, copy / CAMERAS_FILE, "missing")
    _expect(tmp_path / "nowhere", tmp_path / "nowhere", "not a folder")
    (copy / CAMERAS_FILE).write_text("{broken")
    _expect(copy, copy / CAMERAS_FILE, "JSON")


def test_missing_mesh(copy):
    (copy / "mesh.ply").unlink()
    with pytest.raises(PolarInputError, match="mesh"):
        read_gt_mesh(copy, object_only=False)
    read_gt_mesh(copy)  # gt_mesh.ply is still there
    (copy / "gt_mesh.ply").unlink()
    with pytest.raises(PolarInputError, match="mesh.ply"):
        read_gt_mesh(copy)


# --- atomic writing ----------------------------------------------------------------------------


def test_failed_write_leaves_no_partial_files_and_no_cameras(scene, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = cv2.imwrite

    def flaky(path, image):
        calls["n"] += 1
        if calls["n"] == 6:
            raise RuntimeError("disk full")
        return real(path, image)

    monkeypatch.setattr(scene_format.cv2, "imwrite", flaky)
    folder = tmp_path / "partial"
    with pytest.raises(RuntimeError, match="disk full"):
        write_scene(scene, folder)
    leftovers = [p for p in folder.rglob("*") if p.is_file() and p.name.startswith(".")]
    assert leftovers == []
    assert not (folder / CAMERAS_FILE).exists() and not is_scene_folder(folder)
    with pytest.raises(PolarInputError, match="missing"):
        read_scene_folder(folder)
