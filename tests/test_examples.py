"""The examples run as documented (tiny sizes): the custom trainer drives PolarHooks end to end,
and the training loop README and the home page show runs as printed, on top-level imports only."""

from __future__ import annotations

import ast
import importlib.util
import math
import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


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
    assert result["num_gaussians"] == 2000 + result["appended"] and result["appended"] >= 0


def _readme_loop(path: Path) -> str:
    """The training loop of a page: its Python block that constructs PolarHooks."""
    blocks = re.findall(r"```python\n(.*?)```", path.read_text(), re.S)
    return next(block for block in blocks if "PolarHooks(" in block)


def _code_lines(text: str) -> list[str]:
    """The statements of ``text`` line by line, comments and indentation stripped."""
    return [line.split("#")[0].strip() for line in text.splitlines() if line.split("#")[0].strip()]


@pytest.mark.parametrize("page", ["README.md", "docs/index.md"])
def test_the_documented_loop_is_the_examples_and_imports_only_from_the_top_level(page: str) -> None:
    loop = _readme_loop(ROOT / page)
    imports = [node for node in ast.walk(ast.parse(loop)) if isinstance(node, (ast.Import, ast.ImportFrom))]
    modules = {node.module if isinstance(node, ast.ImportFrom) else alias.name for node in imports
               for alias in node.names}
    assert modules == {"torch", "polargs_plugin"}, modules
    example = _code_lines((EXAMPLES / "custom_trainer.py").read_text())
    body = [line for line in _code_lines(loop) if not line.startswith(("import ", "from ", "config ="))]
    at = example.index(body[0])  # ValueError: a line of the page is not in the example
    positions = [example.index(line, at) for line in body]
    assert positions == sorted(positions), "the example's loop runs the page's lines in another order"


def test_the_documented_loop_runs_as_printed(monkeypatch, synthetic_views) -> None:
    """README's block executed as it stands, with the example's parameters, renderer and loss as
    the user's. Dense runs on its schedule (PatchMatch on every due iteration); as a run this
    short seeds nothing yet, each due call hands back, besides, three Gaussians at the first
    rows' places, so that the block's append line runs: every parameter gains the rows, with
    zero Adam moments, and the loss stays finite."""
    from polargs_plugin import NewGaussians, PolarConfig, PolarHooks

    example = _load("custom_trainer")
    iterations, start = 20, 500
    short = PolarConfig.synthetic()  # the paper's schedule shrunk to this run, as the example does
    short.densify.start_iter, short.densify.end_iter, short.densify.interval = 8, iterations, 4
    short.losses.depth_normal_from_iter = 10
    monkeypatch.setattr(PolarConfig, "real", classmethod(lambda cls: short))
    dense, calls = PolarHooks.densify, []

    def densify_and_three(self, iteration, view, render_fn, gaussians, render=None):
        found = dense(self, iteration, view, render_fn, gaussians, render=render)
        calls.append(found)
        rows = slice(0, 3)
        return NewGaussians(gaussians.means[rows] + 0.01, gaussians.quats[rows], gaussians.scales[rows],
                            torch.full((3, 3), 0.5), torch.full((3,), 0.5))

    monkeypatch.setattr(PolarHooks, "densify", densify_and_three)
    views = synthetic_views("bumpy_mixed", num_views=6, width=32, height=32)
    params = example.make_params(views, start)
    optimizer = example.make_optimizer(params, 3.0)
    namespace = {
        "views": views, "params": params, "optimizer": optimizer, "iterations": iterations,
        "render_fn": lambda view: example.render_params(params, view),
        "colour_loss": lambda color, image: example.photometric_loss(color.clamp(0, 1), image.clamp(0, 1)),
    }
    exec(compile(_readme_loop(ROOT / "README.md"), "README.md", "exec"), namespace)
    assert len(calls) == 4  # iterations 8, 12, 16, 20
    grown = start + 3 * len(calls)
    assert all(p.shape[0] == grown for p in params.values())
    state = optimizer.state[params["means"]]
    assert state["exp_avg"].shape[0] == grown and torch.isfinite(namespace["loss"]).item()
    assert torch.count_nonzero(state["exp_avg"][-3:]) == 0  # appended at the last iteration, after its step


@pytest.mark.slow
def test_service_example_trains_meshes_and_evaluates(tmp_path) -> None:
    result = _load("service_run").main(["--out", str(tmp_path), "--views", "6", "--size", "32", "--iters", "30"])
    assert set(result) == {"base", "full"}
    for figures in result.values():
        assert 0 < figures["chamfer"] < 1 and 0 < figures["normal_mae_deg"] < 90
