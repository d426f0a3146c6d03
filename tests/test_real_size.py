"""Real-size captures: compact storage of views and maps (round trips within stated tolerances),
``--resolution`` (the pixel-centre convention of images, masks and K together, and every command
that reads data), the memory and time estimates and the refusal."""

from __future__ import annotations

import json
import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from polargs_plugin.cli import main
from polargs_plugin.compact import HALF_MAX, HALF_RELATIVE_ERROR, AngleImages, Bits, Deferred, Half, Plain, compact
from polargs_plugin.correction import compute_polar_maps
from polargs_plugin.correction.store import MapsStore, compact_maps, expand_maps
from polargs_plugin.data.resolution import (
    area_resize, check_resolution, nearest_resize, prepare_view, resample_view, scale_intrinsics, target_size,
)
from polargs_plugin.data.scene_format import read_scene_folder
from polargs_plugin.io import PolarInputError
from polargs_plugin.optics.stokes import stokes_from_intensities
from polargs_plugin.service import estimates
from polargs_plugin.service.data import ReaderOptions, load_dataset
from polargs_plugin.service.scenes import SceneRequest, generate_scene_folder
from polargs_plugin.types import View, validate_view

SCENE = "glossy_plane_sphere"


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory) -> Path:
    """6 views of 32x24 (8-bit), written as a scene folder."""
    out = tmp_path_factory.mktemp("real") / "scene"
    generate_scene_folder(SceneRequest(SCENE, views=6, width=32, height=24), out)
    return out


def _half_error(values: torch.Tensor) -> torch.Tensor:
    """Bound of a float16 round trip: half an ulp, relative 2^-11 (2^-25 absolute below float16's normals)."""
    return values.abs() * HALF_RELATIVE_ERROR + 2.0**-25


# ------------------------------------------------------------------------------ stored forms
@pytest.mark.parametrize("dtype, full", [(torch.uint8, 255), (torch.uint16, 65535), (torch.uint16, 4095)])
def test_angle_images_decode_to_the_float32_stokes_of_the_images_bit_for_bit(dtype, full):
    levels = torch.randint(0, full + 1, (4, 3, 9, 7), generator=torch.Generator().manual_seed(1)).to(dtype)
    stored = AngleImages(levels, full)
    # what reading the images into float32 and computing the Stokes at once gives (numpy's division)
    reference = stokes_from_intensities(torch.from_numpy(levels.numpy().astype(np.float32) / np.float32(full)))
    assert torch.equal(stored.decode(), reference) and stored.decode().dtype == torch.float32
    assert stored.shape == (3, 3, 9, 7) and stored.nbytes == levels.numel() * levels.element_size()


def test_half_holds_floats_within_float16_rounding_and_refuses_nothing_silently():
    values = torch.randn(3, 3, 8, 8, dtype=torch.float64) * 10
    stored = compact(values)
    assert isinstance(stored, Half) and stored.dtype == torch.float64 and stored.nbytes == values.numel() * 2
    assert bool(((stored.decode() - values).abs() <= _half_error(values)).all())
    huge = values.clone()
    huge[0, 0, 0, 0] = 2 * HALF_MAX  # beyond float16: kept as it is
    assert isinstance(compact(huge), Plain) and compact(huge).decode() is huge


@pytest.mark.parametrize("shape", [(1, 8, 8), (1, 5, 7), (3,), (0,)])
def test_masks_are_kept_as_bits_and_come_back_exactly(shape):
    mask = torch.rand(shape) > 0.5
    stored = compact(mask)
    assert isinstance(stored, Bits) and stored.shape == mask.shape and stored.dtype == torch.bool
    assert stored.nbytes == math.ceil(mask.numel() / 8)
    decoded = stored.decode()
    assert decoded.dtype == torch.bool and torch.equal(decoded, mask)
    # bit i % 8 of byte i // 8, against numpy's little-endian packbits
    expected = np.packbits(mask.reshape(-1).numpy(), bitorder="little")
    assert np.array_equal(stored.packed.numpy(), expected)
    assert torch.equal(pickle.loads(pickle.dumps(stored.to("cpu"))).decode(), mask)
    with pytest.raises(TypeError, match="bool"):
        Bits.pack(mask.float())


def test_a_view_decodes_its_stored_images_on_every_read():
    levels = torch.randint(0, 256, (4, 1, 6, 5), dtype=torch.uint8)
    K, w2c = torch.eye(3, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    view = View("v", K, w2c, AngleImages(levels, 255), mask=torch.ones(1, 6, 5, dtype=torch.bool))
    assert (view.width, view.height, view.channels) == (5, 6, 1) and view.nbytes == 4 * 30 + 30
    first, second = view.stokes, view.stokes
    assert first is not second and torch.equal(first, second) and first.dtype == torch.float32
    assert torch.equal(view.image, first[0] / 2)
    moved = view.to("cpu").replaced(name="w")
    assert isinstance(moved.stored("stokes"), AngleImages) and moved.name == "w" and torch.equal(moved.stokes, first)
    validate_view(view, "test")  # shapes and finiteness from the stored forms
    plain = View("p", K, w2c, first)
    assert plain.stokes is first  # a tensor given is kept as it is, no copy
    with pytest.raises(TypeError, match="stored form"):
        View("x", K, w2c, first.numpy())


def test_a_scene_folders_ground_truth_stays_in_its_files_until_read(scene_folder):
    view = read_scene_folder(scene_folder)[2]
    assert isinstance(view.stored("normal_gt"), Deferred) and isinstance(view.stored("depth_gt"), Deferred)
    assert isinstance(view.stored("stokes"), AngleImages)
    assert view.nbytes == view.stored("stokes").nbytes + view.stored("mask").nbytes  # 12 + 1 bytes a pixel
    normals = torch.from_numpy(np.load(scene_folder / "normals" / f"{view.name}.npy")).permute(2, 0, 1)
    assert torch.equal(view.normal_gt, normals)


def test_the_maps_cache_keeps_float16_maps_and_the_exact_training_colour(scene_folder, tmp_path):
    from polargs_plugin.config import PolarConfig

    view = read_scene_folder(scene_folder)[0]
    maps = compute_polar_maps(view.stokes, view.mask)
    stored = compact_maps(maps)
    assert stored["intensity"].dtype == torch.float32 and stored["aolp"].dtype == torch.float16
    back = expand_maps(stored)
    assert torch.equal(back.intensity, maps.intensity) and torch.equal(back.specular_mask, maps.specular_mask)
    for name in ("aolp", "dolp", "pri", "i_diff", "i_chro"):
        original = getattr(maps, name)
        assert getattr(back, name).dtype == torch.float32
        assert bool(((getattr(back, name) - original).abs() <= _half_error(original)).all()), name
    config = PolarConfig.synthetic()
    store = MapsStore(tmp_path / "maps", budget=0)  # nothing kept in memory: every read from the file
    calls = []
    store.prepare(view, config, lambda: calls.append(1) or maps)
    again = MapsStore(tmp_path / "maps", budget=0)
    again.prepare(view, config, lambda: calls.append(1) or maps)
    assert calls == [1] and view.name in again and torch.equal(again[view.name].aolp, back.aolp)


def test_a_cache_of_views_keeps_entries_only_when_every_view_fits():
    """Views visited in a random order: a cache of a few of many would rarely hit, so with
    ``cycle`` set it keeps an entry only when ``cycle`` of them fit; least recently used first out."""
    from polargs_plugin.correction.store import BytesLRU

    cache = BytesLRU(100)
    for key in "abcd":
        cache.put(key, key.upper(), 30)
    assert [cache.get(k) for k in "abcd"] == [None, "B", "C", "D"] and cache.bytes == 90
    cache.set_cycle(4)  # 4 entries of 30 bytes do not fit in 100: nothing is kept any more
    assert [cache.get(k) for k in "bcd"] == [None, None, None] and cache.bytes == 0
    cache.put("a", "A", 30)
    assert cache.get("a") is None
    cache.put("e", "E", 25)  # 4 of 25 fit
    assert cache.get("e") == "E"
    cache.set_cycle(3)
    for key in "abc":
        cache.put(key, key.upper(), 30)
    assert [cache.get(k) for k in "abce"] == ["A", "B", "C", None] and cache.bytes == 90


def test_raw_frames_keep_their_demosaiced_integer_levels(tmp_path):
    from polargs_plugin.data.imageio_utils import write_png
    from polargs_plugin.data.polar_folder import _stokes_from_raw
    from polargs_plugin.optics.mosaic import demosaic_polar

    raw = np.random.default_rng(3).integers(0, 4096, (16, 24), dtype=np.uint16)
    stored = _stokes_from_raw(write_png(tmp_path / "frame.png", raw, 16), "rgb", 12)
    assert isinstance(stored, AngleImages) and stored.full_scale == 4095
    assert torch.equal(stored.decode(), stokes_from_intensities(demosaic_polar(raw, "rgb", 12)))


# -------------------------------------------------------------------------------- resolution
def test_resolution_has_the_upstream_meaning():
    assert target_size(612, 512, 1) == (612, 512) and target_size(612, 512, 2) == (306, 256)
    assert target_size(612, 512, 8) == (76, 64)  # round(76.5) as the upstream trainers round
    assert target_size(1224, 1024, 300) == (300, 251)  # above 8: a target width, the aspect kept
    for bad in (0, 3, 5, 7, -2):
        with pytest.raises(ValueError, match="1, 2, 4 or 8"):
            check_resolution(bad)
    with pytest.raises(ValueError, match="above the images' width 612"):
        target_size(612, 512, 700)


def test_area_average_is_exact_for_any_ratio():
    image = torch.rand(2, 13, 17, dtype=torch.float64)
    assert torch.allclose(area_resize(image[:, :12, :16], (8, 6)).double(),
                          torch.nn.functional.avg_pool2d(image[None, :, :12, :16], 2)[0], atol=1e-6)
    # brute force: each new pixel integrates the old pixels over its footprint [i W/w, (i+1) W/w)
    new = area_resize(image, (5, 4)).double()

    def weights(old: int, count: int) -> torch.Tensor:
        grid = torch.zeros(count, old, dtype=torch.float64)
        for i in range(count):
            lo, hi = i * old / count, (i + 1) * old / count
            for j in range(old):
                grid[i, j] = max(0.0, min(hi, j + 1) - max(lo, j)) / (hi - lo)
        return grid

    expected = torch.einsum("ih,chw,jw->cij", weights(13, 4), image, weights(17, 5))
    assert torch.allclose(new, expected, atol=1e-6)


@pytest.mark.parametrize("resolution", [2, 4, 8, 50])
def test_images_masks_and_K_keep_one_pixel_centre_convention(resolution):
    """The pixel-centre convention (docs/conventions.md: pixel u covers [u, u + 1), its centre at
    u + 0.5) holds for the resampled images, masks and K together: a ramp image holding each old
    pixel's centre column averages to each new pixel's centre in old columns, a mask cut at an old
    column keeps that cut, and K' projects a point where the image says the point is. Any of the
    three sampled or scaled about another origin (e.g. K' = s (K + 0.5) - 0.5, or masks sampled at
    a pixel's corner) fails this test."""
    width, height, cut = 160, 96, 21  # the mask: old pixel columns whose centre lies left of `cut`
    columns = (torch.arange(width, dtype=torch.float64) + 0.5).expand(height, width)
    rows = (torch.arange(height, dtype=torch.float64) + 0.5)[:, None].expand(height, width)
    stokes = torch.stack([torch.stack([columns, rows, torch.ones_like(rows)])] * 3)  # (3, 3, H, W): s0 = ramps
    mask = (columns < cut)[None]
    K = torch.tensor([[180.0, 0.0, 83.3], [0.0, 175.0, 41.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    view = View("ramp", K, torch.eye(4, dtype=torch.float64), stokes.float(), mask=mask)
    small = resample_view(view, resolution)
    new_w, new_h = small.width, small.height
    sx, sy = new_w / width, new_h / height
    centres_x = (torch.arange(new_w, dtype=torch.float64) + 0.5) / sx  # new pixel centres in old columns
    centres_y = (torch.arange(new_h, dtype=torch.float64) + 0.5) / sy
    got = small.stokes[0].double()
    if width % new_w == 0 and height % new_h == 0:  # whole pixels per cell: the average of the ramp is its centre
        assert torch.allclose(got[0], centres_x.expand(new_h, new_w), atol=1e-3)
        assert torch.allclose(got[1], centres_y[:, None].expand(new_h, new_w), atol=1e-3)
    else:  # cells cut pixels: the staircase's average lies within a quarter pixel of the centre
        assert float((got[0] - centres_x).abs().max()) <= 0.25
    assert torch.equal(small.mask[0], (centres_x < cut).expand(new_h, new_w))
    # a point projected through K' lands in the new pixel whose content (the ramps: where that pixel's
    # centre lies in old pixels) is where the old K put the point, up to its offset inside the pixel
    points = torch.rand(400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * torch.tensor(
        [1.6, 1.0, 1.0], dtype=torch.float64) - torch.tensor([0.8, 0.5, -1.5], dtype=torch.float64)
    old, new = (K @ points.T).T, (small.K @ points.T).T
    old, new = old[:, :2] / old[:, 2:], new[:, :2] / new[:, 2:]
    inside = (new[:, 0] >= 0) & (new[:, 0] < new_w) & (new[:, 1] >= 0) & (new[:, 1] < new_h)
    assert int(inside.sum()) > 100
    col, row = new[inside, 0].floor().long(), new[inside, 1].floor().long()
    tolerance = 1e-3 if width % new_w == 0 and height % new_h == 0 else 0.25
    offset_x = (old[inside, 0] - got[0][row, col]) * sx - (new[inside, 0] - (col + 0.5))
    offset_y = (old[inside, 1] - got[1][row, col]) * sy - (new[inside, 1] - (row + 0.5))
    assert float(offset_x.abs().max()) <= tolerance * sx and float(offset_y.abs().max()) <= tolerance * sy
    assert torch.allclose(scale_intrinsics(K, (width, height), (new_w, new_h))[:2, 2], K[:2, 2] * torch.tensor(
        [sx, sy], dtype=torch.float64))


def test_nearest_takes_the_pixel_that_holds_the_new_centre():
    row = torch.arange(12)[None]
    assert nearest_resize(row, (4, 1)).tolist() == [[1, 4, 7, 10]]  # centres 1.5, 4.5, 7.5, 10.5
    assert nearest_resize(row, (5, 1)).tolist() == [[1, 3, 6, 8, 10]]


def test_a_scene_folder_read_at_half_resolution(scene_folder):
    full, half = read_scene_folder(scene_folder), read_scene_folder(scene_folder, resolution=2)
    for a, b in zip(full, half):
        assert (b.width, b.height) == (16, 12) and isinstance(b.stored("stokes"), Half)
        expected = torch.nn.functional.avg_pool2d(a.stokes, 2)
        assert bool(((b.stokes - expected).abs() <= _half_error(expected) + 1e-7).all())
        assert torch.equal(b.mask, a.mask[:, 1::2, 1::2]) and torch.equal(b.normal_gt, a.normal_gt[:, 1::2, 1::2])
        assert torch.allclose(b.K, a.K * torch.tensor([[0.5], [0.5], [1.0]], dtype=torch.float64))
    copied = pickle.loads(pickle.dumps(half[0]))  # views travel to worker processes
    assert torch.equal(copied.stokes, half[0].stokes) and torch.equal(copied.normal_gt, half[0].normal_gt)
    with pytest.raises(PolarInputError, match="--resolution: resolution 40 is a target width above the images' width 32"):
        read_scene_folder(scene_folder, resolution=40)


def test_prepare_view_keeps_integer_images_and_compacts_float_ones_and_masks():
    levels = torch.randint(0, 256, (4, 3, 8, 8), dtype=torch.uint8)
    K, w2c = torch.eye(3, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    kept = prepare_view(View("a", K, w2c, AngleImages(levels, 255)))
    assert isinstance(kept.stored("stokes"), AngleImages)
    mask = torch.rand(1, 8, 8) > 0.5
    floats = prepare_view(View("b", K, w2c, torch.rand(3, 3, 8, 8), mask=mask, normal_gt=torch.rand(3, 8, 8)))
    assert isinstance(floats.stored("stokes"), Half) and isinstance(floats.stored("normal_gt"), Half)
    assert isinstance(floats.stored("mask"), Bits) and torch.equal(floats.mask, mask)


# ------------------------------------------------------------------ --resolution on every command
def test_train_records_the_resolution_and_mesh_reads_the_run_at_it(scene_folder, tmp_path, capsys):
    from polargs_plugin.service import load_run

    settings = tmp_path / "tiny.json"
    settings.write_text(json.dumps({"train": {"num_init_points": 200}}))
    run = tmp_path / "run"
    assert main(["train", str(scene_folder), "--out", str(run), "--iters", "4", "--quiet", "--no-polar",
                 "--config", str(settings), "--resolution", "2"]) == 0
    printed = capsys.readouterr().out
    assert "estimate: peak memory about" in printed and "estimate: about" in printed
    summary = json.loads((run / "summary.json").read_text())
    assert summary["reader"] == {"resolution": 2} and summary["image_size"] == [16, 12]
    assert summary["estimate"]["peak_memory_bytes"] > 0 and summary["peak_memory_bytes"] > 0
    views = load_run(run).views
    assert {(v.width, v.height) for v in views} == {(16, 12)}
    assert main(["mesh", str(run)]) == 0 and (run / "tsdf_mesh.ply").is_file()
    assert main(["train", "synthetic:" + SCENE, "--out", str(tmp_path / "syn"), "--iters", "2", "--quiet",
                 "--no-polar", "--config", str(settings), "-r", "64"]) == 0
    assert json.loads((tmp_path / "syn" / "summary.json").read_text())["image_size"] == [64, 64]


def test_preprocess_reads_at_the_resolution(scene_folder, tmp_path, capsys):
    assert main(["preprocess", str(scene_folder), "--out", str(tmp_path / "pre"), "--no-pictures", "--resolution", "2"]) == 0
    assert "view_000: 16x12" in capsys.readouterr().out
    maps = torch.load(next((tmp_path / "pre" / "maps").glob("*.pt")), weights_only=True)
    assert tuple(maps["aolp"].shape) == (1, 12, 16)


def test_a_bad_resolution_is_one_line_naming_it(scene_folder, tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:  # argparse: 3 is neither a divisor nor a width
        main(["train", str(scene_folder), "--out", str(tmp_path / "a"), "--resolution", "3"])
    assert stopped.value.code == 2 and "--resolution: must be 1, 2, 4 or 8" in capsys.readouterr().err
    assert main(["train", str(scene_folder), "--out", str(tmp_path / "b"), "--resolution", "500", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "target width above the images' width 32" in err and "\n" not in err
    assert not (tmp_path / "b").exists()


def test_ablate_and_demo_take_the_resolution_for_bundled_scenes_and_folders(tmp_path, monkeypatch, capsys,
                                                                           synthetic_views):
    import polargs_plugin.ablation.pipeline as pipeline_module
    import polargs_plugin.service.data as service_data
    from polargs_plugin.ablation.cell import Cell

    views = synthetic_views(SCENE, num_views=3, width=16, height=16)
    calls = []

    def fake_load(spec, options):
        calls.append(options.resolution)
        return service_data.Dataset(spec, views, "polargs", options)

    def stop_at_mesh(*args):
        raise RuntimeError("stopped before meshing")

    monkeypatch.setattr(service_data, "load_dataset", fake_load)
    monkeypatch.setattr(pipeline_module, "_mesh", stop_at_mesh)
    tiny = ["--views", "3", "--size", "32x32", "--iters", "1", "--train-set", "num_init_points=100", "--jobs", "1",
            "--quiet", "--variants", "base"]
    assert main(["demo", "--out", str(tmp_path / "demo"), "--resolution", "2", *tiny]) == 1
    data = tmp_path / "data"
    data.mkdir()
    (data / "gt_mesh.ply").write_text("stands in for the GT mesh")
    assert main(["ablate", "--scenes", f"mine={data}", "--out", str(tmp_path / "ablate"), "-r", "4", *tiny]) == 1
    assert "stopped before meshing" in capsys.readouterr().err and calls == [2, 4]
    for out, expected in (("demo", {"resolution": 2}), ("ablate", {"resolution": 4})):
        grid = json.loads((tmp_path / out / "grid.json").read_text())
        cells = [Cell.from_dict(c) for c in (grid["cells"] if isinstance(grid, dict) else grid)]
        assert [c.reader for c in cells] == [expected] and cells[0].fingerprint()["reader"] == expected


def test_demo_takes_a_family_scene_as_ablate_spells_it(tmp_path, monkeypatch, capsys):
    import polargs_plugin.cli.ablate as ablate_cli

    planned = []
    monkeypatch.setattr(ablate_cli, "execute", lambda args, cells, command: planned.extend(cells) or 0)
    assert main(["demo", "--out", str(tmp_path / "demo"), "--scene", "family:16", "--views", "3"]) == 0
    assert [(c.scene.name, c.scene.bundled, c.scene.seed, c.variant) for c in planned] == [
        ("family-16", "family", 16, "base"), ("family-16", "family", 16, "full")]
    assert main(["demo", "--out", str(tmp_path / "demo"), "--scene", "family:x"]) == 2
    assert "unknown scene 'family:x'" in capsys.readouterr().err


# ---------------------------------------------------------------------- estimates and refusal
def test_the_estimate_refuses_in_one_line_and_names_the_resolution_that_fits(scene_folder):
    from polargs_plugin.service import polar_config, train_config

    views = load_dataset(str(scene_folder)).views
    train, polar = train_config("cpu"), polar_config("synthetic", 1 / 6)
    roomy = estimates.estimate_memory(views, train, polar, held=500 << 20, available=8 << 30)
    assert roomy.fits and roomy.dense_calls == 61 and roomy.pixels == 6 * 32 * 24
    assert roomy.peak_bytes > roomy.held_bytes and roomy.image_bytes == sum(v.nbytes for v in views)
    # what the model adds per pixel shrinks with the square of the divisor
    per_pixel = roomy.peak_bytes - roomy.fixed_bytes
    assert roomy.peak_at(2) == roomy.fixed_bytes + math.ceil(per_pixel / 4)
    reach = roomy.peak_at(2) + (roomy.peak_bytes - roomy.peak_at(2)) // 2  # between the peaks at 1 and 2
    tight = estimates.estimate_memory(views, train, polar, held=500 << 20, available=reach - (500 << 20))
    assert not tight.fits
    line = tight.refusal()
    assert line.startswith("--resolution: training would need about") and " of memory (" in line
    assert "--resolution 2 (about" in line
    assert "\n" not in line
    hopeless = estimates.estimate_memory(views, train, polar, held=500 << 20, available=0)
    assert "--resolution (8, or a target width) or use fewer views" in hopeless.refusal()
    unknown = estimates.estimate_memory(views, train, None, held=500 << 20, available=None)
    assert unknown.fits and unknown.dense_calls == 0
    assert estimates.dense_calls(polar, 1000) == 11  # 500, 550, ..., 1000
    # Dense's per-view state (9 bytes a pixel of every view) is in memory only without a maps folder
    on_disk = estimates.estimate_memory(views, train, polar, held=500 << 20, available=None, maps_folder=True)
    assert roomy.peak_bytes - on_disk.peak_bytes == estimates.DENSE_STATE_BYTES_PER_PIXEL * roomy.pixels
    # a step's and a Dense call's buffers are not held at once: the larger of the two, per pixel of the largest view
    per_pixel = max(estimates.STEP_BYTES_PER_PIXEL + estimates.HOOKS_BYTES_PER_PIXEL, estimates.DENSE_BYTES_PER_PIXEL)
    assert on_disk.peak_bytes - on_disk.fixed_bytes - on_disk.image_bytes == per_pixel * 32 * 24


def test_a_cuda_training_is_estimated_against_the_gpus_memory(scene_folder, monkeypatch):
    from polargs_plugin.service import train_config

    views = load_dataset(str(scene_folder)).views
    asked = []
    monkeypatch.setattr(estimates, "device_memory", lambda device: asked.append(device) or (100 << 20, 1 << 20))
    estimate = estimates.estimate_memory(views, train_config("cpu", device="cuda:0"), None)
    images = sum(v.nbytes for v in views)
    assert asked == ["cuda:0"] and estimate.memory == "GPU memory"
    assert estimate.held_bytes == (100 << 20) + images and estimate.reach_bytes == (101 << 20)
    assert not estimate.fits and "of GPU memory" in estimate.refusal()


def test_train_refuses_what_does_not_fit_before_anything_is_written(scene_folder, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(estimates, "available_memory", lambda: 0)
    out = tmp_path / "run"
    assert main(["train", str(scene_folder), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {scene_folder}: --resolution: training would need about") and "\n" not in err
    assert not out.exists()


def test_timing_a_step_leaves_the_training_as_it_was(scene_folder):
    from polargs_plugin.service import build_trainer, train_config

    views = load_dataset(str(scene_folder)).views
    config = train_config("cpu", overrides={"num_init_points": 200, "iterations": 5}, progress=False)
    timed, plain = build_trainer(views, config, None), build_trainer(views, config, None)
    assert timed.time_step(views[0]) > 0
    for trainer in (timed, plain):
        for _ in range(5):
            trainer.step()
    assert torch.equal(timed.model.means, plain.model.means) and torch.equal(timed.model.sh, plain.model.sh)


def test_estimated_time_uses_the_timed_step(scene_folder):
    from polargs_plugin.service import build_trainer, polar_config, train_config

    views = load_dataset(str(scene_folder)).views
    config = train_config("cpu", overrides={"num_init_points": 200, "iterations": 100}, progress=False)
    polar = polar_config("synthetic", 1 / 6)
    trainer = build_trainer(views, config, None)
    base = estimates.estimate_memory(views, config, polar, held=1, available=None)
    timed = estimates.estimate_time(base, trainer, 100)
    assert timed.step_seconds > 0 and timed.seconds == pytest.approx(timed.step_seconds * estimates.STEP_GROWTH * 100)
    assert "estimate: about" in timed.time_line(100)


# ------------------------------------------------------------------------- streamed generation
def test_generated_views_come_one_at_a_time_and_equal_the_whole_scene():
    from polargs_plugin.data.synthetic import generate_scene, generate_scene_views

    whole = generate_scene(SCENE, num_views=3, width=16, height=12, seed=2)
    parts = list(generate_scene_views(SCENE, num_views=3, width=16, height=12, seed=2))
    assert [len(p.views) for p in parts] == [1, 1, 1]
    for part, view, angles in zip(parts, whole.views, whole.angle_images):
        assert torch.equal(part.views[0].stokes, view.stokes) and torch.equal(part.angle_images[0], angles)
        assert part.meta == whole.meta


def test_generate_writes_raw_frames_that_train_reads_back(tmp_path):
    from polargs_plugin.data.polar_folder import read_polar_folder

    out = tmp_path / "raw"
    made = generate_scene_folder(SceneRequest("bumpy_mixed", views=3, width=96, height=64, mosaic="rgb", bits=16), out)
    assert made.num_views == 3 and sorted(p.name for p in (out / "raw").iterdir())[0] == "view_000.png"
    assert (out / "sparse" / "0" / "cameras.txt").is_file() and (out / "gt_mesh.ply").is_file()
    info: dict = {}
    views = read_polar_folder(out, pattern="auto", info=info, resolution=2)
    assert info["pattern"] == "rgb" and {(v.width, v.height) for v in views} == {(48, 32)}
    bare = generate_scene_folder(SceneRequest(SCENE, views=3, width=32, height=24, mosaic="mono", cameras=False),
                                 tmp_path / "bare")
    assert not (bare.folder / "sparse").exists()
    with pytest.raises(PolarInputError, match="no COLMAP model"):
        load_dataset(str(bare.folder), ReaderOptions(pattern="mono"))
    with pytest.raises(PolarInputError, match="--size: a rgb mosaic needs a width and height divisible by 4"):
        generate_scene_folder(SceneRequest(SCENE, views=1, width=30, height=24, mosaic="rgb"), tmp_path / "odd")
