"""The service layer on its own: typed requests in, typed results out, one-line errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from polargs_plugin.config import PolarConfig
from polargs_plugin.io import PolarInputError
from polargs_plugin.service import (
    Dataset, EvalSettings, MeshSettings, ReaderOptions, SceneRequest, StopRequest, TrainingInterrupted, TrainRequest,
    adapter_inputs, compare_fingerprints, evaluate, fingerprint, fuse_model, generate_scene_folder, load_dataset,
    load_run, mesh_run, options_from_record, polar_config, prepare_maps_cache, read_settings, train_config, train_run,
)
from polargs_plugin.service.maps import maps_entries

SCENE = "glossy_plane_sphere"


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory) -> Path:
    """A small bundled scene written as a scene folder (6 views, 32x32)."""
    out = tmp_path_factory.mktemp("scene") / "gps"
    made = generate_scene_folder(SceneRequest(SCENE, views=6, width=32, height=32), out)
    assert made.folder == out and (out / "cameras.json").is_file()
    return out


def _tiny_train(**fields):
    return train_config("cpu", overrides={"num_init_points": 200, "iterations": 6}, progress=False, **fields)


# ------------------------------------------------------------------------------- reading data
def test_reader_options_round_trip_through_a_run_record():
    options = ReaderOptions(fmt="polar", pattern="mono", bit_depth=12, check_pattern=False)
    assert options.to_dict() == {"fmt": "polar", "pattern": "mono", "bit_depth": 12, "check_pattern": False}
    assert ReaderOptions(**options.to_dict()) == options
    assert ReaderOptions().to_dict() == {} and ReaderOptions(sfm=True).reader_kwargs() == {"sfm": True}
    dataset = Dataset("data", [], "polar", options, pattern="mono")
    # SfM is not recorded (its model then lies in the folder); the detected pattern is
    assert options_from_record(dataset.record()) == ReaderOptions(fmt="polar", pattern="mono", bit_depth=12,
                                                                 check_pattern=False)
    with pytest.raises(ValueError, match="unknown reader option"):
        options_from_record({"colour": 1})


def test_load_dataset_reads_a_folder_and_names_what_is_wrong(scene_folder, tmp_path):
    dataset = load_dataset(str(scene_folder))
    assert dataset.format == "polargs" and len(dataset.views) == 6 and dataset.views[0].width == 32
    cases = [
        (str(tmp_path / "missing"), ReaderOptions(), "dataset not found"),
        (str(scene_folder), ReaderOptions(pattern="rgb"), "--pattern: only for polar folders"),
        (f"synthetic:{SCENE}", ReaderOptions(bit_depth=12), "--bit-depth apply to dataset folders"),
        ("synthetic:teapot", ReaderOptions(), "unknown synthetic scene 'teapot'"),
    ]
    for spec, options, problem in cases:
        with pytest.raises(PolarInputError, match=problem) as info:
            load_dataset(spec, options)
        assert "\n" not in str(info.value)


# ------------------------------------------------------------------------------- settings
def test_read_settings_layouts_and_their_errors(tmp_path):
    layered = tmp_path / "layered.json"
    layered.write_text(json.dumps({"polar": {"losses": {"alpha_normal": 0.1}}, "train": {"iterations": 7}}))
    settings = read_settings(layered)
    assert settings.polar == {"losses": {"alpha_normal": 0.1}} and settings.train == {"iterations": 7}
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({"losses": {"alpha_normal": 0.1}}))
    assert read_settings(bare, bare_polar=True).polar == {"losses": {"alpha_normal": 0.1}}
    with pytest.raises(PolarInputError, match="unknown key 'losses'"):
        read_settings(bare)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(PolarInputError, match="broken.json: not valid JSON"):
        read_settings(broken)
    assert read_settings(None).polar == {}


def test_polar_config_scales_the_paper_schedules_for_the_cpu_preset():
    # the CPU preset (vanilla x 1/6) runs PolarGS' schedules at 1/2: Dense 500-3500 every 50, L_dn from 3500
    config = polar_config("synthetic", 1 / 6)
    d = config.densify
    assert (d.start_iter, d.end_iter, d.interval) == (500, 3500, 50)
    assert config.losses.depth_normal_from_iter == 3500 and config.losses.normal_until_after_dense == 50
    assert config == PolarConfig.cpu_demo(0.5)
    real = polar_config("real", None, {"losses": {"use_scale": False}}, switches=["no_dense"])
    assert real.densify.patchmatch.lambda_aolp == 0.2 and real.losses.alpha_normal == 0.1
    assert real.densify.enabled is False and real.losses.use_scale is False and real.densify.interval == 100


def test_settings_errors_name_the_source_and_the_setting():
    with pytest.raises(PolarInputError, match=r"^run\.json: polar\.densify\.interval: must be a positive integer, got 0$"):
        polar_config("synthetic", None, {"densify": {"interval": 0}}, "run.json")
    with pytest.raises(PolarInputError, match=r"^run\.json: train\.iterations: must be a positive integer, got 0$"):
        train_config("cpu", None, {"iterations": 0}, "run.json")
    with pytest.raises(PolarInputError, match="unknown setting 'iters'"):
        train_config("cpu", None, {"iters": 3}, "run.json")
    config = train_config("paper", None, {"density": {"max_gaussians": 3000}}, seed=4)
    assert config.iterations == 30_000 and config.density.max_gaussians == 3000 and config.seed == 4


# ------------------------------------------------------------------------------- fingerprints
def test_fingerprint_tells_changed_images_and_moved_cameras(scene_folder):
    views = load_dataset(str(scene_folder)).views
    prints = fingerprint(views)
    assert compare_fingerprints(json.loads(json.dumps(prints)), prints) is None
    darker = [v.replaced(stokes=v.stokes * 0.5) for v in views]
    assert "the images of 6 of 6 views" in compare_fingerprints(prints, fingerprint(darker))
    moved = [v.replaced(world_to_camera=v.world_to_camera.clone()) for v in views]
    moved[2].world_to_camera[1, 3] += 0.1
    assert compare_fingerprints(prints, fingerprint(moved)) == (
        f"the cameras of 1 of 6 views ({views[2].name}) differ from those this run was trained on")
    assert "this run was trained on 6 views" in compare_fingerprints(prints, fingerprint(views[:5]))


def test_maps_cache_reuses_what_preprocess_left(scene_folder, tmp_path):
    views = load_dataset(str(scene_folder)).views
    config = polar_config("synthetic")
    source = scene_folder / "preprocessed" / "maps"
    entries = maps_entries(views, config, source)
    source.mkdir(parents=True)
    for path in list(entries.values())[:2]:
        path.write_bytes(b"cached")
    try:
        cache = prepare_maps_cache(views, config, tmp_path / "run", None, str(scene_folder))
        assert cache.cached == 2 and cache.copied_from == source and cache.folder == tmp_path / "run" / "maps"
        assert sorted(p.name for p in cache.folder.iterdir()) == sorted(p.name for p in list(entries.values())[:2])
        again = prepare_maps_cache(views, config, tmp_path / "run", None, str(scene_folder))
        assert again.cached == 2 and again.copied_from is None  # nothing left to copy: the run's own cache
        assert again.describe() == f"maps: reused 2 of 6 views from {again.folder}"
        given = prepare_maps_cache(views, config, tmp_path / "run", source.parent, str(scene_folder))
        assert given.given and given.folder == source and "2 of 6 views cached" in given.describe()
    finally:
        for path in source.iterdir():
            path.unlink()
        source.rmdir()
        source.parent.rmdir()


# ------------------------------------------------------------------------------- a run
@pytest.mark.slow
def test_train_mesh_evaluate_a_run(scene_folder, tmp_path):
    out = tmp_path / "run"
    notes: list[str] = []
    request = TrainRequest(str(scene_folder), out, _tiny_train(), polar_config("synthetic", 1 / 6), checkpoint_every=3,
                           labels={"schedule": "cpu", "preset": "synthetic"})
    result = train_run(request, notify=notes.append)
    summary = json.loads((out / "summary.json").read_text())
    assert summary == json.loads(json.dumps(result.summary))
    assert summary["iterations"] == 6 and summary["num_views"] == 6 and summary["dataset_format"] == "polargs"
    assert summary["polar_config"]["densify"]["interval"] == 50 and summary["maps_cache"] == str(out / "maps")
    assert any(line.startswith("maps: computing 6 views") for line in notes)
    with pytest.raises(PolarInputError, match="checkpoint.pt: exists; pass --resume"):
        train_run(request)
    run = load_run(out)
    assert [v.name for v in run.views] == [v.name for v in result.dataset.views]
    model_params = run.model.checkpoint()
    mesh, path = mesh_run(run, MeshSettings(alpha_threshold=0.1, min_cluster=0.0))
    assert path == out / "tsdf_mesh.ply" and json.loads(path.with_suffix(".json").read_text())["views"] == 6
    assert len(mesh.mesh.triangles) > 0
    settings = EvalSettings(gt=scene_folder, normals=True, num_samples=20_000)
    from_disk = evaluate(out, settings)
    in_memory = evaluate(out, settings, run=run)
    assert from_disk == in_memory and from_disk["chamfer"]["chamfer"] > 0
    assert from_disk["occluder"] == str(scene_folder / "mesh.ply") and from_disk["normal_region"] == "object"
    # meshing the run in memory reads nothing back: the same Gaussians give the same mesh
    again = fuse_model(run.model, run.views, MeshSettings(alpha_threshold=0.1, min_cluster=0.0))
    assert len(again.mesh.vertices) == len(mesh.mesh.vertices)
    assert all(torch.equal(a, b) for a, b in zip(model_params.values(), run.model.checkpoint().values())
               if isinstance(a, torch.Tensor))


def test_a_stop_request_ends_with_a_checkpoint_and_the_run_resumes(scene_folder, tmp_path):
    out = tmp_path / "run"
    stop = StopRequest()
    request = TrainRequest(str(scene_folder), out, _tiny_train(), None, checkpoint_every=0)

    def stop_during_training(line: str) -> None:
        pass

    from polargs_plugin.backends.reference.trainer import Trainer

    original = Trainer.step

    def step_then_ask(self):
        logs = original(self)
        if self.iteration == 2:
            stop.request(2)  # SIGINT during iteration 2: training ends after it
        return logs

    Trainer.step = step_then_ask
    try:
        with pytest.raises(TrainingInterrupted) as info:
            train_run(request, notify=stop_during_training, stop=stop)
    finally:
        Trainer.step = original
    assert info.value.resumable and info.value.status == 130
    assert info.value.message("polargs train ... --resume") == "interrupted at iteration 2; resume with: polargs train ... --resume"
    assert (out / "checkpoint.pt").is_file() and not (out / "summary.json").exists()
    resumed = train_run(TrainRequest(str(scene_folder), out, _tiny_train(), None, resume=True))
    assert resumed.summary["iterations"] == 6 and resumed.summary["resumed"] is True


def test_a_refused_run_leaves_no_folder(tmp_path):
    out = tmp_path / "never"
    with pytest.raises(PolarInputError, match="dataset not found"):
        train_run(TrainRequest(str(tmp_path / "missing"), out, _tiny_train()))
    assert not out.exists()


# ------------------------------------------------------------------------------- scenes, adapters
def test_generate_scene_folder_refuses_a_folder_in_use_and_replaces_a_scene(tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    request = SceneRequest(SCENE, views=2, width=16, height=16)
    with pytest.raises(PolarInputError, match="exists and is not empty"):
        generate_scene_folder(request, out)
    with pytest.raises(PolarInputError, match="replaces scene folders only"):
        generate_scene_folder(request, out, overwrite=True)
    (out / "notes.txt").unlink()
    first = generate_scene_folder(request, out)
    second = generate_scene_folder(SceneRequest(SCENE, views=3, width=16, height=16), out, overwrite=True)
    assert first.folder == second.folder == out and len(load_dataset(str(out)).views) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["s"]  # no staging folder left beside it


def test_adapter_inputs_read_the_environment(scene_folder, tmp_path):
    with pytest.raises(PolarInputError, match="^POLARGS_DATA: is not set"):
        adapter_inputs(environ={})
    settings = tmp_path / "polar.json"
    settings.write_text(json.dumps({"losses": {"use_scale": True}}))
    inputs = adapter_inputs(("use_depth_normal", "use_scale"),
                            {"POLARGS_DATA": str(scene_folder), "POLARGS_CONFIG": str(settings)})
    assert len(inputs.views) == 6 and inputs.source == str(scene_folder)
    assert inputs.config.losses.use_scale and not inputs.config.losses.use_depth_normal
    assert inputs.config.densify.patchmatch.lambda_aolp == 0.2  # the real preset by default


def test_importing_the_service_loads_no_heavy_module():
    code = "import sys, polargs_plugin.service; print(sorted(m for m in ('torch', 'numba', 'open3d') if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.stdout.strip() == "[]", result.stderr
