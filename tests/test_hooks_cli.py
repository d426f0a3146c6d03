"""``polargs preprocess``: pictures, content-keyed cache, clear errors on bad input."""

import json

import cv2
import torch

from polargs_plugin.cli import main
from polargs_plugin.data.scene_format import write_scene

PICTURES = ("aolp", "dolp", "masks", "i_diff", "i_chro", "target", "pri")


def test_preprocess_writes_pictures_and_reuses_cache(tmp_path, capsys, synthetic_scene):
    scene = synthetic_scene("glossy_plane_sphere", num_views=2, width=32, height=32)
    dataset = write_scene(scene, tmp_path / "scene")
    out = tmp_path / "pre"
    assert main(["preprocess", str(dataset), "--out", str(out)]) == 0
    for view in scene.views:
        for name in PICTURES:
            picture = cv2.imread(str(out / "pictures" / f"{view.name}_{name}.png"))
            assert picture is not None and picture.shape == (32, 32, 3)
    cache = sorted((out / "maps").glob("*.pt"))
    assert len(cache) == 2
    stamps = [path.stat().st_mtime_ns for path in cache]
    # The masks picture tints specular pixels magenta: compare with the cached mask.
    maps = torch.load(cache[0], weights_only=True)
    view_name = cache[0].name.rsplit("-", 1)[0]
    bgr = cv2.imread(str(out / "pictures" / f"{view_name}_masks.png"))
    tinted = (bgr[..., 0] > 150) & (bgr[..., 1] < 100) & (bgr[..., 2] > 150)
    assert (torch.from_numpy(tinted) >= maps["specular_mask"][0]).all()

    assert main(["preprocess", str(dataset), "--out", str(out), "--no-pictures"]) == 0
    assert [path.stat().st_mtime_ns for path in sorted((out / "maps").glob("*.pt"))] == stamps
    printed = capsys.readouterr().out
    assert "specular" in printed and "maps: reused 2 of 2 views" in printed


def test_preprocess_bad_input_is_reported_and_writes_nothing(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "out"
    assert main(["preprocess", str(empty), "--out", str(out)]) == 2
    assert str(empty) in capsys.readouterr().err
    assert not out.exists()
    bad_config = tmp_path / "bad.json"
    bad_config.write_text(json.dumps({"correction": {"no_such_knob": 1}}))
    assert main(["preprocess", str(empty), "--out", str(out), "--config", str(bad_config)]) == 2
    err = capsys.readouterr().err
    assert str(bad_config) in err and "no_such_knob" in err


def test_preprocess_takes_the_train_settings_file_and_presets(tmp_path, capsys, synthetic_scene):
    scene = synthetic_scene("glossy_plane_sphere", num_views=2, width=16, height=16)
    dataset = write_scene(scene, tmp_path / "scene")
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"polar": {"correction": {"mahalanobis_threshold": 0.5}}, "train": {"iterations": 5}}))
    assert main(["preprocess", str(dataset), "--config", str(settings), "--preset", "real", "--no-pictures"]) == 0
    assert len(list((dataset / "preprocessed" / "maps").glob("*.pt"))) == 2  # where `polargs train` looks
    settings.write_text(json.dumps({"polar": {"correction": {"mahalanobis": 0.5}}}))
    assert main(["preprocess", str(dataset), "--config", str(settings)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {settings}: polar.correction: unknown setting 'mahalanobis'") and err.count("\n") == 1
    assert main(["preprocess", str(dataset), "--bit-depth", "12"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {dataset}: --bit-depth: only for polar folders") and "polargs dataset" in err
