"""``polargs train``: run folder contents, refusal to overwrite, resume."""

import argparse
import json
import math

import pytest
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.backends.reference.trainer import TrainConfig
from polargs_plugin.cli import train as train_cli
from polargs_plugin.types import View


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
    return args.func(args)


@pytest.fixture
def fake_dataset(monkeypatch):
    views = _views()
    monkeypatch.setattr(train_cli, "load_dataset", lambda spec: views)
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
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "summary.json"]


def test_resume_without_checkpoint_and_missing_dataset(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nothing"), "--out", str(tmp_path / "r"), "--no-polar", "--resume"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "nothing"), "--out", str(tmp_path / "r"), "--no-polar", "--quiet"]) == 2
    assert "dataset not found" in capsys.readouterr().err
    assert not (tmp_path / "r" / "summary.json").exists()


def test_help_explains_the_command(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    for word in ("DATASET", "--out", "--preset", "--polar", "--no-polar", "--resume", "--seed", "--iters"):
        assert word in text
