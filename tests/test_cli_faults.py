"""Faults a real user meets on the command line: raw-mosaic folders read with the wrong
pattern, SfM with too few views, reader options on the wrong format, file modes, a slow --help.
Every error is one line ``error: FILE: problem`` naming the file or argument, with nothing
half-written."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from polargs_plugin.cli import _COMMANDS, build_parser, main
from polargs_plugin.data.polar_folder import write_polar_folder
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.io import atomic_path, atomic_write, current_umask
from polargs_plugin.types import View

CROPS = Path(__file__).parent / "data" / "polanalyser"


def _one_error_line(err: str, start: str) -> None:
    assert err.startswith(start), err
    assert err.count("\n") == 1 and "Traceback" not in err, err


def _mono_folder(tmp_path: Path) -> Path:
    """A polar folder whose raw/ holds the real IMX250MZR crops (64x64), with cameras."""
    crops = sorted(CROPS.glob("polarizer_*.png"))
    scene = generate_scene("glossy_plane_sphere", num_views=len(crops), width=64, height=64)
    views = [View(v.name, v.K, v.world_to_camera, v.stokes[:, :1]) for v in scene.views]
    folder = write_polar_folder(views, tmp_path / "mono", mode="raw", pattern="mono", bit_depth=8)
    for view, crop in zip(views, crops):
        (folder / "raw" / f"{view.name}.png").write_bytes(crop.read_bytes())
    return folder


def _colour_folder(tmp_path: Path) -> Path:
    """A polar folder of synthetic IMX250MYR mosaics written by the project's own writer."""
    scene = generate_scene("torus_knot", num_views=4, width=128, height=128)
    return write_polar_folder(scene.views, tmp_path / "colour", mode="raw", pattern="rgb", bit_depth=8,
                              angle_images=scene.angle_images)


def test_mono_frames_read_as_colour_are_refused_and_auto_detects_mono(tmp_path, capsys):
    folder = _mono_folder(tmp_path)
    out = tmp_path / "pre"
    assert main(["preprocess", str(folder), "--out", str(out), "--pattern", "rgb", "--no-pictures"]) == 2
    err = capsys.readouterr().err
    _one_error_line(err, f"error: {folder / 'raw'}/")
    assert "looks like a mono (IMX250MZR) frame" in err and "--pattern mono" in err
    assert not out.exists()
    assert main(["preprocess", str(folder), "--out", str(out), "--no-pictures"]) == 0  # --pattern auto
    assert "raw mosaics: mono (told from the frames)" in capsys.readouterr().out
    # the escape hatch for colour frames of grey scenes
    assert main(["preprocess", str(folder), "--out", str(tmp_path / "p2"), "--pattern", "rgb",
                 "--no-pattern-check", "--no-pictures"]) == 0


def test_colour_frames_read_as_mono_are_refused_and_auto_detects_colour(tmp_path, capsys):
    folder = _colour_folder(tmp_path)
    assert main(["preprocess", str(folder), "--out", str(tmp_path / "pre"), "--pattern", "mono", "--no-pictures"]) == 2
    err = capsys.readouterr().err
    _one_error_line(err, f"error: {folder / 'raw'}/")
    assert "looks like a colour (IMX250MYR) frame" in err and "--pattern rgb" in err
    assert main(["preprocess", str(folder), "--out", str(tmp_path / "pre"), "--no-pictures"]) == 0
    assert "raw mosaics: rgb (told from the frames)" in capsys.readouterr().out


def test_sfm_on_too_few_views_says_what_it_needs(tmp_path, capsys):
    folder = _mono_folder(tmp_path)
    for path in (folder / "sparse").rglob("*"):
        if path.is_file():
            path.unlink()
    for path in sorted((folder / "raw").iterdir())[2:]:
        path.unlink()
    assert main(["preprocess", str(folder), "--pattern", "mono", "--no-pictures"]) == 2
    err = capsys.readouterr().err
    _one_error_line(err, f"error: {folder}: no COLMAP model")
    assert "--sfm" in err
    assert main(["preprocess", str(folder), "--pattern", "mono", "--sfm", "--no-pictures"]) == 2
    err = capsys.readouterr().err
    _one_error_line(err, f"error: {folder}: SfM got 2 image(s)")
    assert "at least 3 overlapping views" in err
    assert not (folder / "preprocessed").exists() and not (folder / "sparse" / "0" / "cameras.txt").exists()


def test_reader_options_on_a_synthetic_scene_name_the_option(tmp_path, capsys):
    from polargs_plugin.service import ReaderOptions, load_dataset

    with pytest.raises(Exception) as info:
        load_dataset("synthetic:shiny_torus", ReaderOptions(pattern="mono"))
    assert "--pattern" in str(info.value) and "synthetic:shiny_torus" in str(info.value)


def test_files_get_the_umask_mode_not_0600(tmp_path):
    old = os.umask(0o027)
    try:
        assert current_umask() == 0o027
        with atomic_write(tmp_path / "a.json") as f:
            json.dump({}, f)
        with atomic_path(tmp_path / "b.npy") as tmp:
            np.save(tmp, np.zeros(2))
    finally:
        os.umask(old)
    for name in ("a.json", "b.npy"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o640


def test_help_imports_no_subcommand_and_lists_every_command():
    code = (
        "import sys\n"
        "from polargs_plugin.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "heavy = [m for m in ('polargs_plugin.cli.train', 'polargs_plugin.cli.ablate', 'polargs_plugin.data.synthetic',"
        " 'numba', 'open3d') if m in sys.modules]\n"
        "print('HEAVY', heavy)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert "HEAVY []" in result.stdout, result.stdout + result.stderr
    for name in _COMMANDS:
        assert name in result.stdout
    # the summaries listed without importing are those the modules register
    full = build_parser()
    sub = next(a for a in full._actions if a.dest == "command")
    assert {c.dest: c.help for c in sub._choices_actions} == {k: v for k, v in _COMMANDS.items() if k in sub.choices}


@pytest.mark.slow
def test_errors_are_one_line_without_traceback_in_a_real_process(tmp_path):
    settings = tmp_path / "s.json"
    settings.write_text(json.dumps({"trian": {}}))
    result = subprocess.run(
        [sys.executable, "-m", "polargs_plugin.cli", "train", "synthetic:shiny_torus", "--out", str(tmp_path / "run"),
         "--config", str(settings)],
        capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert result.returncode == 2
    _one_error_line(result.stderr, f"error: {settings}: unknown key 'trian'")
    assert not (tmp_path / "run").exists()


def test_mesh_rereads_the_views_with_the_runs_reader_options(tmp_path, monkeypatch):
    """`polargs mesh` on a run folder reads the dataset with summary.json's "reader" entry (as
    `polargs train` and `polargs ablate` record it), here pattern="mono"."""
    import polargs_plugin.service.runs as runs
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.service.data import Dataset

    views = generate_scene("bumpy_mixed", num_views=3, width=24, height=24).views
    trainer = Trainer(views, TrainConfig.cpu(progress=False, num_init_points=100, iterations=1))
    trainer.step()
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    trainer.save_checkpoint(run_dir / runs.CHECKPOINT_NAME)
    dataset = tmp_path / "polar"  # never read: the loader is replaced
    (run_dir / runs.SUMMARY_NAME).write_text(json.dumps({"dataset": str(dataset), "reader": {"pattern": "mono"}}))
    calls = []

    def fake_load(spec, options):
        calls.append((spec, options.fmt, options.reader_kwargs()))
        return Dataset(spec, views, "polar", options)

    monkeypatch.setattr(runs, "load_dataset", fake_load)
    assert main(["mesh", str(run_dir), "--out", str(tmp_path / "mesh.ply")]) == 0
    assert calls == [(str(dataset), "auto", {"pattern": "mono"})]
