"""SfM on a polar folder without a COLMAP model (the optional ``sfm`` extra, pycolmap).

The scene is a textured room corner (floor and two walls) ray-cast here in numpy; the recovered
cameras must match the true ones up to a similarity (COLMAP fixes neither scale nor frame).
"""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from polargs_plugin.data import cameras as cam
from polargs_plugin.data.colmap import find_colmap_model
from polargs_plugin.data.polar_folder import read_polar_folder

pycolmap = pytest.importorskip("pycolmap")

H, W, F = 240, 320, 260.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])


def _texture(rng, size=48):
    coarse = rng.uniform(0, 1, (size, size))
    return cv2.resize(coarse, (8 * size, 8 * size), interpolation=cv2.INTER_CUBIC)


def _render(w2c, textures):
    """Brightness of the nearest of the planes z=0, x=-1, y=-1 (each textured over [-1, 2]^2)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ w2c[:3, :3]  # world directions
    origin = -w2c[:3, :3].T @ w2c[:3, 3]
    best, image = np.full((H, W), np.inf), np.zeros((H, W))
    for axis, offset, texture in zip((2, 0, 1), (0.0, -1.0, -1.0), textures):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offset - origin[axis]) / rays[..., axis]
        hit = origin + t[..., None] * rays
        others = [hit[..., a] for a in range(3) if a != axis]
        inside = (t > 0) & (t < best) & np.all([(o > -1) & (o < 2) for o in others], axis=0)
        coords = [(o + 1) / 3 * (texture.shape[0] - 1) for o in others]
        value = map_coordinates(texture, coords, order=1, mode="nearest")
        image = np.where(inside, 0.15 + 0.7 * value, image)
        best = np.where(inside, t, best)
    return image


@pytest.mark.slow
def test_sfm_recovers_cameras_up_to_similarity(tmp_path):
    rng = np.random.default_rng(3)
    textures = [_texture(rng) for _ in range(3)]
    true = {}
    for i in range(8):
        angle = math.radians(20 + 7 * i)
        eye = np.array([3.2 * math.cos(angle), 3.2 * math.sin(angle), 1.6])
        w2c = cam.look_at(eye, [0.2, 0.2, 0.4], up=[0, 0, 1])
        true[f"view{i}"] = w2c
        s0 = _render(w2c, textures)
        rho, phi = 0.2, 0.5
        for beta in (0, 45, 90, 135):
            image = s0 / 2 * (1 + rho * math.cos(2 * math.radians(beta) - 2 * phi))
            cv2.imwrite(str(tmp_path / f"view{i}_{beta}.png"), np.rint(image * 255).astype(np.uint8))
    assert find_colmap_model(tmp_path) is None

    views = read_polar_folder(tmp_path, sfm=True)

    assert find_colmap_model(tmp_path) == tmp_path / "sparse" / "0"
    assert len(views) >= 6
    _assert_cameras_match(views, true, max_offset=0.05 * 3.2, max_degrees=1.5)
    for v in views:
        assert abs(v.K[0, 0].item() / F - 1) < 0.03


def _assert_cameras_match(views, true: dict[str, np.ndarray], max_offset: float, max_degrees: float) -> None:
    """The views' cameras are the true world_to_camera matrices up to a similarity (COLMAP fixes
    neither scale nor frame): centres within ``max_offset`` after the least-squares similarity,
    orientations within ``max_degrees``."""
    centres = np.stack([v.camera_center.numpy() for v in views])
    true_centres = cam.camera_centers(np.stack([true[v.name] for v in views]))
    scale, rotation, shift = cam.similarity_transform(centres, true_centres)
    aligned = scale * centres @ rotation.T + shift
    assert np.abs(aligned - true_centres).max() < max_offset
    for v in views:  # camera orientation: R_sfm = R_true @ rotation (world frames differ by it)
        residual = true[v.name][:3, :3] @ rotation @ v.world_to_camera.numpy()[:3, :3].T
        assert math.degrees(math.acos(np.clip((np.trace(residual) - 1) / 2, -1, 1))) < max_degrees


@pytest.mark.slow
def test_sfm_registers_generated_raw_frames_of_a_speckled_floor(tmp_path):
    """Raw colour-polarization frames from the generator (glossy_plane_sphere on a speckle floor)
    go through pattern detection, demosaicking and SfM to the generator's cameras."""
    from polargs_plugin.cli import main
    from polargs_plugin.data.colmap import read_colmap_model

    folder = tmp_path / "raw"
    assert main(["generate", "--scene", "glossy_plane_sphere", "--out", str(folder), "--views", "12", "--size", "640x512",
                 "--mosaic", "rgb", "--bits", "16", "--floor-texture", "speckle"]) == 0
    true = {Path(name).stem: camera.world_to_camera for name, camera in read_colmap_model(folder / "sparse" / "0").items()}
    (folder / "sparse" / "0").rename(tmp_path / "true_model")  # leave the cameras to SfM
    info = {}
    views = read_polar_folder(folder, pattern="auto", sfm=True, info=info)
    assert info["pattern"] == "rgb" and info["sfm"]
    assert len(views) == 12
    _assert_cameras_match(views, true, max_offset=0.02 * 3.0, max_degrees=0.5)


def test_sfm_failures_say_how_many_views_it_needs(tmp_path):
    from polargs_plugin.io import PolarInputError

    rng = np.random.default_rng(0)
    for i in range(3):  # three unrelated noise pictures: nothing to match
        s0 = cv2.resize(rng.uniform(0.1, 0.9, (12, 16)), (W // 4, H // 4), interpolation=cv2.INTER_NEAREST)
        for beta in (0, 45, 90, 135):
            cv2.imwrite(str(tmp_path / f"v{i}_{beta}.png"), np.rint(s0 / 2 * 255).astype(np.uint8))
    with pytest.raises(PolarInputError, match=r"SfM registered [0-2] of 3 images; it needs at least 3 overlapping views"):
        read_polar_folder(tmp_path, sfm=True)
    assert find_colmap_model(tmp_path) is None  # no half-written model
    for beta in (0, 45, 90, 135):
        (tmp_path / f"v2_{beta}.png").unlink()
    with pytest.raises(PolarInputError, match=r"SfM got 2 image\(s\) \(v0, v1\); it needs at least 3 overlapping views"):
        read_polar_folder(tmp_path, sfm=True)
