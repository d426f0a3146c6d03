"""Write a synthetic scene in every dataset format, read it back, compare with the original views.

Tolerances are each format's precision: float32 ``.npy``/EXR exact, 16-bit PNG exact for the
8-bit-quantised synthetic images (65535 = 257 x 255), Radiance RGBE within its 8-bit mantissa
(error <= max channel x 2^-7 per stored image), cameras to 1e-6.
"""

import math

import numpy as np
import pytest
import torch

from polargs_plugin.compact import HALF_RELATIVE_ERROR
from polargs_plugin.data import cameras as cam
from polargs_plugin.data.colmap import read_colmap_model, write_colmap_scene
from polargs_plugin.data.neisf import read_neisf, write_neisf
from polargs_plugin.data.nersp import read_nersp, write_nersp
from polargs_plugin.data.pandora import read_pandora, write_pandora
from polargs_plugin.data.polar_folder import write_polar_folder
from polargs_plugin.data.registry import detect_format, load_views
from polargs_plugin.data.scene_format import write_scene
from polargs_plugin.types import View
import scene_cache

RGBE_RELATIVE = 2.0**-7
MIN_POLARIZED = 0.02  # |(s1, s2)| above which AoLP is compared ("DoLP meaningful")


def _quantised_view(name, stokes_fn, eye, size=(24, 32)) -> View:
    """A view whose four angle images are 8-bit codes with I0 + I90 = I45 + I135, so that its
    Malus images are those codes again and 16-bit PNG stores them exactly."""
    height, width = size
    s0, s1, s2 = stokes_fn(height, width)
    i0, i45, i90 = (torch.round(((s0 + s) / 2).clamp(0, 1) * 255) for s in (s1, s2, -s1))
    i135 = i0 + i90 - i45
    assert i135.min() >= 0 and i135.max() <= 255
    i0, i45, i90, i135 = (i / 255 for i in (i0, i45, i90, i135))
    stokes = torch.stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135]).float()
    K = torch.tensor([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.from_numpy(cam.look_at(eye, [0, 0, 0.2], up=[0, 0, 1]))
    mask = torch.zeros(1, height, width, dtype=torch.bool)
    mask[:, 4:-4, 6:-6] = True
    return View(name=name, K=K, world_to_camera=w2c, stokes=stokes, mask=mask)


def _red(height, width):
    """Pure red, 40% linearly polarized at 30 degrees: only channel 0 is non-zero."""
    s0 = torch.zeros(3, height, width, dtype=torch.float64)
    s0[0] = 0.8
    phi, rho = math.radians(30), 0.4
    return s0, s0 * rho * math.cos(2 * phi), s0 * rho * math.sin(2 * phi)


@pytest.fixture(scope="module")
def scene():
    return scene_cache.scene("glossy_plane_sphere", num_views=3, width=32, height=24, seed=0)


@pytest.fixture(scope="module")
def views(scene) -> list[View]:
    return [*scene.views, _quantised_view("red", _red, eye=[2.0, -2.5, 1.5])]


def _aolp(stokes):
    return 0.5 * torch.atan2(stokes[2].double(), stokes[1].double())


def _compare(original: list[View], read: list[View], stokes_atol, aolp_atol, check_red=True):
    assert len(read) == len(original)
    for a, b in zip(original, read):
        assert b.K.dtype == torch.float64 and b.world_to_camera.dtype == torch.float64
        torch.testing.assert_close(b.K, a.K, atol=1e-6, rtol=0)
        torch.testing.assert_close(b.world_to_camera, a.world_to_camera, atol=1e-6, rtol=0)
        assert b.stokes.dtype == torch.float32 and b.stokes.shape == a.stokes.shape
        error = (b.stokes.double() - a.stokes.double()).abs()
        assert bool((error <= stokes_atol(a.stokes.double()) + 1e-7).all()), float(error.max())
        polarized = torch.hypot(a.stokes[1].double(), a.stokes[2].double())
        meaningful = polarized > MIN_POLARIZED
        assert meaningful.sum() > 10
        diff = torch.remainder(_aolp(b.stokes) - _aolp(a.stokes) + math.pi / 2, math.pi) - math.pi / 2
        tolerance = aolp_atol(a.stokes.double())
        assert bool((diff.abs() <= tolerance)[meaningful].all()), float(diff.abs()[meaningful].max())
        assert b.mask is not None and torch.equal(b.mask, a.mask)
    if not check_red:
        return
    red_read = read[-1].stokes[0]
    assert float(red_read[0].min()) > 0.7 and float(red_read[1:].abs().max()) < 1e-3  # red stays in channel 0


def _exact(stokes):
    return torch.zeros_like(stokes)


def _aolp_exact(stokes):
    return torch.full(stokes.shape[1:], 1e-4, dtype=torch.float64)


def _half(stokes):
    """Readers keep float Stokes as float16: each value within its relative rounding 2^-11."""
    return stokes.abs() * HALF_RELATIVE_ERROR


def _aolp_bound(error, stokes):
    # d(0.5 atan2(s2, s1)) <= 0.5 |d(s1, s2)| / |(s1, s2)|
    polarized = torch.hypot(stokes[1], stokes[2]).clamp_min(1e-12)
    return 0.5 * torch.hypot(error[1], error[2]) / polarized * 1.5 + 1e-6


def _half_aolp(stokes):
    return _aolp_bound(_half(stokes), stokes)


@pytest.mark.parametrize("variant", ["nersp", "polgs"])
def test_nersp_round_trip(views, tmp_path, variant):
    write_nersp(views, tmp_path, variant=variant)
    assert detect_format(tmp_path) == "nersp"
    _compare(views, read_nersp(tmp_path), _half, _half_aolp)


def test_nersp_azimuth_map_holds_the_aolp(views, tmp_path):
    import cv2

    write_nersp(views[-1:], tmp_path)
    azimuth = cv2.imread(str(tmp_path / "input_azimuth_maps" / "0000.png"), cv2.IMREAD_UNCHANGED)
    assert azimuth.dtype == np.uint16 and azimuth.shape[2] == 4
    mean = views[-1].stokes.double().mean(dim=1)  # channel-mean s1, s2 (NeRSP's definition)
    expected = torch.remainder(0.5 * torch.atan2(mean[2], mean[1]), math.pi).numpy()
    np.testing.assert_allclose(azimuth[..., 0] * math.pi / 65535, expected, atol=math.pi / 65535)
    np.testing.assert_array_equal(azimuth[..., 3] > 0, views[-1].mask[0].numpy())


def test_nersp_scale_mat_round_trip(views, tmp_path):
    S = np.diag([3.0, 3.0, 3.0, 1.0])
    S[:3, 3] = [0.5, -1.0, 2.0]
    write_nersp(views, tmp_path, scale_mat=S)
    _compare(views, read_nersp(tmp_path, normalize=True), _half, _half_aolp)


def test_neisf_round_trip(views, tmp_path):
    write_neisf(views, tmp_path)
    assert detect_format(tmp_path) == "neisf"
    _compare(views, read_neisf(tmp_path), _half, _half_aolp)


def _rgbe_error(stokes):
    """Per-pixel bound of the decoded Stokes error: each stored image errs by <= its max channel x 2^-7,
    then the float16 the reader keeps."""
    s0, s1, s2 = stokes
    e0 = s0.amax(dim=0, keepdim=True) * RGBE_RELATIVE
    e1 = (s0 + s1).amax(dim=0, keepdim=True) * RGBE_RELATIVE + e0
    e2 = (s0 + s2).amax(dim=0, keepdim=True) * RGBE_RELATIVE + e0
    rgbe = torch.stack([e0, e1, e2]).expand_as(stokes)
    return rgbe + (stokes.abs() + rgbe) * HALF_RELATIVE_ERROR


def _rgbe_aolp(stokes):
    return _aolp_bound(_rgbe_error(stokes), stokes)


def test_pandora_round_trip(views, tmp_path):
    write_pandora(views, tmp_path)
    assert detect_format(tmp_path) == "pandora"
    read = read_pandora(tmp_path)
    assert [v.name for v in read] == ["01", "02", "03", "04"]
    _compare(views, read, _rgbe_error, _rgbe_aolp)


@pytest.mark.parametrize("per_angle_folders", [False, True])
def test_polar_folder_round_trip(scene, views, tmp_path, per_angle_folders):
    angle_images = [*scene.angle_images, None]  # the red view gets its (exact) Malus images
    write_polar_folder(views, tmp_path, per_angle_folders=per_angle_folders, angle_images=angle_images)
    assert detect_format(tmp_path) == "polar"
    read = load_views(tmp_path)
    assert [v.name for v in read] == sorted(v.name for v in views)
    by_name = {v.name: v for v in read}
    _compare(views, [by_name[v.name] for v in views], lambda s: torch.full_like(s, 1e-6), _aolp_exact)


def _uniform_view(name, channels, eye):
    """Constant Stokes per channel: demosaicing a constant mosaic is exact."""
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    s0 = torch.tensor(rng.uniform(0.3, 0.9, channels))
    rho, phi = torch.tensor(rng.uniform(0.2, 0.6, channels)), torch.tensor(rng.uniform(0, math.pi, channels))

    def stokes_fn(height, width):
        grid = lambda v: v[:, None, None].expand(channels, height, width).clone()  # noqa: E731
        return grid(s0), grid(s0 * rho * torch.cos(2 * phi)), grid(s0 * rho * torch.sin(2 * phi))

    return _quantised_view(name, stokes_fn, eye)


@pytest.mark.parametrize("pattern, channels", [("mono", 1), ("rgb", 3)])
def test_polar_folder_raw_mosaic_round_trip(tmp_path, pattern, channels):
    views = [_uniform_view(f"v{i}", channels, eye=[2.5 * math.cos(i), 2.5 * math.sin(i), 1.0]) for i in range(2)]
    if pattern == "rgb":
        views.append(_quantised_view("red", _red, eye=[2.0, -2.5, 1.5]))
    write_polar_folder(views, tmp_path, mode="raw", pattern=pattern)
    read = {v.name: v for v in load_views(tmp_path, pattern=pattern)}
    atol = lambda s: torch.full_like(s, 1e-6)  # noqa: E731
    _compare(views, [read[v.name] for v in views], atol, _aolp_exact, check_red=pattern == "rgb")


def test_colmap_binary_model_matches_text(views, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    write_polar_folder(views[-1:], tmp_path)
    text_dir = tmp_path / "sparse" / "0"
    binary_dir = tmp_path / "binary"
    binary_dir.mkdir()
    pycolmap.Reconstruction(str(text_dir)).write_binary(str(binary_dir))
    assert (binary_dir / "images.bin").is_file()
    text, binary = read_colmap_model(text_dir), read_colmap_model(binary_dir)
    assert sorted(text) == sorted(binary) == ["red.png"]
    for name in text:
        np.testing.assert_allclose(binary[name].K, text[name].K, atol=1e-12)
        np.testing.assert_allclose(binary[name].world_to_camera, text[name].world_to_camera, atol=1e-12)


def test_colmap_scene_export_writes_a_binary_model_colmap_reads(views, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    points = np.array([[0.1, 0.2, 0.3], [1.0, -2.0, 0.5]])
    colors = np.array([[10, 20, 30], [200, 100, 50]], dtype=np.uint8)
    write_colmap_scene(tmp_path / "scene", views, points, colors)
    model = tmp_path / "scene" / "sparse" / "0"
    for ext in (".bin", ".txt"):  # the same model in each form alone
        only = tmp_path / f"only{ext}"
        only.mkdir()
        for name in ("cameras", "images", "points3D"):
            (only / f"{name}{ext}").write_bytes((model / f"{name}{ext}").read_bytes())
        assert read_colmap_model(only).keys() == read_colmap_model(tmp_path / "scene" / "sparse").keys()
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "only.bin"))  # COLMAP's own reader
    assert sorted(image.name for image in reconstruction.images.values()) == sorted(f"{v.name}.png" for v in views)
    np.testing.assert_allclose(sorted(p.xyz.tolist() for p in reconstruction.points3D.values()), points.tolist())
    assert sorted(p.color.tolist() for p in reconstruction.points3D.values()) == colors.tolist()
    by_name = {v.name: v for v in views}
    for image in reconstruction.images.values():
        view = by_name[image.name[: -len(".png")]]
        np.testing.assert_allclose(image.cam_from_world().matrix(), view.world_to_camera.double().numpy()[:3], atol=1e-9)
        fx, fy, cx, cy = reconstruction.cameras[image.camera_id].params
        np.testing.assert_allclose([fx, fy, cx, cy], view.K.double().numpy()[[0, 1, 0, 1], [0, 1, 2, 2]], atol=1e-9)


def test_registry_detects_the_project_format(scene, tmp_path):
    write_scene(scene, tmp_path)
    assert detect_format(tmp_path) == "polargs"
    read = load_views(tmp_path)
    assert [v.name for v in read] == [v.name for v in scene.views]
    torch.testing.assert_close(read[0].stokes, scene.views[0].stokes, atol=1e-6, rtol=0)
