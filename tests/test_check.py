"""Silhouette check of the AoLP direction, the 8-bit scale check and the GT-normal frame."""

import argparse
import json
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from polargs_plugin.data.checks import check_views, image_scale_ratio, orient_normal_map


def mirrored(views):
    """AoLP -> -AoLP (s2 -> -s2): a reader with the wrong rotation direction."""
    return [replace(v, stokes=torch.stack([v.stokes[0], v.stokes[1], -v.stokes[2]])) for v in views]


@pytest.mark.parametrize("name", ["glossy_plane_sphere", "shiny_torus", "bumpy_mixed"])
def test_synthetic_scenes_are_consistent_and_mirroring_is_flagged(name, synthetic_views):
    views = synthetic_views(name, num_views=8, width=64, height=64)
    report = check_views(views)
    assert report.verdict == "consistent", report.to_dict()["overall"]
    assert abs(report.overall.offset_deg) < 5 and report.overall.strength > 0.4
    flipped = check_views(mirrored(views))
    assert flipped.verdict == "mirrored" and any("mirrored" in m for m in flipped.messages)


def test_rotated_reference_and_no_polarization(synthetic_views):
    views = synthetic_views("bumpy_mixed", num_views=4, width=48, height=48)
    # rotate the Stokes reference by 30 degrees: (s1, s2) turned by 60 degrees
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    rotated = [replace(v, stokes=torch.stack([v.stokes[0], c * v.stokes[1] - s * v.stokes[2], s * v.stokes[1] + c * v.stokes[2]]))
               for v in views]
    report = check_views(rotated)
    assert report.verdict == "rotated" and abs(abs(report.overall.offset_deg) - 30) < 5
    flat = [replace(v, stokes=torch.stack([v.stokes[0], 0 * v.stokes[1], 0 * v.stokes[2]])) for v in views]
    assert check_views(flat).verdict == "inconclusive"


def test_image_scale_ratio_finds_a_factor_two(synthetic_views):
    view = synthetic_views("bumpy_mixed", num_views=1, width=48, height=48)[0]
    image = view.image.clamp_min(0).numpy()
    srgb = np.where(image <= 0.0031308, 12.92 * image, 1.055 * image ** (1 / 2.4) - 0.055)
    picture = np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8).transpose(1, 2, 0)
    mask = view.mask[0].numpy()
    assert image_scale_ratio(view.stokes, picture, mask)["ratio"] == pytest.approx(1.0, abs=0.03)
    half = image_scale_ratio(view.stokes * 0.5, picture, mask)
    assert half["ratio"] == pytest.approx(2.0, rel=0.03) and half["encoding"] == "srgb"


def test_orient_normal_map_tells_the_frame(synthetic_views):
    view = synthetic_views("shiny_torus", num_views=1, width=48, height=48)[0]
    n, mask, w2c = view.normal_gt.numpy(), view.mask[0].numpy(), view.world_to_camera.numpy()
    gl = n * np.array([1.0, -1.0, -1.0])[:, None, None]
    world = np.einsum("ji,jhw->ihw", w2c[:3, :3], n)
    for stored, frame in ((n, "opencv"), (gl, "opengl"), (world, "world")):
        out, found, score = orient_normal_map(stored, mask, w2c)
        assert found == frame and score > 0.5
        np.testing.assert_allclose(out[:, mask], n[:, mask], atol=1e-5)


def test_neisf_warns_on_poses_outside_its_normalisation(tmp_path, synthetic_views):
    from polargs_plugin.data.neisf import read_neisf, write_neisf

    views = synthetic_views("bumpy_mixed", num_views=2, width=32, height=32)
    far = []
    for v in views:
        w2c = v.world_to_camera.clone()
        w2c[:3, 3] *= 2.0  # cameras at distance 6
        far.append(replace(v, world_to_camera=w2c))
    write_neisf(far, tmp_path / "far")
    with pytest.warns(UserWarning, match="outside NeISF's normalisation"):
        read_neisf(tmp_path / "far")
    write_neisf(views, tmp_path / "near")  # distance 3 < 3.3: silent
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*NeISF's normalisation.*")
        read_neisf(tmp_path / "near")


def test_check_command(tmp_path, capsys, synthetic_views):
    from polargs_plugin.cli import check as check_cli
    from polargs_plugin.cli import main
    from polargs_plugin.data.nersp import write_nersp

    parser = argparse.ArgumentParser()
    check_cli.register(parser.add_subparsers())
    views = synthetic_views("shiny_torus", num_views=4, width=48, height=48)
    write_nersp(views, tmp_path / "ok")
    write_nersp(mirrored(views), tmp_path / "bad")
    args = parser.parse_args(["check", str(tmp_path / "ok"), "--json", str(tmp_path / "r.json")])
    assert args.func(args) == 0
    assert "consistent" in capsys.readouterr().out
    assert json.loads((tmp_path / "r.json").read_text())["verdict"] == "consistent"
    args = parser.parse_args(["check", str(tmp_path / "bad")])
    assert args.func(args) == 1 and "mirrored" in capsys.readouterr().out
    assert main(["check", str(tmp_path / "missing")]) == 2
    assert capsys.readouterr().err.startswith("error: ")
