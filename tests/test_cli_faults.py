"""Faults a real user meets on the command line: raw-mosaic folders read with the wrong
pattern, SfM with too few views, reader options on the wrong format, file modes, a slow --help,
and the table ``CLI_FAULTS`` (bit depths that lie, settings out of range, dot-named scenes, files
that are no checkpoint, other data under a run's view names), a full disk, SIGTERM to a grid.
Every error is one line ``error: FILE: problem`` naming the file or argument, with exit status 2
and nothing half-written."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from polargs_plugin.cli import _COMMANDS, build_parser, main
from polargs_plugin.data.polar_folder import write_polar_folder
from polargs_plugin.io import atomic_path, atomic_write, current_umask
from polargs_plugin.types import View
import scene_cache
from test_faults import (  # noqa: F401 - scene16 and tiny_scene are fixtures, used by name
    _CANNOT_WRITE, _disk_full_at, _rewrite_angles, _scene8_with_16bit_view, scene16, tiny_scene,
)

CROPS = Path(__file__).parent / "data" / "polanalyser"


def _one_error_line(err: str, start: str) -> None:
    assert err.startswith(start), err
    assert err.count("\n") == 1 and "Traceback" not in err, err


def _mono_folder(tmp_path: Path) -> Path:
    """A polar folder whose raw/ holds the real IMX250MZR crops (64x64), with cameras."""
    crops = sorted(CROPS.glob("polarizer_*.png"))
    scene = scene_cache.scene("glossy_plane_sphere", num_views=len(crops), width=64, height=64)
    views = [View(v.name, v.K, v.world_to_camera, v.stokes[:, :1]) for v in scene.views]
    folder = write_polar_folder(views, tmp_path / "mono", mode="raw", pattern="mono", bit_depth=8)
    for view, crop in zip(views, crops):
        (folder / "raw" / f"{view.name}.png").write_bytes(crop.read_bytes())
    return folder


def _colour_folder(tmp_path: Path) -> Path:
    """A polar folder of synthetic IMX250MYR mosaics written by the project's own writer."""
    scene = scene_cache.scene("torus_knot", num_views=4, width=128, height=128)
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


def test_mesh_rereads_the_views_with_the_runs_reader_options(tmp_path, monkeypatch, synthetic_views):
    """`polargs mesh` on a run folder reads the dataset with summary.json's "reader" entry (as
    `polargs train` and `polargs ablate` record it), here pattern="mono"."""
    import polargs_plugin.service.runs as runs
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.service.data import Dataset

    views = synthetic_views("bumpy_mixed", num_views=3, width=24, height=24)
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


# ------------------------------------------------------------------------------------------------
# The fault table: each row a command a careful user (or an adversarial one) runs on bad input, and
# the one line it must print (exit status 2), with nothing written and nothing left behind.


@dataclass
class CliFault:
    """One row of the table.

    Attributes:
        case: what the user does wrong.
        setup: builds the input under the test folder (``setup(tmp, fixtures)``, ``fixtures``:
            pytest's request, for the scene folders) and returns the command line, without ``polargs``.
        message: the line after ``error: `` (``{tmp}``: the test folder).
    """

    case: str
    setup: Callable
    message: str


def _copy(request, fixture: str, tmp: Path, name: str = "data") -> Path:
    return Path(shutil.copytree(request.getfixturevalue(fixture), tmp / name))


def _settings(tmp: Path, settings: dict) -> str:
    (tmp / "settings.json").write_text(json.dumps(settings))
    return str(tmp / "settings.json")


def _trained(tmp: Path, request) -> Path:
    """A run trained (2 iterations) on a copy of the tiny scene, ``tmp/run``."""
    data = _copy(request, "tiny_scene", tmp)
    assert main(["train", str(data), "--out", str(tmp / "run"), "--iters", "2", "--no-polar", "--quiet"]) == 0
    return tmp / "run"


def _trained_then_changed(tmp: Path, request) -> Path:
    run = _trained(tmp, request)
    _rewrite_angles(tmp / "data", "view_001", lambda a: (a // 2).astype(a.dtype))
    return run


def _random_checkpoint(tmp: Path) -> Path:
    (tmp / "run").mkdir()
    (tmp / "run" / "summary.json").write_text(json.dumps({"dataset": "synthetic:shiny_torus"}))
    (tmp / "run" / "checkpoint.pt").write_bytes(bytes(range(256)) * 16)
    return tmp / "run"


def _untrained_folder(tmp: Path) -> Path:
    """What an older version left after a refused run: fingerprint.json, no checkpoint."""
    (tmp / "run").mkdir()
    (tmp / "run" / "fingerprint.json").write_text(json.dumps({"format": "polargs-data-fingerprint-v1", "views": []}))
    return tmp / "run"


def _polar_folder8(tmp: Path) -> Path:
    views = scene_cache.views("glossy_plane_sphere", num_views=3, width=24, height=24)
    return write_polar_folder(views, tmp / "polar", mode="angles", bit_depth=8)


def _ablate(tmp: Path, *extra: str, variants: str = "base") -> list[str]:
    return ["ablate", "--scenes", "glossy_plane_sphere", "--variants", variants, "--out", str(tmp / "grid"), "--quiet",
            *extra]


_TRAIN = ["--iters", "2", "--quiet"]
_NOT_OURS = "not a checkpoint of this package (torch cannot read it as plain tensors and containers)"
_OTHER_DATA = ("{tmp}/run/fingerprint.json: {tmp}/data is not the data this run was trained on: the images of 1 of 3 "
               "views (view_001) differ from those this run was trained on")

CLI_FAULTS = [
    CliFault("a view of 16-bit files holding 0-255 in a folder whose cameras.json says 8-bit",
             lambda tmp, rq: (_scene8_with_16bit_view(_copy(rq, "scene16", tmp)),
                              ["train", str(tmp / "data"), "--out", str(tmp / "run"), *_TRAIN])[1],
             "{tmp}/data/polar/view_002_000.png: 16-bit image, but cameras.json declares bit_depth 8"),
    CliFault("--bit-depth 16 for 8-bit images",
             lambda tmp, rq: ["train", str(_polar_folder8(tmp)), "--out", str(tmp / "run"), "--bit-depth", "16", *_TRAIN],
             "{tmp}/polar/images/view_000_0.png: 8-bit file, but --bit-depth 16 was given: it holds at most 8 bits"),
    CliFault("a zero Dense interval in --config",
             lambda tmp, rq: ["train", "synthetic:shiny_torus", "--out", str(tmp / "run"), "--config",
                              _settings(tmp, {"polar": {"densify": {"interval": 0}}})],
             "{tmp}/settings.json: polar.densify.interval: must be a positive integer, got 0"),
    CliFault("a negative max_gaussians in --config",
             lambda tmp, rq: ["train", "synthetic:shiny_torus", "--out", str(tmp / "run"), "--config",
                              _settings(tmp, {"train": {"density": {"max_gaussians": -5}}})],
             "{tmp}/settings.json: train.density.max_gaussians: must be a non-negative integer or null, got -5"),
    CliFault("iterations 0 in --config",
             lambda tmp, rq: ["train", "synthetic:shiny_torus", "--out", str(tmp / "run"), "--config",
                              _settings(tmp, {"train": {"iterations": 0}})],
             "{tmp}/settings.json: train.iterations: must be a positive integer, got 0"),
    CliFault("--resume of a folder a refused run left, with the same settings",
             lambda tmp, rq: ["train", "synthetic:shiny_torus", "--out", str(_untrained_folder(tmp)), "--resume",
                              "--config", _settings(tmp, {"polar": {"densify": {"interval": 0}}})],
             "{tmp}/settings.json: polar.densify.interval: must be a positive integer, got 0"),
    CliFault("--resume of a folder a refused run left",
             lambda tmp, rq: ["train", "synthetic:shiny_torus", "--out", str(_untrained_folder(tmp)), "--resume"],
             "{tmp}/run/checkpoint.pt: --resume given but the file does not exist"),
    CliFault("a zero Dense interval in --polar-set",
             lambda tmp, rq: _ablate(tmp, "--polar-set", "densify.interval=0", variants="base,full"),
             "--polar-set: polar.densify.interval: must be a positive integer, got 0"),
    CliFault("--polar-set for a grid without the PolarGS hooks",
             lambda tmp, rq: _ablate(tmp, "--polar-set", "densify.interval=0"),
             "--polar-set: sets PolarGS values, but no variant of this grid uses the PolarGS hooks (base)"),
    CliFault("a negative max_gaussians in --train-set",
             lambda tmp, rq: _ablate(tmp, "--train-set", "density.max_gaussians=-5"),
             "--train-set: train.density.max_gaussians: must be a non-negative integer or null, got -5"),
    CliFault("iterations 0 in --train-set", lambda tmp, rq: _ablate(tmp, "--train-set", "iterations=0"),
             "--train-set: train.iterations: must be a positive integer, got 0"),
    CliFault("a scene named '..'",
             lambda tmp, rq: ["ablate", "--scenes", f"..={tmp}", "--out", str(tmp / "grid"), "--quiet"],
             "--scenes: scene '..={tmp}': name '..' starts with '.'; give another name (NAME=PATH)"),
    CliFault("a scene folder whose name starts with a dot",
             lambda tmp, rq: ["ablate", "--scenes", str(_copy(rq, "tiny_scene", tmp, ".scan")), "--out",
                              str(tmp / "grid"), "--quiet"],
             "--scenes: scene '{tmp}/.scan': name '.scan' starts with '.'; give another name (NAME=PATH)"),
    CliFault("a checkpoint of random bytes", lambda tmp, rq: ["mesh", str(_random_checkpoint(tmp)), "--quiet"],
             f"{{tmp}}/run/checkpoint.pt: {_NOT_OURS}"),
    CliFault("mesh on other data under the same view names",
             lambda tmp, rq: ["mesh", str(_trained_then_changed(tmp, rq)), "--quiet"], _OTHER_DATA),
    CliFault("eval on other data under the same view names",
             lambda tmp, rq: ["eval", str(_trained_then_changed(tmp, rq)), "--normals", "--quiet"], _OTHER_DATA),
]


def _files(folder: Path) -> dict[str, tuple[int, int] | None]:
    """Every file (size, modification time) and folder (None) under ``folder``."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) if p.is_file() else None
            for p in folder.rglob("*")}


@pytest.mark.parametrize("fault", CLI_FAULTS, ids=[f.case for f in CLI_FAULTS])
def test_cli_faults_are_one_line_exit_2_and_leave_nothing(tmp_path, capsys, monkeypatch, request, fault):
    import polargs_plugin.ablation.grid as grid

    argv = fault.setup(tmp_path, request)
    capsys.readouterr()
    monkeypatch.setattr(grid, "run_grid", lambda *args, **kwargs: pytest.fail("a refused grid ran"))
    before = _files(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == f"error: {fault.message.format(tmp=tmp_path)}\n"
    assert _files(tmp_path) == before  # nothing written, nothing half-written, nothing removed


def test_a_full_disk_while_training_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch, tiny_scene):
    _disk_full_at(monkeypatch, 1)
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "run"), "--no-polar", *_TRAIN]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path}/run/checkpoint.pt: {_CANNOT_WRITE}; nothing of this run is kept\n"
    assert not (tmp_path / "run").exists()


def test_mesh_from_another_folder_reads_the_data_the_run_was_trained_on(tmp_path, monkeypatch, capsys, tiny_scene):
    """`polargs train base` from one folder, `polargs mesh` from another that holds a different
    `base`: the run recorded where its `base` is."""
    first, second = tmp_path / "first", tmp_path / "second"
    shutil.copytree(tiny_scene, first / "base")
    (second / "base").mkdir(parents=True)  # not a dataset: reading it would fail
    monkeypatch.chdir(first)
    assert main(["train", "base", "--out", "run", "--no-polar", *_TRAIN]) == 0
    monkeypatch.chdir(second)
    assert main(["mesh", str(first / "run"), "--quiet"]) == 0
    assert json.loads((first / "run" / "tsdf_mesh.json").read_text())["run_dir"] == str(first / "run")
    assert main(["eval", "../first/run", "--normals", "--quiet"]) == 0
    assert json.loads((first / "run" / "metrics.json").read_text())["target"] == str(first / "run")


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_ablate_stopped_by_sigterm_says_so_and_ends_its_pool_cleanly(tmp_path):
    """SIGTERM to `polargs ablate` (a scheduler's timeout, `kill`): its workers stop their cells as
    Ctrl-C does (each keeps its partial folder, with the attempt's log), the pool ends without
    leaked semaphores, and the command ends with one line and exit status 143."""
    import signal
    import time

    out = tmp_path / "grid"
    args = ["ablate", "--scenes", "glossy_plane_sphere", "--variants", "base,reg", "--out", str(out), "--views", "4",
            "--size", "24x24", "--train-set", "iterations=100000", "--jobs", "2", "--quiet"]
    proc = subprocess.Popen([sys.executable, "-m", "polargs_plugin.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 180
        while len(list(out.glob(".tmp-*"))) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)  # both cells under way
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    assert err.splitlines()[-1] == (f"interrupted (SIGTERM): 0 of 2 runs finished; runs under way keep their last "
                                    f"periodic checkpoint in {out}/.partial; the same command continues them")
    assert "leaked semaphore" not in err and "Traceback" not in err
    logs = list(out.glob(".partial/*/attempts.log"))
    assert len(logs) == 2 and all("\nINTERRUPTED (" in log.read_text() for log in logs)  # not FAILED
    assert not list(out.glob(".tmp-*")) and not list(out.glob("logs/*.log"))  # no failure recorded
