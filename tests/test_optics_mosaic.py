"""Sensor mosaic layout, bilinear interpolation and input checks (polanalyser: test_optics_polanalyser)."""

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import convolve

from polargs_plugin.io import PolarInputError
from polargs_plugin.optics import (
    POLARIZER_LATTICE,
    aolp_from_stokes,
    demosaic_polar,
    dolp_from_stokes,
    mosaic_from_intensities,
    stokes_from_intensities,
)

# (row, column) of each angle in the 2x2 super-pixel, written out from the IMX250MZR datasheet
# layout (90 45 / 135 0), independently of the module's constant.
LAYOUT = {0: (1, 1), 45: (0, 1), 90: (0, 0), 135: (1, 0)}
ANGLES = (0, 45, 90, 135)


def _raw_by_hand(images, colour):
    """Numpy mosaic: images (4, C, H, W) at 0/45/90/135 -> (H, W); RGGB inside each sub-lattice."""
    h, w = images.shape[-2:]
    raw = np.zeros((h, w), dtype=images.dtype)
    for k, angle in enumerate(ANGLES):
        r, c = LAYOUT[angle]
        if not colour:
            raw[r::2, c::2] = images[k, 0, r::2, c::2]
            continue
        for (br, bc), channel in (((0, 0), 0), ((0, 1), 1), ((1, 0), 1), ((1, 1), 2)):
            raw[r + 2 * br :: 4, c + 2 * bc :: 4] = images[k, channel, r + 2 * br :: 4, c + 2 * bc :: 4]
    return raw


def _random_images(channels, h=16, w=24, seed=0):
    return np.random.default_rng(seed).random((4, channels, h, w))


def test_lattice_constant_matches_sensor_layout():
    assert POLARIZER_LATTICE == tuple(LAYOUT[angle] for angle in ANGLES)


@pytest.mark.parametrize("pattern,channels", [("mono", 1), ("rgb", 3)])
def test_mosaic_from_intensities_matches_layout(pattern, channels):
    images = _random_images(channels)
    ours = mosaic_from_intensities(torch.from_numpy(images), pattern)
    np.testing.assert_array_equal(ours.numpy(), _raw_by_hand(images, channels == 3))
    batched = mosaic_from_intensities(torch.from_numpy(np.stack([images, images[::-1].copy()])), pattern)
    assert batched.shape == (2, 16, 24)
    np.testing.assert_array_equal(batched[1].numpy(), _raw_by_hand(images[::-1].copy(), channels == 3))


def test_constant_angle_images_survive_mono_and_colour_demosaic():
    # Distinct constant levels per angle (and per colour) come back exactly, in 0/45/90/135 and
    # RGB order: red stays in channel 0.
    levels = np.array([[10, 20, 30], [60, 70, 80], [110, 120, 130], [160, 170, 180]], dtype=np.uint8)
    images = np.broadcast_to(levels[:, :, None, None], (4, 3, 16, 24)).copy()
    rgb = demosaic_polar(_raw_by_hand(images, colour=True), "rgb")
    assert rgb.shape == (4, 3, 16, 24) and rgb.dtype == torch.float32
    torch.testing.assert_close(rgb * 255, torch.from_numpy(images).float())
    mono = demosaic_polar(_raw_by_hand(images[:, :1], colour=False), "mono")
    torch.testing.assert_close(mono * 255, torch.from_numpy(images[:, :1]).float())


def _bilinear_reference(raw, offset, kernel):
    """Zero-filled lattice convolved with the bilinear kernel; one-pixel border repeated."""
    sparse = np.zeros_like(raw)
    sparse[offset[0] :: 2, offset[1] :: 2] = raw[offset[0] :: 2, offset[1] :: 2]
    full = convolve(sparse, kernel, mode="constant")
    return np.pad(full[1:-1, 1:-1], 1, mode="edge")


def test_float_mono_demosaic_is_bilinear():
    raw = np.random.default_rng(1).random((12, 20)).astype(np.float32)
    ours = demosaic_polar(raw, "mono").numpy()
    kernel = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 4
    for k, angle in enumerate(ANGLES):
        np.testing.assert_allclose(ours[k, 0], _bilinear_reference(raw.astype(np.float64), LAYOUT[angle], kernel), atol=1e-6)


def test_float_colour_demosaic_is_bilinear_bayer_then_polar():
    raw = np.random.default_rng(2).random((16, 24))
    ours = demosaic_polar(raw.astype(np.float32), "rgb").numpy()
    rb_kernel = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 4
    g_kernel = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]]) / 4
    colour = np.zeros((3, 16, 24))
    for angle in ANGLES:
        r, c = LAYOUT[angle]
        sub = raw[r::2, c::2]
        green = np.zeros_like(sub)
        green[0::2, 1::2], green[1::2, 0::2] = sub[0::2, 1::2], sub[1::2, 0::2]
        green = np.pad(convolve(green, g_kernel, mode="constant")[1:-1, 1:-1], 1, mode="edge")
        colour[0, r::2, c::2] = _bilinear_reference(sub, (0, 0), rb_kernel)
        colour[1, r::2, c::2] = green
        colour[2, r::2, c::2] = _bilinear_reference(sub, (1, 1), rb_kernel)
    for k, angle in enumerate(ANGLES):
        for ch in range(3):
            np.testing.assert_allclose(ours[k, ch], _bilinear_reference(colour[ch], LAYOUT[angle], rb_kernel), atol=1e-6)


def test_recovers_known_polarization_from_synthetic_mosaic():
    h, w = 32, 40
    s0, rho, phi = 0.8, 0.35, math.radians(120.0)
    images = np.stack([np.full((1, h, w), 0.5 * s0 * (1 + rho * math.cos(2 * (math.radians(b) - phi)))) for b in ANGLES])
    raw16 = np.round(_raw_by_hand(images, colour=False) * 65535).astype(np.uint16)
    stokes = stokes_from_intensities(demosaic_polar(raw16))
    assert float((stokes[0] - s0).abs().max()) < 1e-4
    assert float((dolp_from_stokes(stokes) - rho).abs().max()) < 1e-4
    assert float((aolp_from_stokes(stokes) - phi).abs().max()) < 1e-4


def test_bit_depth_inference_and_override():
    rng = np.random.default_rng(3)
    raw12 = rng.integers(0, 4096, (8, 8)).astype(np.uint16)
    torch.testing.assert_close(demosaic_polar(raw12, bit_depth=12) * 4095, demosaic_polar(raw12) * 65535)
    raw8 = rng.integers(0, 256, (8, 8)).astype(np.uint8)
    assert float(demosaic_polar(raw8).max()) <= 1.0
    torch.testing.assert_close(demosaic_polar(raw8) * 255, demosaic_polar(raw8.astype(np.uint16)) * 65535)
    as_int = torch.from_numpy(raw12.astype(np.int32))
    torch.testing.assert_close(demosaic_polar(as_int, bit_depth=12), demosaic_polar(raw12, bit_depth=12))
    as_float = raw12.astype(np.float32)
    out = demosaic_polar(as_float, bit_depth=12)
    assert float(out.max()) <= 1.0 and float(out.min()) >= 0.0


def test_tensor_input_keeps_device_and_integer_rounding():
    raw = np.random.default_rng(4).integers(0, 256, (8, 12)).astype(np.uint8)
    from_tensor = demosaic_polar(torch.from_numpy(raw))
    torch.testing.assert_close(from_tensor, demosaic_polar(raw))
    scaled = from_tensor * 255
    torch.testing.assert_close(scaled, scaled.round(), rtol=0, atol=1e-4)  # OpenCV rounds to integers


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    raw = np.random.default_rng(5).integers(0, 65536, (32, 48)).astype(np.uint16)
    for pattern in ("mono", "rgb"):
        gpu = demosaic_polar(torch.from_numpy(raw.astype(np.int32)).cuda(), pattern, bit_depth=16)
        assert gpu.is_cuda
        torch.testing.assert_close(gpu.cpu(), demosaic_polar(raw, pattern), rtol=0, atol=1e-7)
        assert mosaic_from_intensities(gpu, pattern).is_cuda


@pytest.mark.parametrize(
    "raw,kwargs,problem",
    [
        (np.zeros((8, 8), np.uint8), {"pattern": "bayer"}, "unknown mosaic pattern"),
        (np.zeros((7, 8), np.uint8), {}, "multiple of 2"),
        (np.zeros((8, 10), np.uint8), {"pattern": "rgb"}, "multiple of 4"),
        (np.zeros((2, 2), np.uint8), {}, "at least 4"),
        (np.zeros((8, 8, 3), np.uint8), {}, "must be 2-D"),
        (np.full((8, 8), np.nan, np.float32), {}, "non-finite"),
        (np.full((8, 8), 2.0, np.float32), {}, "outside [0, 1]"),
        (np.full((8, 8), 5000, np.uint16), {"bit_depth": 12}, "12-bit range"),
        (np.zeros((8, 8), np.int32), {}, "give bit_depth"),
        (np.zeros((8, 8), np.uint8), {"bit_depth": 9}, "unsupported bit_depth"),
        (np.zeros((8, 8), np.bool_), {}, "unsupported dtype"),
        ([[0, 1], [1, 0]], {}, "numpy array or torch tensor"),
    ],
)
def test_bad_input_names_source_and_problem(raw, kwargs, problem):
    with pytest.raises(PolarInputError) as info:
        demosaic_polar(raw, source="shots/frame_0007.png", **kwargs)
    assert info.value.path == "shots/frame_0007.png"
    assert problem in str(info.value)


def test_mosaic_from_intensities_rejects_bad_shapes():
    with pytest.raises(ValueError, match="unknown mosaic pattern"):
        mosaic_from_intensities(torch.zeros(4, 1, 4, 4), "quad")
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 3, H, W\)"):
        mosaic_from_intensities(torch.zeros(4, 3, 6, 8), "rgb")
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 1, H, W\)"):
        mosaic_from_intensities(torch.zeros(4, 3, 4, 4), "mono")


# ------------------------------------------------------------------ mono / colour from the frame
def _real_crops():
    import cv2
    from pathlib import Path

    folder = Path(__file__).parent / "data" / "polanalyser"
    return {p.name: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(folder.glob("*.png"))}


def test_real_mono_frames_show_no_bayer_colour_structure():
    from polargs_plugin.optics.pattern import check_mosaic_pattern, classify_mosaic, mosaic_colour_evidence

    crops = _real_crops()
    assert len(crops) == 5
    for name, raw in crops.items():
        evidence = mosaic_colour_evidence(raw, source=name)
        assert evidence is not None and evidence < 0.02, name
        assert classify_mosaic(evidence) == "mono"
        assert check_mosaic_pattern(raw, "auto", source=name) == "mono"
        with pytest.raises(PolarInputError, match=rf"{name}: read as a colour .* looks like a mono"):
            check_mosaic_pattern(raw, "rgb", source=name)
        # also at 12 bits in 16-bit words (the scale does not matter)
        assert check_mosaic_pattern(raw.astype(np.uint16) * 16, "mono", bit_depth=12) == "mono"


@pytest.mark.parametrize("name", ["glossy_plane_sphere", "shiny_torus", "bumpy_mixed", "torus_knot"])
def test_synthetic_mosaics_from_the_writer_are_told_apart(name, synthetic_scene):
    from polargs_plugin.optics.pattern import check_mosaic_pattern, classify_mosaic, mosaic_colour_evidence

    scene = synthetic_scene(name, num_views=4, width=128, height=128)
    quantise = lambda x: np.rint(np.clip(x.numpy(), 0, 1) * 255).astype(np.uint8)  # noqa: E731
    colours, monos = [], []
    for images in scene.angle_images:
        images = images.double()
        colours.append(mosaic_colour_evidence(quantise(mosaic_from_intensities(images, "rgb"))))
        monos.append(mosaic_colour_evidence(quantise(mosaic_from_intensities(images.mean(1, keepdim=True), "mono"))))
    # a mono mosaic never looks colour; the colour mosaics of the bundled (coloured) scenes look
    # colour in most views (a near-grey view may be undecided, never mono)
    assert all(classify_mosaic(m) != "rgb" for m in monos) and max(monos) < 0.2
    assert all(classify_mosaic(c) != "mono" for c in colours) and sum(classify_mosaic(c) == "rgb" for c in colours) >= 3
    raw = quantise(mosaic_from_intensities(scene.angle_images[int(np.argmax(colours))].double(), "rgb"))
    with pytest.raises(PolarInputError, match="read as a mono .* looks like a colour"):
        check_mosaic_pattern(raw, "mono", source="frame.png")


def test_pattern_check_cannot_tell_flat_or_tiny_frames():
    from polargs_plugin.optics.pattern import check_mosaic_pattern, mosaic_colour_evidence

    flat = np.full((64, 64), 100, np.uint8)
    assert mosaic_colour_evidence(np.zeros((8, 8), np.uint8)) is None
    assert check_mosaic_pattern(flat, "rgb") == "rgb" and check_mosaic_pattern(flat, "mono") == "mono"
    with pytest.raises(PolarInputError, match="flat.png: cannot tell"):
        check_mosaic_pattern(flat, "auto", source="flat.png")
    with pytest.raises(PolarInputError, match="unknown mosaic pattern 'bayer'"):
        check_mosaic_pattern(flat, "bayer", source="flat.png")
