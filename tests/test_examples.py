"""The examples run as documented (tiny sizes): the custom trainer drives PolarHooks end to end."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_custom_trainer_example_trains_with_the_hooks() -> None:
    source = (EXAMPLES / "custom_trainer.py").read_text()
    assert len(source.splitlines()) < 150
    result = _load("custom_trainer").main(["--iterations", "40", "--size", "32", "--views", "6"])
    assert math.isfinite(result["loss"])
    assert result["num_gaussians"] == 2000 + result["appended"]


@pytest.mark.slow
def test_service_example_trains_meshes_and_evaluates(tmp_path) -> None:
    result = _load("service_run").main(["--out", str(tmp_path), "--views", "6", "--size", "32", "--iters", "30"])
    assert set(result) == {"base", "full"}
    for figures in result.values():
        assert 0 < figures["chamfer"] < 1 and 0 < figures["normal_mae_deg"] < 90
