"""``polargs train``: run folder contents, refusal to overwrite, resume, presets and switches,
settings files, the maps cache, interruption, locks and data fingerprints."""

import argparse
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.cli import train as train_cli
from polargs_plugin.service import train as service_train
from polargs_plugin.service.data import Dataset
from polargs_plugin.types import View
from provenance_check import check_provenance


def _views() -> list[View]:
    """Four 16x16 views of one red Gaussian at the origin."""
    size, f = 16, 20.0
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    views = []
    for i in range(4):
        a = 2 * math.pi * i / 4
        eye = torch.tensor([2.5 * math.cos(a), 2.5 * math.sin(a), 0.5], dtype=torch.float64)
        z = -eye / eye.norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        x = x / x.norm()
        R = torch.stack([x, torch.linalg.cross(z, x), z])
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        out = rasterize(
            torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.3), torch.tensor([0.9]),
            torch.tensor([[0.9, 0.1, 0.1]]), K.float(), w2c.float(), size, size,
        )
        stokes = torch.zeros(3, 3, size, size)
        stokes[0] = 2 * out.color.detach()
        views.append(View(name=f"v{i}", K=K, world_to_camera=w2c, stokes=stokes, mask=out.alpha.detach() > 0.2))
    return views


def main(argv: list[str]) -> int:
    """``polargs`` with only the train subcommand registered (the others' imports are slow)."""
    parser = argparse.ArgumentParser(prog="polargs")
    train_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    args._argv = argv
    return args.func(args)


@pytest.fixture
def fake_dataset(monkeypatch):
    views = _views()
    monkeypatch.setattr(service_train, "load_dataset", lambda spec, *a, **k: Dataset(spec, views, "fake"))
    # the CLI plumbing is under test, not the preset: fewer initial points keep it fast
    small = TrainConfig.cpu(num_init_points=100)
    monkeypatch.setattr(TrainConfig, "cpu", classmethod(lambda cls: small))
    return views


def test_train_writes_checkpoint_and_summary_then_resumes(fake_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "fake", "--out", str(run), "--iters", "3", "--no-polar", "--quiet"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 3 and summary["polar"] is False and summary["num_views"] == 4
    assert summary["num_gaussians"] > 0 and math.isfinite(summary["psnr"])
    assert (run / "checkpoint.pt").is_file()
    # refuses to overwrite a run without --resume
    assert main(["train", "fake", "--out", str(run), "--iters", "3", "--no-polar", "--quiet"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["train", "fake", "--out", str(run), "--iters", "5", "--no-polar", "--quiet", "--resume"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 5 and summary["resumed"] is True
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "fingerprint.json", "summary.json"]


def test_train_records_provenance(fake_dataset, tmp_path):
    """summary.json says which libraries, commit, command line, machine and threads made the run."""
    run = tmp_path / "run"
    assert main(["train", "fake", "--out", str(run), "--iters", "2", "--no-polar", "--quiet"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    check_provenance(summary["provenance"], command=f"polargs train fake --out {run} --iters 2 --no-polar --quiet",
                     threads=torch.get_num_threads())


def test_resume_without_checkpoint_and_missing_dataset(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nothing"), "--out", str(tmp_path / "r"), "--no-polar", "--resume"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "nothing"), "--out", str(tmp_path / "r"), "--no-polar", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "dataset not found" in err and str(tmp_path / "nothing") in err
    assert not (tmp_path / "r").exists()  # nothing half-written: the folder it created is gone again


def test_help_explains_the_command(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    for word in ("DATASET", "--out", "--preset", "--schedule", "--polar", "--no-polar", "--resume", "--seed", "--iters",
                 "--config", "--maps-cache", "--no-pc", "--no-dense", "--no-ref-loss", "--no-normal-loss",
                 "--no-depth-normal-loss", "--no-scale-loss", "--pattern", "--bit-depth", "--sfm", "--checkpoint-every"):
        assert word in text


# ------------------------------------------------------------------ presets, switches, settings
def _summary(run):
    return json.loads((run / "summary.json").read_text())


@pytest.mark.slow
def test_preset_real_and_schedule_are_separate_axes(fake_dataset, tmp_path, capsys):
    run = tmp_path / "real"
    assert main(["train", "fake", "--out", str(run), "--iters", "2", "--quiet", "--preset", "real", "--no-dense"]) == 0
    summary = _summary(run)
    polar = summary["polar_config"]
    assert summary["preset"] == "real" and summary["schedule"] == "cpu"
    assert polar["densify"]["patchmatch"]["lambda_aolp"] == 0.2 and polar["losses"]["alpha_normal"] == 0.1
    assert polar["densify"]["enabled"] is False and summary["switches"] == ["--no-dense"]
    # the cpu schedule scales PolarGS' own schedule too, by half (Dense from iteration 1000 x 0.5)
    assert polar["densify"]["start_iter"] == 500 and polar["losses"]["depth_normal_from_iter"] == 3500
    # the old --preset cpu still selects the schedule, with a note
    legacy = tmp_path / "legacy"
    assert main(["train", "fake", "--out", str(legacy), "--iters", "2", "--quiet", "--preset", "cpu", "--no-polar"]) == 0
    assert "--schedule cpu" in capsys.readouterr().err
    assert _summary(legacy)["schedule"] == "cpu" and _summary(legacy)["polar_config"] is None


def test_all_ablation_switches_reach_the_polar_config(fake_dataset, tmp_path):
    run = tmp_path / "run"
    argv = ["train", "fake", "--out", str(run), "--iters", "1", "--quiet", "--no-pc", "--no-dense", "--no-ref-loss",
            "--no-normal-loss", "--no-depth-normal-loss", "--no-scale-loss"]
    assert main(argv) == 0
    polar = _summary(run)["polar_config"]
    assert polar["correction"]["enabled"] is False and polar["densify"]["enabled"] is False
    assert not any(polar["losses"][k] for k in ("use_ref", "use_normal", "use_depth_normal", "use_scale"))


def test_switches_without_hooks_are_refused(fake_dataset, tmp_path, capsys):
    assert main(["train", "fake", "--out", str(tmp_path / "r"), "--no-polar", "--no-pc"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --no-pc") and err.count("\n") == 1
    assert not (tmp_path / "r").exists()


def test_config_file_sets_any_field_and_unknown_keys_name_key_and_file(fake_dataset, tmp_path, capsys):
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"polar": {"losses": {"alpha_normal": 0.3}, "densify": {"enabled": False}},
                                    "train": {"density": {"max_gaussians": 321}}}))
    run = tmp_path / "run"
    assert main(["train", "fake", "--out", str(run), "--iters", "1", "--quiet", "--config", str(settings)]) == 0
    summary = _summary(run)
    assert summary["polar_config"]["losses"]["alpha_normal"] == 0.3
    assert summary["config"]["density"]["max_gaussians"] == 321 and summary["config_file"] == str(settings)
    for content, key in (({"polar": {"losses": {"alpha_nrmal": 1}}}, "polar.losses: unknown setting 'alpha_nrmal'"),
                         ({"train": {"iterationz": 5}}, "train: unknown setting 'iterationz'"),
                         # a setting that moved says where to
                         ({"train": {"ssim_weight": 0.2}}, "train: setting 'ssim_weight' is no longer here: the colour "
                                                           "loss's SSIM share is PolarConfig's losses.ssim_weight"),
                         ({"polar": {"refractive_index": 1.5}}, "polar: setting 'refractive_index' is no longer here"),
                         ({"correction": {}}, "correction")):
        settings.write_text(json.dumps(content))
        out = tmp_path / f"bad-{key}"
        assert main(["train", "fake", "--out", str(out), "--config", str(settings)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {settings}: ") and key in err and err.count("\n") == 1
        assert not out.exists()
    settings.write_text(json.dumps({"train": {"iterations": "many"}}))
    assert main(["train", "fake", "--out", str(tmp_path / "t"), "--config", str(settings)]) == 2
    assert "train.iterations: expected an integer" in capsys.readouterr().err
    # Checked against the field's annotation: an optional threshold takes null, a pair takes two numbers.
    for content, message in (({"polar": {"correction": {"specular_dolp": [0.3]}}},
                              "polar.correction.specular_dolp: expected a list of 2 (a number, a number)"),
                             ({"polar": {"correction": {"rho_d": "high"}}}, "polar.correction.rho_d: expected a number or null")):
        settings.write_text(json.dumps(content))
        assert main(["train", "fake", "--out", str(tmp_path / "t"), "--config", str(settings)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    settings.write_text(json.dumps({"polar": {"densify": {"seed_max_plane_deviation": None}}}))
    assert main(["train", "fake", "--out", str(tmp_path / "n"), "--iters", "1", "--quiet", "--config", str(settings)]) == 0
    assert _summary(tmp_path / "n")["polar_config"]["densify"]["seed_max_plane_deviation"] is None
    settings.write_text("{not json")
    assert main(["train", "fake", "--out", str(tmp_path / "t"), "--config", str(settings)]) == 2
    assert f"{settings}: not valid JSON" in capsys.readouterr().err


# ------------------------------------------------------------------ maps cache
@pytest.mark.slow
def test_train_reuses_cached_maps_and_says_so(fake_dataset, tmp_path, capsys):
    first = tmp_path / "first"
    assert main(["train", "fake", "--out", str(first), "--iters", "1", "--quiet", "--no-dense"]) == 0
    assert "maps: computing 4 views" in capsys.readouterr().out
    entries = sorted((first / "maps").glob("*.pt"))
    assert len(entries) == 4
    stamps = [p.stat().st_mtime_ns for p in entries]
    # an explicit cache (here the first run's folder, which holds maps/) is used in place
    second = tmp_path / "second"
    assert main(["train", "fake", "--out", str(second), "--iters", "1", "--quiet", "--no-dense",
                 "--maps-cache", str(first)]) == 0
    assert f"maps: 4 of 4 views cached in {first / 'maps'}" in capsys.readouterr().out
    assert [p.stat().st_mtime_ns for p in entries] == stamps and not (second / "maps").exists()
    assert _summary(second)["maps_cache"] == str(first / "maps")
    # the default: what `polargs preprocess DATASET` left in DATASET/preprocessed/maps is reused
    dataset = tmp_path / "dataset"
    shutil.copytree(first / "maps", dataset / "preprocessed" / "maps")
    third = tmp_path / "third"
    assert main(["train", str(dataset), "--out", str(third), "--iters", "1", "--quiet", "--no-dense"]) == 0
    out = capsys.readouterr().out
    assert f"reused 4 of 4 views from {dataset / 'preprocessed' / 'maps'}" in out
    assert len(list((third / "maps").glob("*.pt"))) == 4


# ------------------------------------------------------------------ no lost runs
STEP = Trainer.step


def _kill_at(monkeypatch, iteration: int, signum: int) -> None:
    step = STEP

    def step_and_signal(self):
        logs = step(self)
        if self.iteration == iteration:
            os.kill(os.getpid(), signum)
        return logs

    monkeypatch.setattr(Trainer, "step", step_and_signal)


@pytest.mark.slow
@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupt_writes_a_final_checkpoint_and_says_how_to_resume(fake_dataset, tmp_path, capsys, monkeypatch, signum, status):
    run = tmp_path / "run"
    _kill_at(monkeypatch, 3, signum)
    argv = ["train", "fake", "--out", str(run), "--iters", "8", "--no-polar", "--quiet", "--checkpoint-every", "0"]
    assert main(argv) == status
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith("interrupted at iteration 3; resume with: polargs train fake --out") and last.endswith("--resume")
    assert "Traceback" not in err
    assert not (run / "summary.json").exists() and not (run / "train.lock").exists()
    data = torch.load(run / "checkpoint.pt", weights_only=True)
    assert data["iteration"] == 3
    monkeypatch.setattr(Trainer, "step", STEP)
    assert main(argv + ["--resume"]) == 0
    assert _summary(run)["iterations"] == 8


def test_periodic_checkpoints_by_default(fake_dataset, tmp_path, monkeypatch):
    saved = []
    save = Trainer.save_checkpoint
    monkeypatch.setattr(Trainer, "save_checkpoint", lambda self, path: saved.append(self.iteration) or save(self, path))
    run = tmp_path / "run"
    assert main(["train", "fake", "--out", str(run), "--iters", "20", "--no-polar", "--quiet"]) == 0
    assert _summary(run)["checkpoint_every"] == 2  # 10 % of the run
    assert saved[:10] == [2, 4, 6, 8, 10, 12, 14, 16, 18, 20]


def test_unwritable_out_is_found_before_training(fake_dataset, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(Trainer, "train", lambda *a, **k: pytest.fail("trained into an unwritable folder"))
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["train", "fake", "--out", str(blocker / "run"), "--no-polar", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {blocker / 'run'}: cannot write there") and err.count("\n") == 1
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "readonly"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            assert main(["train", "fake", "--out", str(locked / "run"), "--no-polar", "--quiet"]) == 2
            assert str(locked / "run") in capsys.readouterr().err
        finally:
            locked.chmod(0o700)


def _write_lock(run, pid, host=None, started=None):
    run.mkdir(parents=True, exist_ok=True)
    (run / "train.lock").write_text(json.dumps({"pid": pid, "host": host or socket.gethostname(),
                                                "started": started or time.time(), "command": "polargs train other"}))


def test_second_training_into_a_locked_folder_is_refused(fake_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _write_lock(run, holder.pid)
        assert main(["train", "fake", "--out", str(run), "--no-polar", "--quiet", "--iters", "1"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {run / 'train.lock'}: the folder is in use by pid {holder.pid}") and err.count("\n") == 1
        assert not (run / "checkpoint.pt").exists() and (run / "train.lock").exists()
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: its lock is stale and taken over, with a note
    assert main(["train", "fake", "--out", str(run), "--no-polar", "--quiet", "--iters", "1"]) == 0
    assert f"took over the stale lock of pid {holder.pid}" in capsys.readouterr().err
    assert not (run / "train.lock").exists()


def test_resume_on_other_data_with_the_same_names_is_refused(fake_dataset, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    assert main(["train", "fake", "--out", str(run), "--iters", "2", "--no-polar", "--quiet"]) == 0
    other = [View(v.name, v.K, v.world_to_camera, v.stokes.roll(5, -1), v.mask.roll(5, -1)) for v in fake_dataset]
    monkeypatch.setattr(service_train, "load_dataset", lambda spec, *a, **k: Dataset(spec, other, "fake"))
    assert main(["train", "fake", "--out", str(run), "--iters", "4", "--no-polar", "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {run / 'fingerprint.json'}: --resume on other data") and "images of 4 of 4 views" in err
    moved = [View(v.name, v.K, v.world_to_camera.clone(),
                  v.stokes, v.mask) for v in fake_dataset]
    moved[0].world_to_camera[0, 3] += 0.5
    monkeypatch.setattr(service_train, "load_dataset", lambda spec, *a, **k: Dataset(spec, moved, "fake"))
    assert main(["train", "fake", "--out", str(run), "--iters", "4", "--no-polar", "--quiet", "--resume"]) == 2
    assert "cameras of 1 of 4 views (v0)" in capsys.readouterr().err
    assert _summary(run)["iterations"] == 2  # untouched
