"""The anchor-line patch scripts (adapters/<name>/patch.py) and their engine (kit/patching.py).

The trainers patched here are the placeholder files under tests/data/trainers/ (same statement
shape as the upstream loops, none of their code) and variants made from them in the tests.
"""

from __future__ import annotations

import importlib.util
import os
import re
import stat
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import pytest

from polargs_plugin.kit import patching
from polargs_plugin.kit.patching import MARKER, Anchor, PatchError

ROOT = Path(__file__).resolve().parents[1]
TRAINERS = Path(__file__).resolve().parent / "data" / "trainers"


def load_script(adapter: str) -> ModuleType:
    """adapters/<adapter>/patch.py as a module (not run as __main__)."""
    path = ROOT / "adapters" / adapter / "patch.py"
    spec = importlib.util.spec_from_file_location(f"_polargs_patch_{adapter}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@dataclass(frozen=True)
class Case:
    """A trainer file and what patching it must insert, keyed by the anchor line it goes next to."""

    adapter: str
    fixture: str
    attach_args: str
    import_after: str


CASES = [
    Case(
        "graphdeco",
        "graphdeco_2023_train.py",
        "scene, gaussians, pipe, render",
        "from argparse import ArgumentParser",
    ),
    Case(
        "graphdeco",
        "graphdeco_2024_train.py",
        "scene, gaussians, pipe, render, use_trained_exp=dataset.train_test_exp, separate_sh=SPARSE_ADAM_AVAILABLE",
        "from argparse import ArgumentParser",
    ),
    Case(
        "gof",
        "gof_5245b20_train.py",
        "scene, gaussians, pipe, render, kernel_size=dataset.kernel_size",
        "from utils.depth_utils import depth_to_normal",
    ),
    Case(
        "pgsr",
        "pgsr_de24f1a_train.py",
        "scene, gaussians, pipe, render, app_model=app_model",
        "import torch.nn.functional as F",
    ),
]
IDS = [c.fixture.removesuffix("_train.py") for c in CASES]


@dataclass(frozen=True)
class Names:
    """Local names of a trainer file (renamed in the variants)."""

    scene: str = "scene"
    gaussians: str = "gaussians"
    render: str = "render"
    render_pkg: str = "render_pkg"
    camera: str = "viewpoint_cam"
    loss: str = "loss"
    iteration: str = "iteration"


def expected(case: Case, names: Names = Names(), unit: str = "    ") -> list[tuple[str, str, str]]:
    """(inserted line, neighbour line, 'above'|'below' where the neighbour sits), indentation included."""
    n = names
    attach = case.attach_args
    for old, new in (("scene", n.scene), ("gaussians", n.gaussians), ("render", n.render)):
        attach = re.sub(rf"\b{old}\b", new, attach)
    return [
        (f"import polargs_adapters.{case.adapter} as polargs_{case.adapter}", case.import_after, "above"),
        (f"{unit}polar = polargs_{case.adapter}.attach({attach})", f"{unit}for {n.iteration} in range(", "below"),
        (
            f"{unit * 2}{n.loss} = {n.loss} + polar.loss({n.iteration}, {n.camera}, {n.render_pkg})",
            f"{unit * 2}{n.loss}.backward()",
            "below",
        ),
        (
            f"{unit * 3}polar.densify({n.iteration}, {n.camera}, {n.render_pkg})",
            f"{unit * 3}if ({n.iteration} in checkpoint_iterations):",
            "below",
        ),
    ]


def assert_inserted(patched: str, case: Case, names: Names = Names(), unit: str = "    ") -> None:
    """Exactly the four expected marked lines, each right next to its anchor line."""
    lines = patched.splitlines()
    marked = [line for line in lines if line.endswith(MARKER)]
    assert len(marked) == 4, marked
    for text, neighbour, side in expected(case, names, unit):
        full = f"{text}  {MARKER}"
        assert lines.count(full) == 1, (full, marked)
        i = lines.index(full)
        other = lines[i + 1] if side == "below" else lines[i - 1]
        assert other.startswith(neighbour), (full, other)
    compile(patched, "train.py", "exec")


def copy_fixture(tmp_path: Path, fixture: str, text: str | None = None, mode: int = 0o640) -> Path:
    """A checkout folder holding the fixture (or ``text``) as train.py."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    target = checkout / "train.py"
    if text is None:
        target.write_bytes((TRAINERS / fixture).read_bytes())
    else:
        target.write_bytes(text.encode())
    target.chmod(mode)
    return checkout


def fixture_text(case: Case) -> str:
    return (TRAINERS / case.fixture).read_text()


def run_main(case: Case, *argv: str) -> int:
    return patching.main(list(argv), load_script(case.adapter).ANCHORS, "test")


# ----------------------------------------------------------------------------------------------
# patch / patch again / revert / dry run on each trainer shape


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_patch_inserts_hooks_at_their_anchors(case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    checkout = copy_fixture(tmp_path, case.fixture)
    original = (checkout / "train.py").read_bytes()
    assert run_main(case, str(checkout)) == 0
    patched = (checkout / "train.py").read_text()
    assert_inserted(patched, case)
    assert patching.strip_marked(patched).encode() == original
    assert (checkout / "train.py.polargs-orig").read_bytes() == original
    assert "4 lines inserted" in capsys.readouterr().out


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_patch_again_changes_nothing_and_revert_restores_bytes(
    case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    checkout = copy_fixture(tmp_path, case.fixture, mode=0o751)
    target = checkout / "train.py"
    original = target.read_bytes()
    assert run_main(case, str(checkout)) == 0
    once = target.read_bytes()
    assert run_main(case, str(checkout)) == 0
    assert target.read_bytes() == once
    assert "already patched, no change" in capsys.readouterr().out
    assert stat.S_IMODE(target.stat().st_mode) == 0o751
    assert stat.S_IMODE((checkout / "train.py.polargs-orig").stat().st_mode) == 0o751
    assert run_main(case, str(checkout), "--revert") == 0
    assert target.read_bytes() == original
    assert stat.S_IMODE(target.stat().st_mode) == 0o751
    assert sorted(p.name for p in checkout.iterdir()) == ["train.py"]


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_dry_run_prints_diff_and_writes_nothing(case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    checkout = copy_fixture(tmp_path, case.fixture)
    original = (checkout / "train.py").read_bytes()
    assert run_main(case, str(checkout), "--dry-run") == 0
    out = capsys.readouterr().out
    assert out.startswith("---") and "\n+++ " in out and "\n@@ " in out
    added = [line[1:] for line in out.splitlines() if line.startswith("+") and not line.startswith("+++")]
    assert len(added) == 4 and all(line.endswith(MARKER) for line in added)
    assert not any(line.startswith("-") and not line.startswith("---") for line in out.splitlines())
    assert (checkout / "train.py").read_bytes() == original
    assert sorted(p.name for p in checkout.iterdir()) == ["train.py"]


# ----------------------------------------------------------------------------------------------
# unrecognised loops: exit 2, one line naming file and anchor, nothing written

MISSING = [
    (CASES[0], r"^ *loss\.backward\(\)\n", "loss backward"),
    (CASES[1], r"^ *render_pkg = render\(viewpoint_cam.*\n", "render call"),
    (CASES[2], r"^ *if \(iteration in checkpoint_iterations\):\n", "checkpoint block"),
    (CASES[3], r"^    for iteration in range\(first_iter, opt\.iterations \+ 1\):\n", "training loop"),
    (CASES[3], r"^ *scene = Scene\(dataset, gaussians\)\n", "Scene"),
    (CASES[0], r"^from gaussian_renderer import render, network_gui\n", "render import"),
]


@pytest.mark.parametrize(("case", "pattern", "anchor"), MISSING, ids=[f"{c.adapter}-{a}" for c, _, a in MISSING])
def test_missing_anchor_is_refused(
    case: Case, pattern: str, anchor: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text, count = re.subn(pattern, "", fixture_text(case), flags=re.M)
    assert count == 1
    checkout = copy_fixture(tmp_path, case.fixture, text)
    target = checkout / "train.py"
    assert run_main(case, str(checkout)) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err
    assert err.count("\n") == 1
    assert err.startswith(f"error: {target}: anchor '{anchor}' not found (")
    assert err.rstrip().endswith(")")
    assert target.read_text() == text
    assert sorted(p.name for p in checkout.iterdir()) == ["train.py"]


def test_anchor_matching_twice_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    case = CASES[1]
    text = fixture_text(case).replace("        loss.backward()\n", "        loss.backward()\n        loss.backward()\n")
    checkout = copy_fixture(tmp_path, case.fixture, text)
    assert run_main(case, str(checkout)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    target = re.escape(str(checkout / "train.py"))
    assert re.match(rf"error: {target}: anchor 'loss backward' matches 2 lines \(L\d+, L\d+\)", err)
    assert (checkout / "train.py").read_text() == text


def test_missing_file_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run_main(CASES[0], str(tmp_path)) == 2
    assert capsys.readouterr().err == f"error: {tmp_path}: no train.py in {tmp_path}; pass the trainer's checkout or the file itself\n"
    assert run_main(CASES[0], str(tmp_path / "absent.py")) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'absent.py'}: no such file or folder\n"


# ----------------------------------------------------------------------------------------------
# robustness: renamed locals, whitespace, re-indentation, line endings

RENAMES = Names(scene="sc", gaussians="gs", render="rend", render_pkg="out", camera="cam", loss="total", iteration="it")


def renamed(text: str) -> str:
    """The fixture with its locals renamed and render imported under another name."""
    text = text.replace("import render, network_gui", "import render as rend, network_gui")
    text = re.sub(r"\brender\(", "rend(", text)
    for old, new in (
        ("render_pkg", "out"),
        ("viewpoint_cam", "cam"),
        ("gaussians", "gs"),
        ("scene", "sc"),
        ("loss", "total"),
        ("iteration", "it"),
    ):
        text = re.sub(rf"\b{old}\b", new, text)
    return text


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_renamed_locals_are_reused(case: Case, tmp_path: Path) -> None:
    text = renamed(fixture_text(case))
    checkout = copy_fixture(tmp_path, case.fixture, text)
    assert run_main(case, str(checkout)) == 0
    patched = (checkout / "train.py").read_text()
    assert_inserted(patched, case, RENAMES)
    assert patching.strip_marked(patched) == text


def respaced(text: str) -> str:
    """Whitespace changes: spaced-out calls, a call split over lines, trailing blanks, comments."""
    text = text.replace(
        "render_pkg = render(viewpoint_cam, gaussians, pipe, ",
        "render_pkg  =  render( viewpoint_cam ,gaussians ,\n                pipe ,  ",
    )
    text = text.replace("        loss.backward()\n", "        loss.backward( )   # step\n")
    text = text.replace("        with torch.no_grad():\n", "        with torch.no_grad() :  \n")
    text = text.replace("    scene = Scene(dataset, gaussians)", "    scene=Scene( dataset,gaussians )")
    return text


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_changed_whitespace_is_tolerated(case: Case, tmp_path: Path) -> None:
    text = respaced(fixture_text(case))
    assert text != fixture_text(case)
    checkout = copy_fixture(tmp_path, case.fixture, text)
    assert run_main(case, str(checkout)) == 0
    patched = (checkout / "train.py").read_text()
    lines = patched.splitlines()
    assert sum(line.endswith(MARKER) for line in lines) == 4
    i = lines.index("        loss.backward( )   # step")
    assert lines[i - 1] == f"        loss = loss + polar.loss(iteration, viewpoint_cam, render_pkg)  {MARKER}"
    compile(patched, "train.py", "exec")
    assert patching.strip_marked(patched) == text


@pytest.mark.parametrize(("unit", "name"), [("  ", "two-spaces"), ("\t", "tabs")])
@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_indentation_comes_from_the_anchor_line(case: Case, unit: str, name: str, tmp_path: Path) -> None:
    def reindent(match: re.Match[str]) -> str:
        return unit * (len(match.group(0)) // 4) + " " * (len(match.group(0)) % 4)

    text = re.sub(r"^ +", reindent, fixture_text(case), flags=re.M)
    compile(text, "reindented.py", "exec")
    checkout = copy_fixture(tmp_path, case.fixture, text)
    assert run_main(case, str(checkout)) == 0
    assert_inserted((checkout / "train.py").read_text(), case, unit=unit)


def test_crlf_line_endings_are_kept(tmp_path: Path) -> None:
    case = CASES[0]
    text = fixture_text(case).replace("\n", "\r\n")
    checkout = copy_fixture(tmp_path, case.fixture, text)
    target = checkout / "train.py"
    original = target.read_bytes()
    assert run_main(case, str(checkout)) == 0
    data = target.read_bytes()
    assert data.count(b"\r\n") == data.count(b"\n") == original.count(b"\n") + 4
    assert run_main(case, str(checkout), "--revert") == 0
    assert target.read_bytes() == original


# ----------------------------------------------------------------------------------------------
# backup / revert edge cases, atomic writes


def test_revert_refuses_a_file_edited_after_patching(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    case = CASES[0]
    checkout = copy_fixture(tmp_path, case.fixture)
    target = checkout / "train.py"
    original = target.read_bytes()
    assert run_main(case, str(checkout)) == 0
    edited = target.read_text() + "# my own change\n"
    target.write_text(edited)
    assert run_main(case, str(checkout), "--revert") == 2
    assert "changed since it was patched" in capsys.readouterr().err
    assert target.read_text() == edited
    assert run_main(case, str(checkout), "--revert", "--force") == 0
    assert target.read_bytes() == original


def test_revert_without_backup_removes_marked_lines(tmp_path: Path) -> None:
    case = CASES[2]
    checkout = copy_fixture(tmp_path, case.fixture)
    target = checkout / "train.py"
    original = target.read_bytes()
    assert run_main(case, str(checkout)) == 0
    (checkout / "train.py.polargs-orig").unlink()
    assert run_main(case, str(checkout), "--revert", "--dry-run") == 0
    assert MARKER in target.read_text()
    assert run_main(case, str(checkout), "--revert") == 0
    assert target.read_bytes() == original
    assert run_main(case, str(checkout), "--revert") == 0  # nothing left to revert: not an error
    assert target.read_bytes() == original


def test_repatching_an_updated_file_refreshes_the_backup(tmp_path: Path) -> None:
    case = CASES[1]
    checkout = copy_fixture(tmp_path, case.fixture)
    target = checkout / "train.py"
    assert run_main(case, str(checkout)) == 0
    updated = target.read_text().replace("    first_iter = 0\n", "    first_iter = 0\n    extra_setup = None\n")
    target.write_text(updated)
    assert run_main(case, str(checkout)) == 0
    assert (checkout / "train.py.polargs-orig").read_text() == patching.strip_marked(updated)
    assert_inserted(target.read_text(), case)
    assert run_main(case, str(checkout), "--revert") == 0
    assert target.read_text() == patching.strip_marked(updated)


def test_failed_write_leaves_the_file_and_no_temporary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "train.py"
    target.write_bytes(b"x = 1\n")

    def broken(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(patching.os, "replace", broken)
    with pytest.raises(OSError):
        patching.write_atomic(target, b"y = 2\n")
    assert target.read_bytes() == b"x = 1\n"
    assert [p.name for p in tmp_path.iterdir()] == ["train.py"]


# ----------------------------------------------------------------------------------------------
# the engine on its own


def test_logical_lines_join_continuations_and_drop_comments() -> None:
    lines = ["x = f(a,  # note\n", "      b)\n", "# y = g()\n", "if x:\n", "    z = 1\n"]
    stmts = patching.logical_lines(lines)
    assert [(s.first, s.last, s.text) for s in stmts] == [(0, 1, "x = f(a, b)"), (3, 3, "if x:"), (4, 4, "    z = 1")]
    assert patching.block_last_line(stmts, stmts[1]) == 4


def test_placeholders_use_escaped_captures_and_conflicts_are_errors() -> None:
    anchors = [
        Anchor("first", r"(?P<name>\w+\.\w+) = 1"),
        Anchor("second", r"y = {name}$", lines=("z = {name}",), where="after"),
    ]
    patched = patching.apply_anchors("a.b = 1\ny = a.b\ny = aXb\n", anchors)
    assert patched == f"a.b = 1\ny = a.b\nz = a.b  {MARKER}\ny = aXb\n"
    clash = [Anchor("one", r"(?P<v>\w+) = 1"), Anchor("two", r"(?P<v>\w+) = 2")]
    with pytest.raises(PatchError, match="captured v='b' but an earlier anchor captured 'a'"):
        patching.apply_anchors("a = 1\nb = 2\n", clash, "f.py")


def test_anchor_definitions_are_checked() -> None:
    with pytest.raises(ValueError):
        Anchor("bad", "x", where="around")
    with pytest.raises(ValueError):
        Anchor("bad", "x", lines=(f"y = 1  {MARKER}",))
    with pytest.raises(ValueError, match="not an earlier anchor"):
        patching.locate([Anchor("a", "x", after="b"), Anchor("b", "x")], [], "f.py")


def test_result_that_would_not_compile_is_refused(tmp_path: Path) -> None:
    target = tmp_path / "train.py"
    target.write_text("if x:\n    y = 1\n")
    anchors = [Anchor("body", r"\s*y = 1", lines=("else:",))]
    with pytest.raises(PatchError, match="would not compile"):
        patching.patch_file(target, anchors)
    assert target.read_text() == "if x:\n    y = 1\n"


# ----------------------------------------------------------------------------------------------
# the scripts as the user runs them


@pytest.mark.slow
@pytest.mark.parametrize("case", [CASES[1], CASES[2], CASES[3]], ids=[IDS[1], IDS[2], IDS[3]])
def test_script_runs_as_a_subprocess(case: Case, tmp_path: Path) -> None:
    checkout = copy_fixture(tmp_path, case.fixture)
    script = ROOT / "adapters" / case.adapter / "patch.py"
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    command = [sys.executable, str(script), str(checkout)]
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert_inserted((checkout / "train.py").read_text(), case)
    broken = fixture_text(case).replace("loss.backward()", "loss.step()")
    (checkout / "train.py").write_text(broken)
    (checkout / "train.py.polargs-orig").unlink()
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.startswith(f"error: {checkout / 'train.py'}: anchor 'loss backward' not found (")
    assert (checkout / "train.py").read_text() == broken


# ----------------------------------------------------------------------------------------------
# 2DGS, gsplat's simple_trainer.py (1.5.3 and main), mip-splatting


TWODGS = Case("twodgs", "twodgs_1920a23_train.py", "scene, gaussians, pipe, render", "from argparse import ArgumentParser")
GSPLAT_TRAINERS = ["gsplat_v1.5.3_simple_trainer.py", "gsplat_90d7b4b_simple_trainer.py"]
GSPLAT_LINES = [  # (inserted line, its neighbour, where the neighbour sits)
    ("import polargs_adapters.gsplat as polargs_gsplat", "from gsplat.strategy import DefaultStrategy", "above"),
    ("        self.polar = polargs_gsplat.attach(self)", "        self.cfg.strategy.check_sanity(", "below"),
    (
        "            loss = loss + self.polar.loss(step, image_ids, camtoworlds, Ks, renders, alphas, info)",
        "            loss.backward()",
        "below",
    ),
]


def round_trip(script: str, checkout: Path, target: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Dry run (nothing written), patch, patch again (no change), revert (byte-identical); returns
    the patched text."""
    original = target.read_bytes()
    patch = load_script(script)
    filename = target.name
    assert patching.main([str(checkout), "--dry-run"], patch.ANCHORS, "test", filename=filename) == 0
    assert target.read_bytes() == original and sorted(p.name for p in checkout.iterdir()) == [filename]
    assert patching.main([str(checkout)], patch.ANCHORS, "test", filename=filename) == 0
    patched = target.read_text()
    assert patching.main([str(checkout)], patch.ANCHORS, "test", filename=filename) == 0
    assert target.read_text() == patched and "already patched, no change" in capsys.readouterr().out
    assert patching.main([str(checkout), "--revert"], patch.ANCHORS, "test", filename=filename) == 0
    assert target.read_bytes() == original and sorted(p.name for p in checkout.iterdir()) == [filename]
    return patched


def test_twodgs_round_trip_puts_densify_in_the_first_no_grad_block(tmp_path: Path, capsys) -> None:
    checkout = copy_fixture(tmp_path, TWODGS.fixture)
    patched = round_trip("twodgs", checkout, checkout / "train.py", capsys)
    assert_inserted(patched, TWODGS, Names(loss="total_loss"))
    lines = patched.splitlines()
    densify = next(i for i, line in enumerate(lines) if "polar.densify(" in line)
    blocks = [i for i, line in enumerate(lines) if line.strip() == "with torch.no_grad():"]
    assert len(blocks) == 2 and blocks[0] < densify < blocks[1]


@pytest.mark.parametrize("fixture", GSPLAT_TRAINERS)
def test_gsplat_simple_trainer_round_trip(fixture: str, tmp_path: Path, capsys) -> None:
    checkout = tmp_path / "examples"
    checkout.mkdir()
    target = checkout / "simple_trainer.py"
    target.write_bytes((TRAINERS / fixture).read_bytes())
    patched = round_trip("gsplat", checkout, target, capsys)
    lines = patched.splitlines()
    assert sum(line.endswith(MARKER) for line in lines) == len(GSPLAT_LINES)
    for text, neighbour, side in GSPLAT_LINES:
        i = lines.index(f"{text}  {MARKER}")
        other = lines[i + 1] if side == "below" else lines[i - 1]
        assert other.startswith(neighbour), (text, other)
    compile(patched, "simple_trainer.py", "exec")


def test_the_gsplat_script_finds_the_trainer_under_the_repository_root(tmp_path: Path) -> None:
    """`patch.py GSPLAT_REPO` patches examples/simple_trainer.py; a folder without it is named with
    the examples/ folder the script looked in."""
    script = [sys.executable, str(ROOT / "adapters" / "gsplat" / "patch.py")]
    (tmp_path / "repo" / "examples").mkdir(parents=True)
    target = tmp_path / "repo" / "examples" / "simple_trainer.py"
    target.write_bytes((TRAINERS / GSPLAT_TRAINERS[1]).read_bytes())
    done = subprocess.run([*script, str(tmp_path / "repo")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.startswith(f"{target}: patched, {len(GSPLAT_LINES)} lines inserted")
    assert sum(line.endswith(MARKER) for line in target.read_text().splitlines()) == len(GSPLAT_LINES)
    (tmp_path / "empty").mkdir()
    refused = subprocess.run([*script, str(tmp_path / "empty")], capture_output=True, text=True, timeout=60)
    examples = tmp_path / "empty" / "examples"
    assert refused.returncode == 2 and refused.stderr == (
        f"error: {tmp_path / 'empty'}: no simple_trainer.py in {tmp_path / 'empty'} or {examples}{os.sep}; "
        "pass the trainer's checkout or the file itself\n")


def test_gsplat_refuses_a_trainer_whose_strategy_is_not_stepped_after_backward(tmp_path: Path, capsys) -> None:
    text = (TRAINERS / GSPLAT_TRAINERS[0]).read_text().replace("strategy.step_post_backward(", "strategy.other(")
    checkout = tmp_path / "examples"
    checkout.mkdir()
    (checkout / "simple_trainer.py").write_text(text)
    assert patching.main([str(checkout)], load_script("gsplat").ANCHORS, "test", filename="simple_trainer.py") == 2
    assert "anchor 'step_post_backward' not found" in capsys.readouterr().err
    assert (checkout / "simple_trainer.py").read_text() == text


REFUSALS = [
    ("graphdeco", "mip_dda02ab_train.py", "passes kernel_size, as mip-splatting and GOF do: mip-splatting's loop is not supported"),
    ("gof", "mip_dda02ab_train.py", "mip-splatting's loop is not supported"),
    ("graphdeco", "twodgs_1920a23_train.py", "the loop reads 2DGS's outputs: use adapters/twodgs/patch.py"),
    ("twodgs", "graphdeco_2023_train.py", "anchor '2DGS outputs' not found"),
]


@pytest.mark.parametrize(("script", "fixture", "message"), REFUSALS, ids=[f"{s}-{f.split('_')[0]}" for s, f, _ in REFUSALS])
def test_relatives_are_refused_in_one_line(script: str, fixture: str, message: str, tmp_path: Path, capsys) -> None:
    checkout = copy_fixture(tmp_path, fixture)
    text = (checkout / "train.py").read_text()
    assert patching.main([str(checkout)], load_script(script).ANCHORS, "test") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {checkout / 'train.py'}: ") and message in err
    assert (checkout / "train.py").read_text() == text
    assert sorted(p.name for p in checkout.iterdir()) == ["train.py"]


def test_a_render_keyword_bound_inside_the_loop_is_refused_before_writing(tmp_path: Path, capsys) -> None:
    """attach() runs above the loop: copying a keyword whose value is assigned in the loop would
    fail at run time with UnboundLocalError (mip-splatting's subpixel_offset, on any fork)."""
    text = fixture_text(CASES[0]).replace(
        "        render_pkg = render(viewpoint_cam, gaussians, pipe, bg)\n",
        "        jitter = bg * 0.5\n        render_pkg = render(viewpoint_cam, gaussians, pipe, bg, offset=jitter)\n",
    )
    checkout = copy_fixture(tmp_path, CASES[0].fixture, text)
    assert run_main(CASES[0], str(checkout)) == 2
    err = capsys.readouterr().err
    lines = text.splitlines()
    jitter_line = lines.index("        jitter = bg * 0.5") + 1
    loop_line = next(i for i, line in enumerate(lines) if line.startswith("    for iteration in range(")) + 1
    assert err.count("\n") == 1
    assert f"the line to insert above L{loop_line} would read 'jitter' before it is bound" in err
    assert f"(first bound at L{jitter_line}, below it)" in err
    assert (checkout / "train.py").read_text() == text
    # bound above the loop, the same keyword is handed to attach
    above = fixture_text(CASES[0]).replace("    first_iter += 1\n", "    first_iter += 1\n    jitter = None\n").replace(
        "render(viewpoint_cam, gaussians, pipe, bg)", "render(viewpoint_cam, gaussians, pipe, bg, offset=jitter)")
    (checkout / "train.py").write_text(above)
    assert run_main(CASES[0], str(checkout)) == 0
    assert "attach(scene, gaussians, pipe, render, offset=jitter)" in (checkout / "train.py").read_text()


def test_unbound_reads_follows_scopes() -> None:
    text = (
        "import os\n"            # 1
        "def f(a):\n"            # 2
        "    b = a\n"            # 3
        "    c = b + a + g\n"    # 4: g is a module name bound later: fine in a function
        "    d = e\n"            # 5: e bound below
        "    e = len([x for x in a])\n"  # 6: comprehension variable, builtin
        "g = 1\n"                # 7
        "h = k\n"                # 8: k bound below, at module level
        "k = 2\n"                # 9
    )
    assert patching.unbound_reads(text, [3, 4, 5, 6, 8]) == [(5, "e", 6), (8, "k", 9)]


def test_read_only_file_is_refused_unless_forced(tmp_path: Path, capsys) -> None:
    case = CASES[0]
    checkout = copy_fixture(tmp_path, case.fixture, mode=0o444)
    target = checkout / "train.py"
    original = target.read_bytes()
    assert run_main(case, str(checkout)) == 2
    err = capsys.readouterr().err
    assert err == f"error: {target}: read-only (mode 0444); --force patches it anyway, keeping the mode\n"
    assert target.read_bytes() == original and sorted(p.name for p in checkout.iterdir()) == ["train.py"]
    assert run_main(case, str(checkout), "--dry-run") == 0  # a dry run writes nothing: allowed
    assert run_main(case, str(checkout), "--force") == 0
    assert_inserted(target.read_text(), case)
    assert stat.S_IMODE(target.stat().st_mode) == 0o444
    assert run_main(case, str(checkout), "--revert") == 2
    assert "--force reverts it anyway" in capsys.readouterr().err
    assert run_main(case, str(checkout), "--revert", "--force") == 0
    assert target.read_bytes() == original and stat.S_IMODE(target.stat().st_mode) == 0o444


# ----------------------------------------------------------------------------------------------
# the engine needs only the standard library

ENGINE_FILES = [
    ROOT / "src" / "polargs_plugin" / "kit" / "patching.py",
    ROOT / "src" / "polargs_plugin" / "kit" / "inria_anchors.py",
    ROOT / "adapters" / "patch_engine.py",
    *sorted((ROOT / "adapters").glob("*/patch.py")),
]


@pytest.mark.parametrize("path", ENGINE_FILES, ids=[str(p.relative_to(ROOT)) for p in ENGINE_FILES])
def test_engine_files_are_python_3_8(path: Path) -> None:
    import ast

    ast.parse(path.read_text(), str(path), feature_version=(3, 8))
    imported = {
        alias.name.split(".")[0]
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Import)
        for alias in node.names
    } | {
        node.module.split(".")[0]
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0
    }
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported - set(sys.stdlib_module_names)


SCRIPT_TARGETS = [
    ("graphdeco", "graphdeco_2024_train.py", "train.py"),
    ("gof", "gof_5245b20_train.py", "train.py"),
    ("pgsr", "pgsr_de24f1a_train.py", "train.py"),
    ("twodgs", "twodgs_1920a23_train.py", "train.py"),
    ("gsplat", "gsplat_90d7b4b_simple_trainer.py", "simple_trainer.py"),
]


@pytest.mark.parametrize(("script", "fixture", "name"), SCRIPT_TARGETS, ids=[s for s, _, _ in SCRIPT_TARGETS])
def test_scripts_run_without_site_packages(script: str, fixture: str, name: str, tmp_path: Path) -> None:
    """``python -S -I``: no site-packages (no torch, no numpy), no PYTHONPATH, no user site."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    target = checkout / name
    target.write_bytes((TRAINERS / fixture).read_bytes())
    original = target.read_bytes()
    command = [sys.executable, "-S", "-I", str(ROOT / "adapters" / script / "patch.py"), str(checkout)]
    done = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert target.read_text().count(MARKER) in (3, 4)
    done = subprocess.run([*command, "--revert"], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert target.read_bytes() == original
    probe = "import sys, runpy; runpy.run_path(sys.argv[1]); print(sorted(m for m in ('torch', 'numpy', 'polargs_plugin') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-S", "-I", "-c", probe, str(ROOT / "adapters" / script / "patch.py")],
                          capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr


# ----------------------------------------------------------------------------------------------
# a trainer file that is a symbolic link

LINKED_TRAINERS = [  # (adapter, fixture, the file's name in a checkout)
    ("graphdeco", "graphdeco_2024_train.py", "train.py"),
    ("gof", "gof_5245b20_train.py", "train.py"),
    ("pgsr", "pgsr_de24f1a_train.py", "train.py"),
    ("twodgs", "twodgs_1920a23_train.py", "train.py"),
    ("gsplat", "gsplat_90d7b4b_simple_trainer.py", "simple_trainer.py"),
]


@pytest.mark.parametrize("adapter, fixture, name", LINKED_TRAINERS, ids=[row[0] for row in LINKED_TRAINERS])
def test_patch_and_revert_act_on_a_linked_trainers_target_and_keep_the_link(adapter, fixture, name, tmp_path):
    """`patch.py CHECKOUT` where CHECKOUT's trainer is a link: the file it points to is patched
    (its backup beside it), the link stays a link, and --revert restores the target byte for byte."""
    script = [sys.executable, str(ROOT / "adapters" / adapter / "patch.py")]
    (tmp_path / "elsewhere").mkdir()
    target = tmp_path / "elsewhere" / name
    original = (TRAINERS / fixture).read_bytes()
    target.write_bytes(original)
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    link = checkout / name
    link.symlink_to(target)
    done = subprocess.run([*script, str(checkout)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stderr == f"{link}: a link; acting on its target {target} (the link is kept)\n"
    assert done.stdout.startswith(f"{target}: patched, ")
    assert link.is_symlink() and link.resolve() == target and MARKER in target.read_text()
    assert (tmp_path / "elsewhere" / f"{name}.polargs-orig").read_bytes() == original
    assert sorted(p.name for p in checkout.iterdir()) == [name]
    done = subprocess.run([*script, str(checkout), "--revert"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert link.is_symlink() and link.resolve() == target and target.read_bytes() == original
    assert sorted(p.name for p in (tmp_path / "elsewhere").iterdir()) == [name]
