"""`polargs demo` and `polargs ablate` on a tiny scene: outputs, resuming, failures (docs/ablation.md).

Tiny sizes go through the commands' own options (6 views of 32x32, 60 iterations, <= 800
Gaussians, 20k Chamfer samples), so the whole module runs in well under a minute once numba's
kernels are cached.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import open3d
import pytest
import torch

from polargs_plugin.ablation import cell as cell_module
from polargs_plugin.ablation import pipeline as pipeline_module
from polargs_plugin.ablation.cell import Cell, CellFailed, run_cell
from polargs_plugin.service import provenance as provenance_module
from polargs_plugin.io import PolarInputError
from polargs_plugin.ablation.gather import gather
from polargs_plugin.ablation.grid import expand, run_grid
from polargs_plugin.ablation.scenes import SceneSpec, parse_scene
from polargs_plugin.ablation.variants import VARIANTS, variant_configs
from polargs_plugin.cli import main
from polargs_plugin.data.synthetic import GENERATOR_VERSION
from provenance_check import check_provenance

TINY = ["--views", "6", "--size", "32x32", "--factor", "0.002", "--eval-samples", "20000",
        "--train-set", "num_init_points=300", "--train-set", "density.max_gaussians=800", "--jobs", "1", "--quiet"]
SCENE = "glossy_plane_sphere"


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


# ------------------------------------------------------------------------------- no training
def test_variant_switches():
    expected = {  # PC, Dense, L_ref, L_n, L_dn, L_scale
        "reg": (False, False, False, False, True, True),
        "no-dense": (True, False, True, False, True, True),
        "no-pc": (False, True, False, True, True, True),
        "full": (True, True, True, True, True, True),
    }
    train, polar = variant_configs("base", factor=0.002, seed=3)
    assert polar is None and train.seed == 3 and train.iterations == 60
    for variant, switches in expected.items():
        train, polar = variant_configs(variant, factor=0.002, seed=3, train_overrides={"density": {"max_gaussians": 10}})
        l = polar.losses
        assert (polar.correction.enabled, polar.densify.enabled, l.use_ref, l.use_normal, l.use_depth_normal, l.use_scale) == switches
        assert train.density.max_gaussians == 10
        assert polar.densify.patchmatch.seed == 3
    assert set(expected) | {"base"} == set(VARIANTS)
    with pytest.raises(PolarInputError, match="--polar-set: polar.losses: unknown setting 'nonsense'"):
        variant_configs("full", polar_overrides={"losses": {"nonsense": 1}})


def test_cell_is_plain_data(tmp_path):
    scene = parse_scene(SCENE, tmp_path / "cache", 6, 32, 32)
    assert scene.bundled == SCENE and scene.path.endswith(f"{SCENE}-6v-32x32-s0-g{GENERATOR_VERSION}")
    named = parse_scene(f"mine={tmp_path}/data:{tmp_path}/gt.ply", tmp_path)
    assert (named.name, named.gt_mesh, named.bundled) == ("mine", str(tmp_path / "gt.ply"), None)
    assert parse_scene(str(tmp_path), tmp_path).name == tmp_path.name
    cells = expand([scene], ["base", "full"], [0, 1], tmp_path, inits=("hull", "random"), factor=0.002,
                   train_overrides={"density": {"max_gaussians": 800}})
    assert len(cells) == 8 and len({c.name for c in cells}) == 8
    for cell in cells:
        assert Cell.from_dict(json.loads(json.dumps(cell.to_dict()))) == cell
    assert cells[0].run_dir == tmp_path / cells[0].name
    with pytest.raises(ValueError, match="unknown variant"):
        Cell(scene=scene, variant="nope", seed=0, out=str(tmp_path))


def test_usage_errors_are_one_line(tmp_path, capsys):
    assert main(["ablate", "--scenes", SCENE, "--variants", "base,nope", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --variants:") and "\n" not in err
    assert main(["ablate", "--scenes", SCENE, "--train-set", "nonsense=1", "--out", str(tmp_path / "a")]) == 2
    assert "error: --train-set" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["demo", "--out", str(tmp_path / "file")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'file'}: exists and is not a folder"


@pytest.mark.slow
def test_pool_reports_failed_cells_with_logs(tmp_path):
    """The process-pool path (spawned workers, each given one "GPU" as on a multi-GPU machine)
    with two cells that fail fast: both are reported with their logs, nothing else is left behind."""
    bad = SceneSpec("missing", str(tmp_path / "missing"))
    cells = expand([bad], ["base", "reg"], [0], tmp_path / "out")
    result = run_grid(cells, jobs=2, progress=False, gpus=("5", "6"))
    assert not result.ok and {c.name for c, _, _ in result.failed} == {c.name for c in cells}
    for cell, log, message in result.failed:
        assert "dataset not found" in message and Path(log) == cell.log_path
        text = Path(log).read_text()
        assert "Traceback" in text and re.search(r"CUDA_VISIBLE_DEVICES=[56]\)", text)
        assert not cell.run_dir.exists()
    assert not list((tmp_path / "out").glob(".tmp-*"))
    with pytest.raises(CellFailed, match="dataset not found"):
        run_cell(cells[0])


@pytest.mark.parametrize("stop", ["interrupted", "failed"])
def test_a_cell_stopped_while_setting_up_leaves_its_log_and_no_temporary_folder(tmp_path, monkeypatch, stop):
    """A stop that lands between the cell's temporary folder and its log (a scheduler's SIGTERM
    under load) still leaves the attempt's log where the next attempt or the user looks: an
    interruption appends to the partial log (after the earlier attempts' words), a failure writes
    the failure log; no .tmp folder is left either way."""

    cell = expand([SceneSpec("s", str(tmp_path / "s"))], ["base"], [0], tmp_path / "out")[0]
    cell.partial_dir.mkdir(parents=True)
    (cell.partial_dir / "attempts.log").write_text("first attempt\n")
    error = KeyboardInterrupt() if stop == "interrupted" else PermissionError("run.log: permission denied")

    def refuse(path, *args, **kwargs):
        if Path(path).name == "run.log":
            raise error
        return open(path, *args, **kwargs)

    monkeypatch.setattr(cell_module, "open", refuse, raising=False)
    if stop == "interrupted":
        with pytest.raises(KeyboardInterrupt):
            run_cell(cell)
        text = (cell.partial_dir / "attempts.log").read_text()
        assert text.startswith("first attempt\n\nINTERRUPTED (KeyboardInterrupt) at ")
        assert not cell.log_path.exists()
    else:
        with pytest.raises(CellFailed, match="permission denied"):
            run_cell(cell)
        assert "FAILED: PermissionError: run.log: permission denied" in cell.log_path.read_text()
        assert (cell.partial_dir / "attempts.log").exists()  # an OSError keeps what a resume needs
    assert not list((tmp_path / "out").glob(".tmp-*")) and not cell.run_dir.exists()


@pytest.mark.slow
def test_mesh_error_is_the_exact_signed_distance(tmp_path):
    """mesh_error.npz of the report: vertices of spheres of radius 1.05 and 0.95 against the unit GT
    sphere are +0.05 / -0.05 from it (analytic), up to the GT's tessellation; the nearest of many GT
    samples (what it was computed from before) agrees to the samples' spacing and is never nearer."""
    import numpy as np
    import open3d as o3d
    from scipy.spatial import cKDTree

    from polargs_plugin.ablation.artifacts import mesh_error
    from polargs_plugin.metrics import sample_surface

    def sphere(radius: float) -> o3d.geometry.TriangleMesh:
        return o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=40)

    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), sphere(1.05) + sphere(0.95))
    o3d.io.write_triangle_mesh(str(tmp_path / "gt.ply"), sphere(1.0))
    error = mesh_error(tmp_path / "pred.ply", tmp_path / "gt.ply")
    radius = np.linalg.norm(error["vertices"].astype(np.float64), axis=1)
    outside = radius > 1
    sag = 1 - math.cos(math.pi / 40)  # farthest a triangle of the GT sphere lies inside it
    distance = error["signed_distance"].astype(np.float64)
    assert outside.mean() == pytest.approx(0.5)
    assert np.all(np.abs(distance[outside] - 0.05) < sag) and np.all(distance[outside] >= 0.05 - 1e-6)
    assert np.all(np.abs(distance[~outside] + 0.05) < sag) and np.all(distance[~outside] <= -0.05 + 1e-6 + sag)

    gt = sphere(1.0)
    samples = sample_surface(gt, 400_000, seed=0)
    nearest = cKDTree(samples).query(error["vertices"].astype(np.float64))[0]
    assert np.all(nearest >= np.abs(distance) - 1e-6)
    assert np.all(nearest - np.abs(distance) < 2e-3) and np.median(nearest - np.abs(distance)) < 1e-4



def test_depth_error_pixels_leave_out_what_is_not_the_object():
    """The report's depth-error picture shows (and scales by) the masked, rendered pixels on the GT
    object's silhouette; without a saved silhouette (older runs) every masked, rendered pixel."""
    from polargs_plugin.ablation.report import _depth_error_pixels

    size = 8
    mask = np.zeros((1, size, size), bool)
    mask[:, 1:7, 1:7] = True
    alpha = np.ones((1, size, size))
    alpha[:, 1, :] = 0.2  # not rendered
    silhouette = np.zeros((1, size, size), bool)
    silhouette[:, :4, :] = True  # the object: the top half of the image, the rest a floor in the mask
    d = {"0/mask": mask, "0/alpha": alpha, "0/depth_gt": np.ones((1, size, size)), "0/gt_silhouette": silhouette}
    expected = np.zeros((size, size), bool)
    expected[2:4, 1:7] = True
    assert np.array_equal(_depth_error_pixels(d, 0), expected)
    del d["0/gt_silhouette"]
    expected[2:7, 1:7] = True
    assert np.array_equal(_depth_error_pixels(d, 0), expected)


def test_mesh_error_flags_the_vertices_the_evaluation_measures(tmp_path):
    """With views, mesh_error.npz says which vertices lie in the object region (`polargs eval`'s
    culling: seen, and inside the GT's dilated silhouette in every view that sees them), the very
    points that chamfer_distance's culling keeps: a shell around the unit GT sphere all of it, a
    floor below it only where every view that sees it sees it behind the sphere."""
    import open3d as o3d
    from test_metrics import silhouette_view

    from polargs_plugin.ablation.artifacts import EVAL_CULL_DILATION, mesh_error
    from polargs_plugin.metrics import cull_to_masks, mesh_silhouettes

    views = [silhouette_view(np.array(e, dtype=np.float64)) for e in ([3, 0, 1], [0, 3, 1], [-3, -1, 0.5])]
    shell = o3d.geometry.TriangleMesh.create_sphere(radius=1.02, resolution=30)
    floor = o3d.geometry.TriangleMesh.create_box(4, 4, 0.01).translate((-2, -2, -1.5)).subdivide_midpoint(4)
    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), shell + floor)
    gt = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=40)
    o3d.io.write_triangle_mesh(str(tmp_path / "gt.ply"), gt)
    error = mesh_error(tmp_path / "pred.ply", tmp_path / "gt.ply", views)
    on_shell = np.linalg.norm(error["vertices"], axis=1) < 1.1
    assert on_shell.sum() == len(shell.vertices)
    assert error["evaluated"][on_shell].all() and error["evaluated"][~on_shell].mean() < 0.25
    vertices = error["vertices"].astype(np.float64)
    culled = cull_to_masks(vertices, views, EVAL_CULL_DILATION, masks=mesh_silhouettes(gt, views), require_seen=True)
    assert np.array_equal(error["evaluated"], culled)
    assert "evaluated" not in mesh_error(tmp_path / "pred.ply", tmp_path / "gt.ply")  # without views: not claimed

def _fake_run(out: Path, variant: str, seed: int, figures: dict, chamfer: dict | None = None, scene: str = SCENE) -> None:
    """A run folder as run_cell writes it, summary.json (and metrics.json) only."""
    from polargs_plugin.ablation.pipeline import RUN_FORMAT

    folder = out / f"{scene}__{variant}__hull__s{seed}"
    folder.mkdir(parents=True)
    summary = {"format": RUN_FORMAT, "scene": {"name": scene}, "variant": variant, "seed": seed, "init": "hull",
               "init_used": "hull", "figures": figures, "timings": {"total": 1.0}, "git": {"commit": "abc"}}
    (folder / "summary.json").write_text(json.dumps(summary))
    if chamfer is not None:
        (folder / "metrics.json").write_text(json.dumps({"chamfer": chamfer}))


def test_the_verdict_needs_both_chamfer_figures_and_the_means_and_dense_budget_add_up(tmp_path):
    """Full against reg: better where both Chamfer figures fall, worse where both rise, level within
    1 %, "disagree" where they move apart; the means over scenes, the worst scene and what Dense's
    appends bought are the plain arithmetic of the per-run figures; a run folder from before the
    visible-surface figures gets them from its metrics.json."""
    # (capped, visible) Chamfer of reg and full per scene, and full's appended Gaussians
    cases = {"a": ((0.010, 0.020), (0.008, 0.015)), "b": ((0.010, 0.020), (0.012, 0.024)),
             "c": ((0.010, 0.020), (0.0101, 0.0199)), "d": ((0.010, 0.020), (0.009, 0.023))}
    for scene, ((reg_capped, reg_visible), (full_capped, full_visible)) in cases.items():
        for variant, capped, visible, appended in (("reg", reg_capped, reg_visible, 0),
                                                    ("no-dense", reg_capped, reg_visible, 0),
                                                    ("full", full_capped, full_visible, 2000)):
            figures = {"chamfer": capped, "chamfer_visible": visible, "normal_mae_deg": 10.0, "appended_total": appended}
            _fake_run(tmp_path, variant, 0, figures, scene=scene)
    # a run folder written before the visible figures were in the summary: they come from metrics.json
    _fake_run(tmp_path, "reg", 0, {"chamfer": 0.01, "normal_mae_deg": 10.0}, scene="old",
              chamfer={"chamfer": 0.01, "chamfer_visible": 0.03, "completeness_by_visibility": {"grazing": 0.05},
                       "visibility_shares": {"grazing": 0.2}})
    results = gather(tmp_path)
    verdict = {(v["scene"], v["reference"]): v for v in results["verdicts"] if v["variant"] == "full"}
    assert {scene: verdict[(scene, "reg")]["verdict"] for scene in cases} == {
        "a": "better", "b": "worse", "c": "level", "d": "disagree"}
    assert verdict[("d", "reg")]["capped"] == pytest.approx(-0.1) and verdict[("d", "reg")]["visible"] == pytest.approx(0.15)
    means = {m["variant"]: m for m in results["scene_means"]}
    assert means["full"]["scenes"] == list(cases)  # "old" has no full run: left out of the means
    full_mean = sum(v for _, (_, v) in cases.values()) / 4
    assert means["full"]["chamfer_visible"] == pytest.approx(full_mean)
    assert means["full"]["chamfer_visible_vs_reg"] == pytest.approx(full_mean / 0.020 - 1)
    assert means["full"]["worst_visible_vs_reg"] == pytest.approx(0.2)  # scene b
    budget = {b["scene"]: b for b in results["dense_budget"]}
    assert budget["a"]["reference"] == "no-dense" and budget["a"]["appended"] == 2000
    assert budget["a"]["change_per_thousand"] == pytest.approx((0.015 / 0.020 - 1) / 2)
    old = next(e for e in results["table"] if e["scene"] == "old")
    assert old["chamfer_visible"]["mean"] == 0.03 and old["completeness_grazing"]["mean"] == 0.05
    markdown = (tmp_path / "results.md").read_text()
    assert "**the Chamfer figures disagree**" in markdown and "### Means over the scenes" in markdown


def _markdown_rows(markdown: str, title: str) -> list[dict[str, str]]:
    """The rows of the Markdown table under ``### title``, as {column: cell}."""
    lines = markdown.split(f"### {title}\n\n", 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| "))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    table = lines[start:end]
    head = [c.strip() for c in table[0].strip("|").split("|")]
    return [dict(zip(head, [c.strip() for c in line.strip("|").split("|")])) for line in table[2:]]


def test_a_variant_that_loses_a_visibility_class_against_base_is_named(tmp_path):
    """Per scene and visibility class: the class's share, each variant's completeness (mean over
    seeds) and its change against base and reg, the missing share; a variant loses the class where
    it is worse than base beyond the larger seed spread (two seeds) or by more than 5 % (one seed),
    and the verdict (results.md and the report's scene section) names it; a class under 5 % of the
    seen surface is shown, marked and not compared."""
    from polargs_plugin.ablation.report import write_report

    shares = {"many": 0.70, "few": 0.27, "grazing": 0.03}
    # scene s, two seeds: (few completeness per seed, grazing completeness per seed, few missing per seed)
    two_seeds = {"base": ([0.010, 0.012], [0.02, 0.02], [0.02, 0.04]),
                 "reg": ([0.0115, 0.0125], [0.02, 0.02], [0.03, 0.03]),   # +9.1 %, within base's spread
                 "no-pc": ([0.0112, 0.0118], [0.02, 0.02], [0.03, 0.03]),  # +4.5 %, within the spread
                 "full": ([0.014, 0.016], [0.05, 0.06], [0.10, 0.12])}    # +36 %: loses few; grazing not compared
    for variant, (few, grazing, missing) in two_seeds.items():
        for seed in range(2):
            figures = {"chamfer": 0.01, "chamfer_visible": 0.02, "normal_mae_deg": 10.0, "visible_fraction": 0.9,
                       **{f"share_{c}": s for c, s in shares.items()}, "completeness_many": 0.005,
                       "completeness_few": few[seed], "completeness_grazing": grazing[seed],
                       "missing_many": 0.0, "missing_few": missing[seed], "missing_grazing": 0.2}
            _fake_run(tmp_path, variant, seed, figures, scene="s")
    # scene t, one seed: no-dense +6 % (loses), full +4 % (holds)
    for variant, few in (("base", 0.010), ("no-dense", 0.0106), ("full", 0.0104)):
        figures = {"chamfer": 0.01, "chamfer_visible": 0.02, "normal_mae_deg": 10.0, "visible_fraction": 0.9,
                   **{f"share_{c}": s for c, s in shares.items()}, "completeness_many": 0.005, "completeness_few": few,
                   "completeness_grazing": 0.02, "missing_few": 0.05}
        _fake_run(tmp_path, variant, 0, figures, scene="t")

    results = gather(tmp_path)
    rows = {(r["scene"], r["class"], r["variant"]): r for r in results["class_completeness"]}
    full = rows[("s", "few", "full")]
    assert full["share"] == pytest.approx(0.27) and full["compared"] and full["seeds"] == 2
    assert full["completeness"] == pytest.approx(0.015) and full["completeness_std"] == pytest.approx(0.001 * math.sqrt(2))
    assert full["vs_base"] == pytest.approx(0.015 / 0.011 - 1) and full["vs_reg"] == pytest.approx(0.015 / 0.012 - 1)
    assert full["missing"] == pytest.approx(0.11) and full["loses_to_base"] is True
    losing = {(s, c, v) for (s, c, v), r in rows.items() if r["loses_to_base"]}
    assert losing == {("s", "few", "full"), ("t", "few", "no-dense")}
    assert rows[("s", "few", "no-pc")]["loses_to_base"] is False and rows[("s", "few", "reg")]["loses_to_base"] is False
    assert rows[("t", "few", "full")]["loses_to_base"] is False and rows[("s", "few", "base")]["loses_to_base"] is None
    grazing = rows[("s", "grazing", "full")]  # 2.5 times base's, but 3 % of the seen surface: not compared
    assert not grazing["compared"] and grazing["loses_to_base"] is None and grazing["vs_base"] == pytest.approx(1.75)
    assert rows[("t", "few", "no-dense")]["vs_reg"] is None  # no reg on t
    assert json.loads((tmp_path / "results.json").read_text())["class_completeness"] == results["class_completeness"]

    markdown = (tmp_path / "results.md").read_text()
    verdict = markdown.split("### Verdict", 1)[1].split("###", 1)[0]
    assert "- `full` loses the `few` class (27 % of the seen surface) against `base` on s: completeness +36.4 % " \
           "(beyond the seeds' spread), missing 11.0 % against base's 3.0 %" in verdict
    assert "- `no-dense` loses the `few` class (27 % of the seen surface) against `base` on t: completeness +6.0 % " \
           "(one seed: more than 5 %)" in verdict
    assert verdict.count(" loses the ") == 2 and "`grazing` class" not in verdict
    table = {(r["scene"], r["class"], r["variant"]): r for r in _markdown_rows(markdown, "Completeness by visibility class")}
    assert len(table) == 3 * (4 + 3)
    assert table[("s", "few", "full")] == {
        "scene": "s", "class": "few", "share of seen": "0.270", "variant": "full", "seeds": "2",
        "completeness": "0.015 ± 0.001414", "vs base": "+36.4 %", "vs reg": "+25.0 %", "missing": "11.0 %",
        "against base": "**loses**"}
    assert table[("s", "few", "reg")]["vs base"] == "+9.1 %" and table[("s", "few", "reg")]["against base"] == "holds"
    assert table[("s", "few", "base")]["vs base"] == "" and table[("s", "few", "base")]["missing"] == "3.0 %"
    assert table[("s", "grazing", "full")]["share of seen"] == "0.030 (under 5 %: not compared)"
    assert table[("s", "grazing", "full")]["against base"] == "" and table[("s", "grazing", "full")]["vs base"] == "+175.0 %"
    assert table[("t", "few", "no-dense")]["missing"] == "5.0 %" and table[("t", "many", "full")]["missing"] == "n/a"

    report = write_report(tmp_path, results).read_text()
    section_s, section_t = report.split("\n## s\n", 1)[1].split("\n## t\n", 1)
    assert "- `full` loses the `few` class (27 % of the seen surface) against `base`: completeness +36.4 %" in section_s
    assert " loses the " not in section_s.replace("- `full` loses the `few`", "")
    assert "- `no-dense` loses the `few` class" in section_t and "`full` loses" not in section_t


def test_uncapped_figures_reach_the_results(tmp_path):
    """The uncapped Chamfer / completeness and the median signed distance of summary["figures"] go
    to results.csv / .json (per run, mean ± spread over seeds) and to the Markdown table; a run
    folder from before they were in the summary gets them from its metrics.json."""
    import csv

    from polargs_plugin.ablation.gather import METRICS

    new = ("chamfer_uncapped", "accuracy_uncapped", "completeness_uncapped", "accuracy_outliers",
           "completeness_outliers", "signed_distance_median")
    base = {"chamfer": 0.03, "accuracy": 0.035, "completeness": 0.025, "fscore": 0.4, "normal_mae_deg": 10.0,
            "psnr": 25.0, "num_gaussians": 100, "train_seconds": 5.0, "iterations": 60}
    for seed, (cu, comp, sd) in enumerate([(0.050, 0.0410, -0.043), (0.060, 0.0430, -0.041)]):
        extra = {"chamfer_uncapped": cu, "accuracy_uncapped": 2 * cu - comp, "completeness_uncapped": comp,
                 "accuracy_outliers": 0.2, "completeness_outliers": 0.08, "signed_distance_median": sd}
        _fake_run(tmp_path, "base", seed, {**base, **extra})
    old = {"chamfer_uncapped": 0.037, "accuracy_uncapped": 0.048, "completeness_uncapped": 0.0262,
           "accuracy_outliers": 0.13, "completeness_outliers": 0.004, "signed_distance_median": -0.032}
    _fake_run(tmp_path, "full", 0, dict(base), chamfer={**old, "chamfer": 0.03})
    assert set(new) <= {key for key, _, _ in METRICS}

    results = gather(tmp_path)
    with open(tmp_path / "results.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert set(new) <= set(rows[0])
    assert [float(r["completeness_uncapped"]) for r in rows] == [0.041, 0.043, 0.0262]
    assert [float(r["signed_distance_median"]) for r in rows] == [-0.043, -0.041, -0.032]
    table = {e["variant"]: e for e in json.loads((tmp_path / "results.json").read_text())["table"]}
    assert table["base"]["chamfer_uncapped"]["mean"] == pytest.approx(0.055)
    assert table["base"]["chamfer_uncapped"]["std"] == pytest.approx(0.01 / math.sqrt(2))
    assert table["full"]["completeness_outliers"]["mean"] == 0.004 and table["full"]["chamfer"]["mean"] == 0.03
    markdown = (tmp_path / "results.md").read_text()
    assert markdown == results["markdown"] + "\n"
    head, _, base_row, full_row = markdown.splitlines()[:4]
    columns = [c.strip() for c in head.strip("|").split("|")]
    cells = dict(zip(columns, [c.strip() for c in base_row.strip("|").split("|")]))
    assert {k: cells[k] for k in ("Chamfer uncapped", "completeness uncapped", "median signed distance")} == {
        "Chamfer uncapped": "0.055 ± 0.007071", "completeness uncapped": "0.042 ± 0.001414",
        "median signed distance": "-0.042 ± 0.00141"}
    assert "| 0.037 ± – | 0.0262 ± – | -0.032 ± – |" in full_row


def test_library_versions_name_a_library_that_is_not_installed_as_null(monkeypatch):
    monkeypatch.setattr(provenance_module, "RECORDED_DISTRIBUTIONS", ("numpy", "no-such-distribution-polargs"))
    versions = provenance_module.library_versions()
    assert versions == {"python": sys.version.split()[0], "numpy": np.__version__, "no-such-distribution-polargs": None}


# ---------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), *TINY]) == 0
    return out


def _check_run(folder: Path, variant: str, command: str = "demo") -> dict:
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["variant"] == variant and summary["seed"] == 0
    assert summary["init"] == summary["init_used"] == "hull"
    assert summary["train_config"]["iterations"] == 60
    assert (summary["polar_config"] is None) == (variant == "base")
    assert summary["timings"]["total"] > 0
    check_provenance(summary["provenance"], threads=1)
    assert summary["provenance"]["command"].startswith(f"polargs {command} ")  # the grid's, not the worker's
    assert summary["eval"]["normal_region"] == "object"  # the normals of the object the Chamfer measures
    # the generated scene's own maps (a dataset without them gets them ray-cast from the GT mesh)
    assert summary["eval"]["depth_source"] == "ground-truth depth maps"
    assert summary["eval"]["normal_source"] == "ground-truth normal maps"
    figures = summary["figures"]
    for key in ("chamfer", "accuracy", "completeness", "fscore", "normal_mae_deg", "psnr", "num_gaussians",
                "chamfer_uncapped", "completeness_uncapped", "signed_distance_median"):
        assert _finite(figures[key]), (key, figures[key])
    # the share of each visibility class's GT samples the mesh misses (NaN for an empty class)
    missing = [figures[f"missing_{name}"] for name in ("many", "few", "grazing")]
    assert any(_finite(m) for m in missing) and all(0 <= m <= 1 for m in missing if _finite(m)), missing
    lines = (folder / "curves.csv").read_text().strip().splitlines()
    assert lines[0].startswith("iteration,loss,psnr,num_gaussians,appended,appended_total") and len(lines) == 61
    for name in ("metrics.json", "tsdf_mesh.ply", "checkpoint.pt", "views.npz", "mesh_error.npz", "run.log"):
        assert (folder / name).is_file(), name
    assert (folder / "pc_maps.npz").is_file() == (variant == "full")
    views, error = np.load(folder / "views.npz"), np.load(folder / "mesh_error.npz")
    # the GT object's silhouette in each report view (the depth-error picture's pixels): seen,
    # and not the whole image; the vertices the evaluation measured, flagged
    for i in range(2):
        silhouette = views[f"{i}/gt_silhouette"]
        assert silhouette.dtype == bool and silhouette.shape == views[f"{i}/alpha"].shape
        assert 0 < silhouette.mean() < 1
    assert error["evaluated"].shape == error["signed_distance"].shape and error["evaluated"].any()
    # the scene folder is evaluated as `polargs eval --gt FOLDER` does: the object-only GT, with
    # the whole-scene mesh beside it hiding what it hides
    metrics = json.loads((folder / "metrics.json").read_text())
    gt, occluder = Path(metrics["gt"]), Path(metrics["occluder"])
    assert (gt.name, occluder.name) == ("gt_mesh.ply", "mesh.ply") and gt.parent == occluder.parent
    return summary


@pytest.mark.slow
def test_demo_writes_runs_results_and_report(demo_dir, capsys):
    runs = {p.name: p for p in demo_dir.iterdir() if (p / "summary.json").is_file()}
    assert set(runs) == {f"{SCENE}__base__hull__s0", f"{SCENE}__full__hull__s0"}
    for name, folder in runs.items():
        _check_run(folder, name.split("__")[1])
    for name in ("results.csv", "results.json", "results.md", "report.md", "grid.json"):
        assert (demo_dir / name).is_file(), name
    table = json.loads((demo_dir / "results.json").read_text())["table"]
    assert [e["variant"] for e in table] == ["base", "full"]
    assert all(_finite(e["chamfer"]["mean"]) for e in table)
    report = (demo_dir / "report.md").read_text()
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    kinds = {Path(p).name.split("_" + SCENE)[0] for p in pictures}
    assert kinds == {"metrics", "views", "mesh_error", "pc_inputs", "curves"}
    for picture in pictures:
        assert (demo_dir / picture).stat().st_size > 1000
    assert "polargs demo" in report and not list(demo_dir.glob(".tmp-*"))


@pytest.mark.slow
def test_ablate_resumes_and_reports_failures(demo_dir, capsys):
    """Same folder as the demo: base is skipped, reg trains, a missing dataset fails with its log;
    a second invocation trains nothing."""
    args = ["ablate", "--scenes", f"{SCENE},broken={demo_dir}/no_such_dataset", "--variants", "base,reg",
            "--out", str(demo_dir), *TINY]
    base = demo_dir / f"{SCENE}__base__hull__s0" / "summary.json"
    before = base.stat().st_mtime_ns
    capsys.readouterr()
    assert main(args) == 1
    captured = capsys.readouterr()
    assert "1 run(s) finished, 1 skipped (already done), 2 failed" in captured.out
    logs = [demo_dir / "logs" / f"broken__{v}__hull__s0.log" for v in ("base", "reg")]
    for log in logs:
        assert str(log) in captured.err and "dataset not found" in log.read_text()
        assert not (demo_dir / log.stem).exists()
    assert base.stat().st_mtime_ns == before
    _check_run(demo_dir / f"{SCENE}__reg__hull__s0", "reg", command="ablate")

    stamps = {p: p.stat().st_mtime_ns for p in demo_dir.glob("*/summary.json")}
    assert main(args) == 1
    assert "0 run(s) finished, 2 skipped (already done), 2 failed" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in demo_dir.glob("*/summary.json")} == stamps

    results = gather(demo_dir, write=False)
    assert [e["variant"] for e in results["table"]] == ["base", "reg", "full"]
    assert results["table"][2]["chamfer_vs_base"] is not None
    assert "broken__base__hull__s0" in (demo_dir / "report.md").read_text()  # listed under failed runs
    assert main(["ablate", "--out", str(demo_dir), "--gather-only", "--no-report"]) == 0
    assert "| full |" in capsys.readouterr().out


def test_sfm_init_falls_back_to_the_hull_and_says_so(tmp_path, synthetic_views):
    """6 views of 32x32 give SIFT almost nothing: the run records the fallback (no training here)."""
    pytest.importorskip("pycolmap")
    from polargs_plugin.ablation.init import MIN_SFM_POINTS, initial_points, sfm_points

    views = synthetic_views(SCENE, num_views=6, width=32, height=32)
    points, colors = sfm_points(views)
    assert points.shape[1] == colors.shape[1] == 3 and len(points) < MIN_SFM_POINTS
    cell = Cell(scene=SceneSpec(SCENE, str(tmp_path)), variant="base", seed=0, out=str(tmp_path), init="sfm")
    init_points, info = initial_points(cell, views, cell.configs()[0])
    assert init_points is None and info["init"] == "sfm" and info["init_used"] == "hull"
    assert "fell back to the visual hull" in info["init_note"]


# ------------------------------------------------------------------------ reader options
@pytest.mark.slow
def test_reader_options_reach_the_loader_and_the_summary(tmp_path, monkeypatch, capsys, synthetic_views):
    """--format / --pattern / --bit-depth / --no-pattern-check of `polargs ablate` become the cell's
    ``reader`` (plain data, JSON round trip), reach load_dataset, and are recorded in summary.json
    under "reader" as `polargs train` records them (what `polargs mesh` / `eval` re-read with)."""
    import polargs_plugin.service.data as service_data

    data = tmp_path / "data"
    data.mkdir()
    (data / "gt_mesh.ply").write_text("stands in for the GT mesh")
    views = synthetic_views("bumpy_mixed", num_views=3, width=24, height=24)
    calls, summaries = [], []

    def fake_load(spec, options):
        calls.append((spec, options.fmt, options.reader_kwargs()))
        # what a polar folder's reader reports
        return service_data.Dataset(spec, views, options.fmt, options, pattern="mono")

    summary_of = pipeline_module._summary

    def record_summary(*args):
        summaries.append(summary_of(*args))
        return summaries[-1]

    def stop_at_mesh(*args):
        raise RuntimeError("stopped before meshing")

    monkeypatch.setattr(service_data, "load_dataset", fake_load)
    monkeypatch.setattr(pipeline_module, "_summary", record_summary)
    monkeypatch.setattr(pipeline_module, "_mesh", stop_at_mesh)
    out = tmp_path / "out"
    reader_flags = ["--format", "polar", "--pattern", "mono", "--bit-depth", "12", "--no-pattern-check"]
    status = main(["ablate", "--scenes", f"mine={data}", "--variants", "base", "--out", str(out), "--jobs", "1", "--quiet",
                   "--iters", "1", "--train-set", "num_init_points=100", *reader_flags])
    assert status == 1 and "stopped before meshing" in capsys.readouterr().err
    expected = {"fmt": "polar", "pattern": "mono", "bit_depth": 12, "check_pattern": False}
    grid = json.loads((out / "grid.json").read_text())
    cells = [Cell.from_dict(c) for c in (grid["cells"] if isinstance(grid, dict) else grid)]
    assert [c.reader for c in cells] == [expected]
    assert Cell.from_dict(json.loads(json.dumps(cells[0].to_dict()))) == cells[0]
    assert cells[0].fingerprint()["reader"] == expected
    assert calls == [(str(data.resolve()), "polar", {"pattern": "mono", "bit_depth": 12, "check_pattern": False})]
    (summary,) = summaries
    assert summary["reader"] == expected and summary["dataset"] == str(data.resolve())
    assert summary["cell"]["reader"] == expected and summary["dataset_format"] == "polar"
    # a cell without reader options keeps the fingerprint of before (its partial checkpoints resume)
    assert "reader" not in Cell(scene=cells[0].scene, variant="base", seed=0, out=str(out)).fingerprint()


def test_reader_options_on_bundled_scenes_name_the_option(tmp_path, capsys):
    assert main(["ablate", "--scenes", SCENE, "--pattern", "mono", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --pattern: only for dataset folders") and SCENE in err and "\n" not in err
    assert main(["demo", "--bit-depth", "12", "--sfm", "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --bit-depth, --sfm: only for dataset folders") and "\n" not in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _children(pid: int) -> list[int]:
    """PIDs of the processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                found.append(int(stat.parent.name))
    return found


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (exited, not yet reaped)."""
    with contextlib.suppress(OSError, IndexError):
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    return False


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_a_grid_stopped_by_sigterm_leaves_no_worker_running(tmp_path):
    """SIGTERM to `polargs ablate` alone (a scheduler's timeout, `kill`): the grid stops its pool
    workers (they would otherwise train their cells to the end unseen) and waits for them, also
    for those still starting up, before it exits."""
    args = ["ablate", "--scenes", SCENE, "--variants", "base,reg", "--out", str(tmp_path / "out"),
            *[a for a in TINY if a not in ("--jobs", "1")], "--jobs", "2", "--train-set", "iterations=100000"]
    proc = subprocess.Popen([sys.executable, "-m", "polargs_plugin.cli", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        workers: list[int] = []
        while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.5)
            workers = [pid for pid in _children(proc.pid) if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()]
        assert len(workers) == 2, f"the grid did not start its two workers (exit status {proc.poll()})"
        proc.terminate()
        proc.wait(timeout=120)  # a worker still importing torch stops once it has started
        deadline = time.monotonic() + 60
        while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not [pid for pid in workers if _running(pid)]
    finally:
        for pid in [proc.pid, *_children(proc.pid)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def test_progress_shows_the_time_left_only_once_it_means_something(tmp_path):
    """Before any cell has ended and below a tenth of the work, no time is guessed; after, the
    time left is the work left at the average rate since the first training step (the set-up
    before it, scene generation and SfM, does not count)."""
    import io

    from polargs_plugin.ablation import grid

    cells = expand([SceneSpec("tiny", str(tmp_path / "tiny"))], ["base", "reg"], [0], tmp_path / "out")
    stream = io.StringIO()
    bar = grid._Progress(cells, True, stream)
    clock = [5000.0]  # a long set-up already behind us: it must not enter the rate
    bar.clock = lambda: clock[0]
    first, second = cells[0].name, cells[1].name
    iterations, extra = bar.weights[first]
    half = iterations + 2 * extra
    assert bar.bar.total == 2 * half
    assert "time left: after the first cell" in bar.bar.postfix
    bar.update(first, "train", 1, 100)  # the first training step
    started = bar.done[first]
    assert 0 < started < 0.1 * bar.bar.total and "time left: after the first cell" in bar.bar.postfix
    # the rest of the first cell takes as long as the second cell's work will at that rate: 600 s
    clock[0] += 600.0 * (half - started) / half
    bar.finish(first, True, "first cell done")
    assert bar.bar.n == half
    assert re.search(r"~10:00 left, 1/2 cells done", bar.bar.postfix), bar.bar.postfix
    bar.update(second, "mesh", 0, 1)
    bar.close()
    assert "first cell done" in stream.getvalue()


def test_progress_rate_leaves_out_a_resumed_runs_checkpoint_and_a_failed_runs_remainder(tmp_path):
    """A run resumed at half its iterations jumps the bar forward at its first step, and a failed
    run's unfinished share leaves the bar at once: the time left comes from the work done here."""
    import io

    from polargs_plugin.ablation import grid

    cells = expand([SceneSpec("tiny", str(tmp_path / "tiny"))], ["base", "reg", "full"], [0], tmp_path / "out")
    bar = grid._Progress(cells, True, io.StringIO())
    clock = [100.0]
    bar.clock = lambda: clock[0]
    resumed, failing, last = (c.name for c in cells)
    iterations, extra = bar.weights[resumed]
    cell_units = iterations + 2 * extra
    bar.update(resumed, "train", 51, 100)  # the first step after a checkpoint at iteration 50
    assert bar.bar.n == round(iterations * 0.51) and bar.worked == round(iterations * 0.51) - round(iterations * 0.5)
    worked_from = bar.worked
    clock[0] += 300.0
    bar.finish(resumed, True, "resumed cell done")  # the other half and the evaluation: 300 s
    bar.update(failing, "train", 1, 100)
    bar.finish(failing, False, "failed cell")  # its unfinished share leaves the bar, not the rate
    assert bar.bar.n == 2 * cell_units
    rate = (bar.worked - worked_from) / 300.0
    # worked here: the resumed cell's second half and evaluation, the failed cell's first step
    assert bar.worked - worked_from == cell_units - round(iterations * 0.51) + round(iterations * 0.01)
    expected = bar.bar.format_interval(cell_units / rate)
    assert f"~{expected} left, 1/3 cells done" in bar.bar.postfix, (expected, bar.bar.postfix)
    # a rate over everything the bar moved would say far less (the old estimate)
    assert bar.bar.format_interval(cell_units / ((bar.bar.n - round(iterations * 0.51)) / 300.0)) != expected
    bar.close()
