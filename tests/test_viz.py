"""Pictures: colouring against polanalyser / OpenCV, PNG writing round-trips and atomicity."""

import math

import cv2
import numpy as np
import polanalyser as pa
import pytest
import torch

import polargs_plugin.viz as viz
from polargs_plugin.optics import aolp_from_stokes, dolp_from_stokes
from polargs_plugin.viz import aolp_to_rgb, dolp_to_rgb, hsv_to_rgb, save_png, save_polar_pictures


def _random_maps(seed=0, size=128):
    g = torch.Generator().manual_seed(seed)
    aolp = torch.rand(1, size, size, generator=g) * math.pi
    aolp[0, 0, :6] = torch.tensor([0.0, 1e-6, math.pi - 1e-6, math.pi / 2, math.pi / 3, -0.3])
    return aolp, torch.rand(1, size, size, generator=g)


@pytest.mark.parametrize("style", ["dark", "light"])
@pytest.mark.parametrize("with_dolp", [False, True])
def test_aolp_to_rgb_matches_polanalyser_within_one_level(style, with_dolp):
    aolp, dolp = _random_maps()
    ours = aolp_to_rgb(aolp, dolp if with_dolp else None, style)
    assert ours.shape == (3, 128, 128) and ours.dtype == torch.float32
    kwargs = {}
    if with_dolp:
        kwargs = {"value": dolp[0].numpy()} if style == "dark" else {"saturation": dolp[0].numpy()}
    reference = pa.applyColorToAoLP(aolp[0].numpy(), **kwargs)[..., ::-1].transpose(2, 0, 1)  # BGR -> RGB
    levels = np.round(ours.numpy() * 255)  # our picture in 8-bit levels
    assert np.abs(levels - reference.astype(np.float64)).max() <= 1.0


def test_aolp_hue_circle_and_styles():
    aolp = torch.tensor([0.0, math.pi / 3, 2 * math.pi / 3]).reshape(1, 1, 3)
    rgb = aolp_to_rgb(aolp)
    # Hue = AoLP / pi of a turn: 0 -> red, pi/3 -> ~green (120 deg), 2pi/3 -> ~blue (240 deg).
    assert int(rgb[:, 0, 0].argmax()) == 0 and int(rgb[:, 0, 1].argmax()) == 1 and int(rgb[:, 0, 2].argmax()) == 2
    zero = torch.zeros(1, 1, 3)
    assert float(aolp_to_rgb(aolp, zero, "dark").max()) == 0.0  # unpolarized is black
    assert float(aolp_to_rgb(aolp, zero, "light").min()) == 1.0  # ... or white


def test_hsv_to_rgb_matches_opencv_float():
    g = torch.Generator().manual_seed(1)
    hsv = torch.rand(3, 32, 32, generator=g)
    ours = hsv_to_rgb(hsv[0], hsv[1], hsv[2])
    image = np.stack([hsv[0].numpy() * 360, hsv[1].numpy(), hsv[2].numpy()], axis=-1).astype(np.float32)
    reference = cv2.cvtColor(image, cv2.COLOR_HSV2RGB).transpose(2, 0, 1)
    np.testing.assert_allclose(ours.numpy(), reference, atol=1e-5)
    batched = hsv_to_rgb(hsv[0].expand(2, 32, 32), hsv[1].expand(2, 32, 32), hsv[2].expand(2, 32, 32))
    assert batched.shape == (2, 3, 32, 32)


def test_dolp_to_rgb_matches_polanalyser_grey():
    _, dolp = _random_maps(seed=2)
    ours = dolp_to_rgb(dolp)
    reference = pa.applyColorToDoP(dolp[0].numpy())[..., ::-1].transpose(2, 0, 1).astype(np.float64)
    # polanalyser truncates twice (LUT index, then the LUT entry), so it can sit 2 levels lower.
    difference = np.round(ours.numpy() * 255) - reference
    assert difference.min() >= 0 and difference.max() <= 2
    clamped = dolp_to_rgb(torch.tensor([-0.5, 0.5, 1.5]).reshape(1, 1, 3))
    torch.testing.assert_close(clamped, torch.tensor([0.0, 0.5, 1.0]).expand(3, 1, 3).reshape(3, 1, 3))


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_save_png_round_trip_rgb_order(tmp_path, bit_depth):
    g = torch.Generator().manual_seed(3)
    image = torch.rand(3, 10, 12, generator=g)
    image[:, 0, 0] = torch.tensor([1.0, 0.0, 0.0])  # pure red
    path = save_png(tmp_path / "sub" / "image.png", image, bit_depth)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    full = 2**bit_depth - 1
    rgb = back[..., ::-1].transpose(2, 0, 1).astype(np.float64) / full
    np.testing.assert_allclose(rgb, image.numpy(), atol=0.5 / full + 1e-7)
    assert back[0, 0].tolist() == [0, 0, full]  # BGR on disk, red in the last slot
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["image.png"]


def test_save_png_grey_and_uint8(tmp_path):
    grey = (torch.arange(12, dtype=torch.uint8) * 20).reshape(1, 3, 4)
    back = cv2.imread(str(save_png(tmp_path / "g.png", grey)), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, grey[0].numpy())
    back16 = cv2.imread(str(save_png(tmp_path / "g16.png", grey, 16)), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back16, grey[0].numpy().astype(np.uint16) * 257)


def test_save_png_is_atomic_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "keep.png"
    save_png(target, torch.zeros(3, 4, 4))
    before = target.read_bytes()

    def broken(*_args, **_kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(viz.cv2, "imwrite", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        save_png(target, torch.ones(3, 4, 4))
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_save_png_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        save_png(tmp_path / "a.png", torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match="non-finite"):
        save_png(tmp_path / "a.png", torch.full((3, 4, 4), float("nan")))
    with pytest.raises(ValueError, match="bit_depth"):
        save_png(tmp_path / "a.png", torch.zeros(3, 4, 4), 12)
    with pytest.raises(ValueError, match="dtype"):
        save_png(tmp_path / "a.png", np.zeros((3, 4, 4), np.int32))
    assert not list(tmp_path.iterdir())


def test_save_polar_pictures(tmp_path):
    g = torch.Generator().manual_seed(4)
    s0 = torch.rand(3, 16, 16, generator=g) + 0.2
    rho, phi = torch.rand(3, 16, 16, generator=g) * 0.8, torch.rand(3, 16, 16, generator=g) * math.pi
    stokes = torch.stack([s0, s0 * rho * torch.cos(2 * phi), s0 * rho * torch.sin(2 * phi)])
    paths = save_polar_pictures(stokes, tmp_path / "pics", "view0")
    assert [p.name for p in paths] == ["view0_aolp.png", "view0_dolp.png", "view0_aolp_dolp.png", "view0_s0.png"]
    read = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[..., ::-1].transpose(2, 0, 1) / 255.0 for p in paths]
    mean = stokes.mean(dim=1, keepdim=True)
    aolp, dolp = aolp_from_stokes(mean), dolp_from_stokes(mean)
    # The AoLP picture is polanalyser's colouring of the channel-mean AoLP.
    reference = pa.applyColorToAoLP(aolp[0].numpy())[..., ::-1].transpose(2, 0, 1) / 255.0
    assert np.abs(read[0] - reference).max() <= 1.5 / 255
    assert np.abs(read[1] - dolp.expand(3, 16, 16).numpy()).max() <= 0.5 / 255 + 1e-6
    assert np.abs(read[3] - np.clip(s0.numpy() / 2, 0, 1)).max() <= 0.5 / 255 + 1e-6
    with pytest.raises(ValueError, match=r"\(3, C, H, W\)"):
        save_polar_pictures(stokes[:2], tmp_path, "bad")


def test_contact_sheet_places_pictures_in_a_grid(tmp_path):
    from polargs_plugin.viz import save_contact_sheet

    red = torch.zeros(3, 4, 5)
    red[0] = 1.0
    grey = torch.full((1, 4, 5), 0.5)
    path = save_contact_sheet([[red, grey], [grey]], tmp_path / "sheet.png", gap=2)
    sheet = cv2.imread(str(path))[..., ::-1]  # RGB
    assert sheet.shape == (4 + 2 + 4, 5 + 2 + 5, 3)
    assert sheet[0, 0].tolist() == [255, 0, 0]
    assert sheet[0, 7].tolist() == [128, 128, 128]
    assert sheet[6, 0].tolist() == [128, 128, 128]
    assert sheet[6, 7].tolist() == [255, 255, 255]  # empty cell stays white
    assert sheet[4, 0].tolist() == [255, 255, 255]  # gap row
    with pytest.raises(ValueError, match="expected"):
        save_contact_sheet([[red, torch.zeros(3, 2, 2)]], tmp_path / "bad.png")
