"""Faults at the doors a user walks through after training: a ground-truth mesh with NaN vertices,
files of views a dataset does not list, a patched trainer Python cannot compile, a damaged or
half-written maps cache, a dataset moved after training. One row of ``DOOR_FAULTS`` each (patch
scripts on a symlinked ``train.py``: tests/test_patch_scripts.py); each row states what the user
sees."""

from __future__ import annotations

import json
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from polargs_plugin.cli import main
from test_faults import _request, _rewrite_angles, tiny_scene  # noqa: F401 - tiny_scene is a fixture, used by name


def _one_error_line(err: str, start: str) -> str:
    assert err.startswith(start), err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def nan_vertex_in_the_gt_mesh(tmp_path: Path, capsys, data: Path) -> None:
    """The GT mesh is named, with how many vertices are not finite; nothing is written."""
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=10)
    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), sphere)
    vertices = np.asarray(sphere.vertices).copy()
    vertices[[3, 7]] = np.nan
    broken = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), sphere.triangles)
    o3d.io.write_triangle_mesh(str(tmp_path / "gt.ply"), broken)
    assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "gt.ply"), "--num-samples", "2000",
                 "--quiet"]) == 2
    _one_error_line(capsys.readouterr().err,
                    f"error: {tmp_path / 'gt.ply'}: 2 of {len(vertices)} vertices are not finite (NaN or inf)")
    assert not (tmp_path / "pred.metrics.json").exists()


def view_files_cameras_json_does_not_list(tmp_path: Path, capsys, data: Path) -> None:
    """The reader reads the listed views and names the files of the others in one warning."""
    from polargs_plugin.service import load_dataset

    cameras = json.loads((data / "cameras.json").read_text())
    cameras["views"] = cameras["views"][:-1]
    (data / "cameras.json").write_text(json.dumps(cameras))
    with pytest.warns(UserWarning) as caught:
        views = load_dataset(str(data)).views
    assert [v.name for v in views] == ["view_000", "view_001"]
    messages = [str(w.message) for w in caught if "not read" in str(w.message)]
    assert len(messages) == 1, messages
    count = sum(1 for sub in data.iterdir() if sub.is_dir() for p in sub.glob("view_002*"))
    assert messages[0].startswith(f"{data}: {count} file(s) of 1 view(s) not read (their views are not listed in "
                                  "cameras.json): depth/view_002.npy, diffuse/view_002.npy") and messages[0].endswith(f"and {count - 5} more")


def stokes_components_without_their_s0(tmp_path: Path, capsys, data: Path) -> None:
    """A NeRSP folder whose s0/ lacks a view: the s1 and s2 files of that view are named."""
    from polargs_plugin.data.nersp import read_nersp, write_nersp
    from polargs_plugin.service import load_dataset

    folder = write_nersp(load_dataset(str(data)).views, tmp_path / "nersp")
    (folder / "s0" / "0002.npy").unlink()
    with pytest.warns(UserWarning, match=r"2 file\(s\) of 1 view\(s\) not read \(no s0/ file of that view\): "
                      r"s1/0002.npy, s2/0002.npy"):
        assert len(read_nersp(folder)) == 2


def a_patched_trainer_python_cannot_compile(tmp_path: Path, capsys, data: Path) -> None:
    """One line naming the file and the line, exit 2; no scene made, no run started."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    (checkout / "train.py").write_text("import sys\nimport polargs_adapters.graphdeco as pg  # polargs-patch\n"
                                       "def training(:\n    pass\n")
    assert main(["dryrun", str(checkout), "--trainer", "graphdeco", "--workdir", str(tmp_path / "work")]) == 2
    captured = capsys.readouterr()
    _one_error_line(captured.err, f"error: {checkout / 'train.py'}:3: Python cannot compile it: SyntaxError: ")
    assert "FAIL" not in captured.out and not (tmp_path / "work").exists()


def _preprocess(data: Path, capsys) -> str:
    assert main(["preprocess", str(data), "--no-pictures"]) == 0
    return capsys.readouterr().out


def a_damaged_maps_cache(tmp_path: Path, capsys, data: Path) -> None:
    """An entry cut short and one overwritten with random bytes: both rebuilt, and said so."""
    _preprocess(data, capsys)
    entries = sorted((data / "preprocessed" / "maps").glob("*.pt"))
    assert [p.name.split("-")[0] for p in entries] == ["view_000", "view_001", "view_002"]
    entries[0].write_bytes(entries[0].read_bytes()[:200])
    entries[2].write_bytes(np.random.default_rng(0).bytes(4096))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _preprocess(data, capsys)
    line = next(line for line in out.splitlines() if line.startswith("maps: "))
    assert line.startswith(f"maps: reused 1 of 3 views from {data / 'preprocessed' / 'maps'}; rebuilt 2 whose cache "
                           "entry could not be used (view_000: unreadable (") and "view_002: unreadable (" in line
    assert sum("rebuilt: unreadable" in str(w.message) for w in caught) == 2
    assert not any("weights_only" in text for text in (line, *(str(w.message) for w in caught)))  # never advised
    assert "maps: reused 3 of 3 views" in _preprocess(data, capsys)  # rewritten whole


def a_temporary_file_a_killed_preprocess_left(tmp_path: Path, capsys, data: Path) -> None:
    """The next `polargs preprocess` removes it and says so; the entries themselves stay."""
    _preprocess(data, capsys)
    maps = data / "preprocessed" / "maps"
    entries = sorted(maps.glob("*.pt"))
    handle, stale = tempfile.mkstemp(prefix=f".{entries[1].stem}.", suffix=".pt", dir=maps)
    with open(handle, "wb") as file:
        file.write(b"half an entry")
    out = _preprocess(data, capsys)
    assert not Path(stale).exists() and sorted(maps.glob("*.pt")) == entries
    assert f"note: {maps}: removed 1 temporary file(s) a killed run left" in out
    assert "maps: reused 3 of 3 views" in out and not (data / "preprocessed" / "preprocess.lock").exists()


def a_dataset_moved_after_training(tmp_path: Path, capsys, data: Path) -> None:
    """`mesh` / `eval` name --data; with it they read the moved dataset, checked against the
    run's fingerprint (other data under the same view names is refused)."""
    from polargs_plugin.service import train_run

    run = tmp_path / "run"
    train_run(_request(data, run, iterations=30))
    moved = Path(shutil.move(str(data), str(tmp_path / "moved")))
    assert main(["mesh", str(run), "--quiet"]) == 2
    _one_error_line(capsys.readouterr().err, f"error: {data}: dataset not found (the one {run / 'summary.json'} names); "
                    "if it moved, give its new place with --data NEW_PATH")
    assert main(["mesh", str(run), "--data", str(moved), "--quiet"]) == 0
    assert main(["eval", str(run), "--gt", str(moved), "--data", str(moved), "--normals", "--num-samples", "2000",
                 "--quiet"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["gt"] == str(moved / "gt_mesh.ply") and metrics["normal_mae_deg"] > 0
    other = Path(shutil.copytree(moved, tmp_path / "other"))
    _rewrite_angles(other, "view_001", lambda a: (a // 2).astype(a.dtype))
    capsys.readouterr()
    assert main(["eval", str(run), "--normals", "--data", str(other), "--quiet"]) == 2
    _one_error_line(capsys.readouterr().err, f"error: {run / 'fingerprint.json'}: {other} is not the data this run was "
                    "trained on: the images of 1 of 3 views (view_001) differ")
    assert main(["eval", str(tmp_path / "run" / "tsdf_mesh.ply"), "--gt", str(moved), "--data", str(moved)]) == 2
    assert "--data names a run's moved dataset" in capsys.readouterr().err


DOOR_FAULTS: list[Callable] = [
    nan_vertex_in_the_gt_mesh,
    view_files_cameras_json_does_not_list,
    stokes_components_without_their_s0,
    a_patched_trainer_python_cannot_compile,
    a_damaged_maps_cache,
    a_temporary_file_a_killed_preprocess_left,
    a_dataset_moved_after_training,
]


@pytest.mark.parametrize("fault", DOOR_FAULTS, ids=[f.__name__ for f in DOOR_FAULTS])
def test_door_faults(fault, tmp_path, capsys, tiny_scene):
    fault(tmp_path, capsys, Path(shutil.copytree(tiny_scene, tmp_path / "data")))
