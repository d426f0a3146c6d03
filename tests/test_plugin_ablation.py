"""The plug-in ablation (``polargs ablate --trainer``): the shrunk upstream schedule, the scaled
literals, the patched run's PolarGS settings, and the placeholder graphdeco trainer (tests/data/
trainers/) trained alone and with PolarGS, read back from its PLY, meshed and evaluated."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

from polargs_plugin.config import PolarConfig
from polargs_plugin.dryrun.trainers import TRAINERS, UPSTREAM_SCHEDULE, shrink_literals, shrunk_schedule_arguments
from polargs_plugin.io import PolarInputError
from polargs_plugin.kit.patching import main as patch_main
from polargs_plugin.service.plugin import PluginRequest, plugin_ablation, plugin_settings, plugin_table

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "data" / "trainers"


def _options(arguments: list[str]) -> dict[str, str]:
    return {flag: value for flag, value in zip(arguments[::2], arguments[1::2]) if flag.startswith("--")}


def test_the_shrunk_schedule_scales_every_upstream_count() -> None:
    options = _options(shrunk_schedule_arguments(TRAINERS["gof"], 0.1))
    for name, value in UPSTREAM_SCHEDULE.items():
        assert options[f"--{name}"] == str(round(value * 0.1))
    assert int(options["--opacity_reset_interval"]) > 3000  # no reset
    assert options["--position_lr_max_steps"] == options["--save_iterations"] == "3000"
    assert options["--distortion_from_iter"] == options["--depth_normal_from_iter"] == "1500"  # GOF's 15000
    assert int(options["--test_iterations"]) > 3000  # no test renders
    tiny = _options(shrunk_schedule_arguments(TRAINERS["graphdeco-2023"], 1e-4))
    assert tiny["--densification_interval"] == "1" and tiny["--densify_from_iter"] == "1"  # never 0
    with pytest.raises(ValueError, match="graphdeco family"):
        shrunk_schedule_arguments(TRAINERS["gsplat"], 0.5)


def test_literal_iterations_are_scaled_and_longer_numbers_left_alone() -> None:
    text = "a = 1 if iteration > 7000 else 0\nb = 1 if iteration > 3000 else 0\nc = iteration > 30000\n"
    shrunk, missing = shrink_literals(TRAINERS["2dgs"], text, 1 / 6)
    assert shrunk == "a = 1 if iteration > 1167 else 0\nb = 1 if iteration > 500 else 0\nc = iteration > 30000\n"
    assert missing == []
    assert shrink_literals(TRAINERS["2dgs"], "nothing here\n", 0.5) == ("nothing here\n", list(TRAINERS["2dgs"].hard_coded))


def test_the_patched_runs_settings_are_the_cpu_presets_schedule() -> None:
    settings = plugin_settings(1 / 6)["polar"]
    preset = PolarConfig.cpu_demo()  # the CPU preset: vanilla x 1/6, PolarGS x 1/2
    assert settings["densify"] == {"start_iter": preset.densify.start_iter, "end_iter": preset.densify.end_iter,
                                   "interval": preset.densify.interval}
    assert settings["losses"]["depth_normal_from_iter"] == preset.losses.depth_normal_from_iter
    PolarConfig.synthetic().update(settings)  # every key is a field the adapters accept


def test_the_table_gives_the_change_against_the_trainer_alone() -> None:
    records = [{"scene": "s", "variant": "alone", "chamfer": 0.02, "chamfer_visible": 0.04, "normal_mae_deg": 20.0,
                "gaussians": 100, "dense_rows_final": None},
               {"scene": "s", "variant": "polargs", "chamfer": 0.015, "chamfer_visible": 0.05, "normal_mae_deg": 15.0,
                "gaussians": 120, "dense_rows_final": 7},
               {"scene": "t", "variant": "alone", "error": "did not finish"}]
    rows = {tuple(c.strip() for c in line.strip("|").split("|")) for line in plugin_table(records)}
    assert ("s", "Chamfer", "0.02", "0.015", "-25.0 %") in rows
    assert ("s", "visible Chamfer", "0.04", "0.05", "+25.0 %") in rows
    assert ("s", "Gaussians", "100", "120", "+20.0 %") in rows
    assert ("s", "Dense rows at the end", "n/a", "7", "") in rows
    assert [row for row in rows if row[0] == "t"] == [("t", "failed", "alone: did not finish", "", "")]


def _patched_checkout(tmp_path: Path) -> Path:
    import importlib.util

    checkout = tmp_path / "checkout"
    shutil.copytree(FIXTURES / "inria_support", checkout, ignore=shutil.ignore_patterns("README.md"))
    shutil.copy(FIXTURES / "graphdeco_2024_train.py", checkout / "train.py")
    spec = importlib.util.spec_from_file_location("_graphdeco_patch", ROOT / "adapters" / "graphdeco" / "patch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert patch_main([str(checkout)], module.ANCHORS, "test") == 0
    return checkout


def test_refusals_name_the_option(tmp_path: Path) -> None:
    with pytest.raises(PolarInputError, match="--trainer.*graphdeco family"):
        plugin_ablation(PluginRequest(trainer="gsplat", checkout=tmp_path, out=tmp_path / "out"))
    with pytest.raises(PolarInputError, match="--variants"):
        plugin_ablation(PluginRequest(trainer="graphdeco", checkout=tmp_path, out=tmp_path / "out", variants=("full",)))
    with pytest.raises(PolarInputError, match="--factor"):
        plugin_ablation(PluginRequest(trainer="graphdeco", checkout=tmp_path, out=tmp_path / "out", factor=2.0))
    with pytest.raises(PolarInputError, match="--scenes.*unknown synthetic scene 'nope'"):
        plugin_ablation(PluginRequest(trainer="graphdeco", checkout=_patched_checkout(tmp_path / "p"), out=tmp_path / "out",
                                      scenes=("nope",)))
    (tmp_path / "train.py").write_text("print('unpatched')\n")
    with pytest.raises(PolarInputError, match="is not patched"):
        plugin_ablation(PluginRequest(trainer="graphdeco", checkout=tmp_path, out=tmp_path / "out"))


@pytest.mark.slow
def test_the_placeholder_trainer_alone_and_with_polargs(tmp_path: Path) -> None:
    checkout = _patched_checkout(tmp_path)
    before = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    # 40 iterations; the tiny factor's densification every iteration is replaced by every 10
    request = PluginRequest(trainer="graphdeco", checkout=checkout, out=tmp_path / "out", scenes=("bumpy_mixed",),
                            factor=40 / 30000, views=8, width=32, height=24, eval_samples=20000,
                            train_arguments=("--densify_from_iter", "10", "--densification_interval", "10"),
                            polar_overrides={"densify": {"interval": 15}}, command="polargs ablate --trainer ...")
    records = plugin_ablation(request)
    assert [(r["scene"], r["variant"]) for r in records] == [("bumpy_mixed", "alone"), ("bumpy_mixed", "polargs")]
    for record in records:
        assert "error" not in record, record
        assert record["iterations"] == 40
        assert all(math.isfinite(record[k]) and record[k] > 0 for k in ("chamfer", "chamfer_visible", "normal_mae_deg"))
        # the model evaluated is the one the trainer saved: its vertex count is the PLY header's
        header = Path(record["ply"]).read_bytes().split(b"end_header")[0].decode()
        assert f"element vertex {record['gaussians']}" in header
        report = json.loads((tmp_path / "out" / "runs" / f"bumpy_mixed__{record['variant']}" / "report-train.json").read_text())
        assert report["gaussians_final"] == record["gaussians"]
    assert records[0]["dense_rows_final"] is None and records[1]["dense_rows_final"] is not None
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["cells"] == records and results["provenance"]["command"] == request.command
    assert "| bumpy_mixed | Chamfer |" in (tmp_path / "out" / "results.md").read_text()
    # resumable: done cells are read back, not run again
    done = tmp_path / "out" / "runs" / "bumpy_mixed__alone" / "cell.json"
    stamp = done.stat().st_mtime_ns
    assert plugin_ablation(request) == records and done.stat().st_mtime_ns == stamp
    after = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    assert after == before  # nothing written into the checkout


@pytest.mark.parametrize(("arguments", "named"), [
    (["--trainer", "2dgs"], "--trainer: expected NAME=CHECKOUT"),
    (["--trainer", "2dgs=x", "--variants", "base,full"], "--variants: choose among alone, polargs"),
    (["--trainer", "2dgs=x", "--seeds", "0,1"], "--seeds: does not apply to --trainer"),
    (["--trainer", "gsplat=x"], "--trainer: gsplat"),
])
def test_the_command_names_a_bad_option(arguments: list[str], named: str, tmp_path: Path, capsys) -> None:
    from polargs_plugin.cli import main

    assert main(["ablate", *arguments, "--out", str(tmp_path / "out")]) == 2
    assert named in capsys.readouterr().err
