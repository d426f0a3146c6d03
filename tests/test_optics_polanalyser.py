"""End-to-end agreement with polanalyser (demosaic, Stokes, AoLP, DoLP) on random and real raw frames.

Tolerance notes: our images are float32 (docs/conventions.md), polanalyser works in float64 on the integer
counts. A float32 count/full-scale value is off by <= 3e-8, so Stokes agree to ~1e-7. AoLP error
grows like 4e-8 / sqrt(s1^2 + s2^2) and DoLP error like 1e-7 / s0, so the 1e-5 comparison of
those two is made where polanalyser's polarized magnitude >= 1e-2 (AoLP) and s0 >= 2e-2 (DoLP);
pixels where polanalyser's DoLP is non-finite (no epsilon) are excluded. Elsewhere the AoLP and
DoLP *functions* are compared to polanalyser on the same Stokes input.
"""

import math
from pathlib import Path

import cv2
import numpy as np
import polanalyser as pa
import pytest
import torch

from polargs_plugin.optics import aolp_from_stokes, demosaic_polar, dolp_from_stokes, stokes_from_intensities
from polargs_plugin.optics.mosaic import _demosaic_torch

DATA = Path(__file__).parent / "data" / "polanalyser"
TOL = 1e-5


def _circular_diff(a, b, period=math.pi):
    d = np.mod(a - b, period)
    return np.minimum(d, period - d)


def _reference(raw, colour):
    """polanalyser pipeline in float64, results channel-first like ours: (4|3, C, H, W)."""
    full = 255.0 if raw.dtype == np.uint8 else 65535.0
    code = pa.COLOR_PolarRGB if colour else pa.COLOR_PolarMono
    images = np.stack(pa.demosaicing(raw, code)).astype(np.float64) / full  # (4, H, W[, 3 BGR])
    images = images[..., ::-1] if colour else images[..., None]  # BGR -> RGB
    stokes = pa.calcStokes(images, np.deg2rad([0, 45, 90, 135]))  # (H, W, C, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        dolp = pa.cvtStokesToDoLP(stokes)
    aolp = pa.cvtStokesToAoLP(stokes)
    # (4, H, W, C) -> (4, C, H, W); (H, W, C, 3) -> (3, C, H, W); (H, W, C) -> (C, H, W).
    return images.transpose(0, 3, 1, 2), stokes.transpose(3, 2, 0, 1), aolp.transpose(2, 0, 1), dolp.transpose(2, 0, 1)


def _check_against_polanalyser(raw, colour):
    images_ref, stokes_ref, aolp_ref, dolp_ref = _reference(raw, colour)
    images = demosaic_polar(raw, "rgb" if colour else "mono")
    stokes = stokes_from_intensities(images)
    aolp, dolp = aolp_from_stokes(stokes).numpy(), dolp_from_stokes(stokes).numpy()
    np.testing.assert_allclose(images.numpy(), images_ref, rtol=0, atol=TOL)
    np.testing.assert_allclose(stokes.numpy(), stokes_ref, rtol=0, atol=TOL)

    magnitude = np.hypot(stokes_ref[1], stokes_ref[2])
    strong = magnitude >= 1e-2
    assert strong.mean() > 0.5
    assert _circular_diff(aolp, aolp_ref)[strong].max() < TOL
    bright = np.isfinite(dolp_ref) & (stokes_ref[0] >= 2e-2)
    assert bright.mean() > 0.5
    np.testing.assert_allclose(dolp[bright], np.minimum(dolp_ref[bright], 1.0), rtol=0, atol=TOL)

    # The AoLP/DoLP functions alone, on identical Stokes, everywhere polanalyser is finite.
    same = stokes.double().numpy().transpose(2, 3, 1, 0)  # (H, W, C, 3)
    aolp64 = aolp_from_stokes(stokes.double()).numpy().transpose(1, 2, 0)
    assert _circular_diff(aolp64, pa.cvtStokesToAoLP(same)).max() < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        dolp_same = pa.cvtStokesToDoLP(same)
    finite = np.isfinite(dolp_same)
    dolp64 = dolp_from_stokes(stokes.double()).numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(dolp64[finite], np.clip(dolp_same[finite], 0, 1), rtol=0, atol=1e-12)


@pytest.mark.parametrize("colour", [False, True], ids=["mono", "rgb"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_random_raw_agrees_with_polanalyser(colour, dtype):
    rng = np.random.default_rng(7 + colour)
    high = np.iinfo(dtype).max
    raw = rng.integers(0, high + 1, (48, 64)).astype(dtype)
    raw[:4, :8] = 0  # dark corner: polanalyser's DoLP is NaN there, ours is 0
    _check_against_polanalyser(raw, colour)
    dolp = dolp_from_stokes(stokes_from_intensities(demosaic_polar(raw, "rgb" if colour else "mono")))
    assert bool(torch.isfinite(dolp).all()) and float(dolp.min()) >= 0 and float(dolp.max()) <= 1


@pytest.mark.parametrize("colour", [False, True], ids=["mono", "rgb"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_torch_integer_path_agrees_with_polanalyser(colour, dtype):
    # On the CPU integer data goes through OpenCV; the torch path (used for GPU tensors) must
    # give the same integers.
    raw = np.random.default_rng(11 + colour).integers(0, np.iinfo(dtype).max + 1, (40, 56)).astype(dtype)
    images_ref = _reference(raw, colour)[0] * np.iinfo(dtype).max
    ours = _demosaic_torch(torch.from_numpy(raw.astype(np.int32)), "rgb" if colour else "mono", True)
    assert ours.dtype == torch.int32
    np.testing.assert_array_equal(ours.numpy(), np.round(images_ref).astype(np.int32))


def _crops():
    return sorted(DATA.glob("*_IMX250MZR_x*_y*.png"))


def test_crops_present():
    names = [p.name for p in _crops()]
    assert len(names) == 5 and any(n.startswith("carps") for n in names)


@pytest.mark.parametrize("path", _crops(), ids=lambda p: p.stem)
def test_real_crops_agree_with_polanalyser(path):
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.ndim == 2 and raw.dtype == np.uint8
    _check_against_polanalyser(raw, colour=False)


# AoLP of the polarizer sheets stated in the source data's README (ccw from +x towards up).
SHEETS = {"x348_y1056": 83.0, "x968_y1056": 44.0, "x1520_y1056": 175.0, "x2076_y1072": 135.0}


@pytest.mark.parametrize("where,expected_deg", SHEETS.items())
def test_polarizer_sheet_aolp_matches_stated_angle(where, expected_deg):
    raw = cv2.imread(str(DATA / f"polarizer_IMX250MZR_{where}.png"), cv2.IMREAD_UNCHANGED)
    stokes = stokes_from_intensities(demosaic_polar(raw, source=where))
    aolp = aolp_from_stokes(stokes)[0, 2:-2, 2:-2].double()
    # Circular mean over the crop (doubled angle: AoLP has period pi).
    mean = 0.5 * torch.atan2(torch.sin(2 * aolp).mean(), torch.cos(2 * aolp).mean())
    error = _circular_diff(math.degrees(float(mean)), expected_deg, 180.0)
    assert error < 3.0, f"sheet at {where}: AoLP {math.degrees(float(mean)) % 180:.1f} deg"
    assert float(dolp_from_stokes(stokes).mean()) > 0.2  # the sheets polarize strongly
