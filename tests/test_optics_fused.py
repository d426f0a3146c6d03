"""Fused raw -> Stokes (optics.mosaic.stokes_from_raw) against the unfused path and polanalyser.

Truths: polanalyser.demosaicing + calcStokes in float64 on the integer counts (independent code),
the unfused demosaic_polar + stokes_from_intensities (itself pinned to polanalyser), and the
closed-form Stokes of a uniformly polarized field.
"""

import math
from pathlib import Path

import cv2
import numpy as np
import polanalyser as pa
import pytest
import torch

from polargs_plugin.io import PolarInputError
from polargs_plugin.optics import demosaic_polar, mosaic_from_intensities, stokes_from_intensities
from polargs_plugin.optics.mosaic import stokes_from_raw

DATA = Path(__file__).parent / "data" / "polanalyser"


def _polanalyser_stokes(raw, colour, full):
    """(3, C, H, W) float64 Stokes from polanalyser, RGB order, in units of full scale."""
    images = pa.demosaicing(raw, pa.COLOR_PolarRGB if colour else pa.COLOR_PolarMono)
    images = np.stack(images).astype(np.float64) / full  # (4, H, W[, 3 BGR])
    images = images[..., ::-1] if colour else images[..., None]
    return pa.calcStokes(images, np.deg2rad([0, 45, 90, 135])).transpose(3, 2, 0, 1)


def _check(raw, pattern, bit_depth=None):
    fused = stokes_from_raw(raw, pattern, bit_depth)
    unfused = stokes_from_intensities(demosaic_polar(raw, pattern, bit_depth))
    assert fused.dtype == torch.float32 and fused.shape == unfused.shape
    torch.testing.assert_close(fused, unfused, rtol=0, atol=1e-6)
    full = float(2 ** (bit_depth or 8 * raw.dtype.itemsize) - 1)
    reference = _polanalyser_stokes(raw, pattern == "rgb", full)
    np.testing.assert_allclose(fused.numpy(), reference, rtol=0, atol=1e-5)
    return fused


@pytest.mark.parametrize("pattern", ["mono", "rgb"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(8, 8), (12, 20), (48, 64), (64, 40)])
def test_random_raw_matches_unfused_and_polanalyser(pattern, dtype, shape):
    rng = np.random.default_rng(sum(shape) + (pattern == "rgb") + 2 * (dtype == np.uint16))
    raw = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    stokes = _check(raw, pattern)
    assert stokes.shape == (3, 1 if pattern == "mono" else 3, *shape)


def test_extreme_values_do_not_overflow():
    # Sums of four 16-bit full-scale samples, and maximal contrast between neighbours.
    for raw in (np.full((16, 16), 65535, np.uint16), np.indices((16, 16)).sum(0).astype(np.uint16) % 2 * 65535):
        for pattern in ("mono", "rgb"):
            _check(raw, pattern)


@pytest.mark.parametrize("path", sorted(DATA.glob("*_IMX250MZR_x*_y*.png")), ids=lambda p: p.stem)
def test_real_crops_match_polanalyser(path):
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    _check(raw, "mono")


def test_uniformly_polarized_field_gives_closed_form_stokes():
    s0, rho, phi = 0.8, 0.35, math.radians(120.0)
    beta = np.deg2rad([0, 45, 90, 135]).reshape(4, 1, 1, 1)
    images = np.broadcast_to(0.5 * s0 * (1 + rho * np.cos(2 * (beta - phi))), (4, 3, 16, 24))
    raw = np.round(mosaic_from_intensities(torch.from_numpy(images.copy()), "rgb").numpy() * 65535).astype(np.uint16)
    stokes = stokes_from_raw(raw, "rgb").double()
    expected = torch.tensor([s0, s0 * rho * math.cos(2 * phi), s0 * rho * math.sin(2 * phi)], dtype=torch.float64)
    torch.testing.assert_close(stokes, expected.reshape(3, 1, 1, 1).expand_as(stokes), rtol=0, atol=2e-5)


def test_other_bit_depths_dtypes_and_inputs():
    rng = np.random.default_rng(3)
    raw12 = rng.integers(0, 4096, (16, 24)).astype(np.uint16)
    _check(raw12, "rgb", bit_depth=12)
    as_int = torch.from_numpy(raw12.astype(np.int32))
    torch.testing.assert_close(stokes_from_raw(as_int, "rgb", 12), stokes_from_raw(raw12, "rgb", 12), rtol=0, atol=0)
    torch.testing.assert_close(stokes_from_raw(torch.from_numpy(raw12), "mono", 12), stokes_from_raw(raw12, "mono", 12))
    # Float data takes the unfused path, already in [0, 1] or scaled by bit_depth. It skips the
    # integer rounding of the two interpolation stages (<= 1/2 count each): each angle is within
    # 1 count of the integer path, so s0 = (sum of 4) / 2 and s1, s2 are within 2 counts.
    as_float = stokes_from_raw(raw12.astype(np.float32), "rgb", 12)
    torch.testing.assert_close(as_float, stokes_from_intensities(demosaic_polar(raw12.astype(np.float32), "rgb", 12)))
    torch.testing.assert_close(as_float, stokes_from_raw(raw12, "rgb", 12), rtol=0, atol=2.0 / 4095)
    unit = rng.random((16, 24)).astype(np.float32)
    torch.testing.assert_close(stokes_from_raw(unit, "mono"), stokes_from_intensities(demosaic_polar(unit, "mono")))


def test_non_contiguous_input():
    raw = np.random.default_rng(4).integers(0, 256, (32, 48)).astype(np.uint8)
    view = raw[::2, ::2]  # a strided (16, 24) view
    torch.testing.assert_close(stokes_from_raw(view, "rgb"), stokes_from_raw(view.copy(), "rgb"), rtol=0, atol=0)


@pytest.mark.parametrize(
    "raw,kwargs,problem",
    [
        (np.zeros((8, 8), np.uint8), {"pattern": "bayer"}, "unknown mosaic pattern"),
        (np.zeros((8, 10), np.uint8), {"pattern": "rgb"}, "multiple of 4"),
        (np.full((8, 8), 5000, np.uint16), {"bit_depth": 12}, "12-bit range"),
        (np.zeros((8, 8), np.int32), {}, "give bit_depth"),
        (np.zeros((8, 8, 3), np.uint8), {}, "must be 2-D"),
    ],
)
def test_bad_input_names_source_and_problem(raw, kwargs, problem):
    with pytest.raises(PolarInputError) as info:
        stokes_from_raw(raw, source="shots/frame_0007.png", **kwargs)
    assert info.value.path == "shots/frame_0007.png"
    assert problem in str(info.value)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_tensor_matches_cpu():
    raw = np.random.default_rng(5).integers(0, 65536, (32, 48)).astype(np.uint16)
    for pattern in ("mono", "rgb"):
        gpu = stokes_from_raw(torch.from_numpy(raw.astype(np.int32)).cuda(), pattern, bit_depth=16)
        assert gpu.is_cuda
        torch.testing.assert_close(gpu.cpu(), stokes_from_raw(raw, pattern), rtol=0, atol=1e-6)
