"""The plug-in ablation (``polargs ablate --trainer NAME=CHECKOUT``; docs/adapters/plugin-ablation.md).

For each scene, an upstream trainer's own training script runs to the end of its own schedule
shrunk by a factor (:func:`~polargs_plugin.dryrun.trainers.shrunk_schedule_arguments`; numbers
its script holds as literals are scaled in the copy that runs), on the CPU with the dry run's
stand-ins of its CUDA extensions, twice: unpatched ("alone") and patched ("polargs", with the
CPU preset's PolarGS schedule at the same factor). The Gaussians each run saves
(``point_cloud/iteration_N/point_cloud.ply``) are read back, rendered with the reference
rasterizer, fused by the same TSDF as every ablation run and evaluated against the scene's
ground truth: capped and visible-surface Chamfer, normal MAE, Gaussians, and Dense's rows still
alive at the end. The checkout is never written: both scripts are copies in the output folder.

Resumable: a cell (scene x variant) is done when its ``cell.json`` exists (written last,
atomically); a command run again skips done cells.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from polargs_plugin.io import PolarInputError, atomic_write, write_json
from polargs_plugin.kit.patching import strip_marked
from polargs_plugin.service.dryrun import environment, free_port, launch_trainer, train_script
from polargs_plugin.service.provenance import provenance

__all__ = ["PluginRequest", "VARIANTS", "plugin_ablation", "plugin_settings", "plugin_table", "CELL_NAME"]

#: The two runs of every scene: the trainer's own loop, and the same loop patched with PolarGS.
VARIANTS = ("alone", "polargs")

#: A finished cell's record (its presence marks the cell done).
CELL_NAME = "cell.json"

#: Figures a cell records, with the table's labels.
_FIGURES = (("chamfer", "Chamfer"), ("chamfer_visible", "visible Chamfer"), ("normal_mae_deg", "normal MAE (deg)"),
            ("gaussians", "Gaussians"), ("dense_rows_final", "Dense rows at the end"))


@dataclass(frozen=True)
class PluginRequest:
    """One plug-in ablation.

    Attributes:
        trainer: a name of :data:`polargs_plugin.dryrun.trainers.TRAINERS` (the graphdeco family).
        checkout: the trainer's checkout, its training script patched by ``adapters/<name>/patch.py``.
        out: the output folder (scenes, runs, ``results.json``, ``results.md``).
        scenes: bundled scene names or ``family:K``.
        variants: which of :data:`VARIANTS` to run (two commands on one ``out`` may run one each,
            at the same time: the results gather every done cell of ``out``).
        factor: the schedule factor (iterations and every iteration count of the upstream schedule
            times this; 1/6: 30000 -> 5000, the CPU preset's).
        views, width, height: size of a bundled scene (a family scene has its own).
        timeout: seconds each training may take.
        train_arguments: more training-script arguments, after the schedule's (they win).
        eval_samples: points sampled per mesh for the Chamfer distance.
        polar_overrides: PolarConfig fields set on the patched run's settings (nested dict, as
            ``--polar-set`` gives them), after the schedule's.
        command: the command line, recorded in ``results.json``.
    """

    trainer: str
    checkout: Path
    out: Path
    scenes: tuple[str, ...] = ("bumpy_mixed",)
    variants: tuple[str, ...] = VARIANTS
    factor: float = 1 / 6
    views: int = 24
    width: int = 128
    height: int = 128
    timeout: float = 6 * 3600.0
    train_arguments: tuple[str, ...] = ()
    eval_samples: int = 1_000_000
    polar_overrides: dict[str, Any] = field(default_factory=dict)
    command: str | None = None


def plugin_settings(factor: float, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The PolarGS settings of the patched run (``POLARGS_CONFIG`` over the synthetic preset): the
    fields in which a reference run's PolarConfig at the vanilla schedule ``factor`` differs from
    the preset (the CPU preset's schedules: Dense's window and interval, L_dn's start, L_n's end),
    with ``overrides`` (``--polar-set``, checked here) set after them."""
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.service.configs import changed_fields, polar_config

    config = polar_config("synthetic", factor, overrides, "--polar-set")
    return {"polar": changed_fields(PolarConfig.synthetic().to_dict(), config.to_dict())}


def _scene_request(name: str, request: PluginRequest):
    from polargs_plugin.data.family import family_name, parse_family
    from polargs_plugin.service.scenes import SceneRequest

    if name.startswith("family:"):
        seed = parse_family(name)
        if seed is None or seed < 0:
            raise PolarInputError("--scenes", f"scene {name!r}: a family scene is family:SEED with SEED an integer >= 0")
        return SceneRequest("family", seed=seed), family_name(seed)
    return SceneRequest(name, views=request.views, width=request.width, height=request.height), name


def _scene_folder(name: str, request: PluginRequest) -> Path:
    """The scene's folder under ``out/scenes`` (made once, with its COLMAP export)."""
    from polargs_plugin.service.scenes import generate_scene_folder

    scene, label = _scene_request(name, request)
    folder = request.out / "scenes" / label
    if not (folder / "colmap" / "sparse" / "0" / "cameras.txt").is_file():
        try:
            generate_scene_folder(scene, folder, overwrite=folder.exists(), export="colmap")
        except ValueError as err:  # an unknown scene name, a bad size
            raise PolarInputError("--scenes", str(err)) from None
    return folder


def _scripts(request: PluginRequest) -> tuple[dict[str, Path], list[str]]:
    """The two training scripts (copies in ``out``): the checkout's patched one and its unpatched
    form, each with its literal iteration numbers scaled; and the statements not found."""
    from polargs_plugin.dryrun.trainers import TRAINERS, shrink_literals

    script, text = train_script(request.checkout, request.trainer)
    spec = TRAINERS[request.trainer]
    missing = shrink_literals(spec, text, request.factor)[1]  # the patch leaves those statements alone
    scripts = {}
    for variant, source in (("polargs", text), ("alone", strip_marked(text))):
        shrunk = shrink_literals(spec, source, request.factor)[0]
        path = request.out / f"{script.stem}_{variant}.py"
        with atomic_write(path) as handle:
            handle.write(shrunk)
        scripts[variant] = path
    return scripts, missing


def _saved_ply(model_path: Path) -> Path:
    """The Gaussians of the run's last save (``point_cloud/iteration_N/point_cloud.ply``, largest N)."""
    saves = sorted((int(p.parent.name.removeprefix("iteration_")), p)
                   for p in model_path.glob("point_cloud/iteration_*/point_cloud.ply")
                   if p.parent.name.removeprefix("iteration_").isdigit())
    if not saves:
        raise PolarInputError(model_path, "the trainer saved no point_cloud/iteration_N/point_cloud.ply")
    return saves[-1][1]


def evaluate_saved(ply: Path, scene: Path, cell: Path, eval_samples: int = 1_000_000) -> dict[str, Any]:
    """Read the trainer's saved Gaussians, mesh them (TSDF over the reference rasterizer's renders
    of the scene's views, the ablation's settings) and evaluate the mesh against the scene's
    ground truth; the mesh goes to ``cell/tsdf_mesh.ply``."""
    from statistics import mean

    from polargs_plugin.backends.reference.model import GaussianModel
    from polargs_plugin.kit.ply import read_gaussian_ply
    from polargs_plugin.mesh import write_mesh
    from polargs_plugin.service.data import load_dataset
    from polargs_plugin.service.evaluation import EvalSettings, evaluate, normal_errors
    from polargs_plugin.service.mesh import MeshSettings, fuse_model

    raw = read_gaussian_ply(ply)
    if len(raw["means"]) == 0:
        raise PolarInputError(ply, "holds no Gaussians: the trainer pruned them all (see its log)")
    model = GaussianModel(dict(raw), sh_degree=raw.sh_degree)
    views = load_dataset(str(scene)).views
    mesh_path = write_mesh(cell / "tsdf_mesh.ply", fuse_model(model, views, MeshSettings(), source=str(cell)).mesh)
    chamfer = evaluate(mesh_path, EvalSettings(gt=scene, views=str(scene), num_samples=eval_samples))["chamfer"]
    per_view = normal_errors(model, views)
    return {"chamfer": chamfer["chamfer"], "chamfer_visible": chamfer.get("chamfer_visible"),
            "normal_mae_deg": mean(per_view.values()) if per_view else None, "gaussians": model.num,
            "ply": str(ply)}


def _run_cell(request: PluginRequest, scene: Path, variant: str, scripts: dict[str, Path], settings: Path,
              say: Callable[[str], None]) -> dict[str, Any]:
    from polargs_plugin.dryrun.trainers import TRAINERS, shrunk_schedule_arguments

    cell = request.out / "runs" / f"{scene.name}__{variant}"
    done = cell / CELL_NAME
    if done.is_file():
        return json.loads(done.read_text())
    cell.mkdir(parents=True, exist_ok=True)
    spec = TRAINERS[request.trainer]
    model_path = cell / "model"
    arguments = ["-s", str(scene / "colmap"), "-m", str(model_path), "--port", str(free_port()),
                 *shrunk_schedule_arguments(spec, request.factor), *request.train_arguments]
    iterations = arguments[arguments.index("--iterations") + 1]
    say(f"{scene.name} / {variant}: {request.trainer}'s {scripts[variant].name}, {iterations} iterations")
    start = time.perf_counter()
    report, log = launch_trainer(request.trainer, request.checkout, scripts[variant], arguments, model_path, cell,
                                 "train", environment(scene, settings), request.timeout)
    seconds = time.perf_counter() - start
    if not report.get("finished"):
        raise PolarInputError(log, f"{scene.name} / {variant} did not finish: {report.get('error') or 'see the log'}")
    figures = evaluate_saved(_saved_ply(model_path), scene, cell, request.eval_samples)
    record = {"scene": scene.name, "variant": variant, "trainer": request.trainer, "train_seconds": seconds,
              "iterations": report.get("iterations"), "dense_appended": sum(c for _, c in report.get("dense_rounds") or []),
              "dense_rows_final": report.get("dense_rows_final") if variant == "polargs" else None, **figures}
    write_json(done, record)
    return record


def plugin_ablation(request: PluginRequest, progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Run every scene alone and with PolarGS (module docstring); returns this call's cells' records (a
    failed cell's holds ``error``: a run that did not finish, naming its log, or saved no
    Gaussians; the other cells go on) and writes ``out/results.json`` and ``out/results.md`` over
    every done cell of ``out`` and this call's failures.

    Raises:
        PolarInputError: a trainer outside the graphdeco family, a factor outside (0, 1], a bad
            ``--polar-set`` field or value, an unknown scene, the dry run's refusals of the checkout
            (unpatched, missing modules, ...).
    """
    from polargs_plugin.dryrun.trainers import TRAINERS

    say = progress or (lambda message: None)
    request = replace(request, checkout=request.checkout.resolve(), out=request.out.resolve())
    if request.trainer in TRAINERS and TRAINERS[request.trainer].family != "inria":
        raise PolarInputError("--trainer", f"{request.trainer}: the plug-in ablation runs the graphdeco family "
                                           "(graphdeco, graphdeco-2023, gof, pgsr, 2dgs)")
    if not request.variants or not set(request.variants) <= set(VARIANTS):
        raise PolarInputError("--variants", f"choose among {', '.join(VARIANTS)}, got {', '.join(request.variants) or 'none'}")
    if not 0 < request.factor <= 1:
        raise PolarInputError("--factor", f"must be in (0, 1], got {request.factor}")
    request.out.mkdir(parents=True, exist_ok=True)
    scripts, missing = _scripts(request)
    for statement in missing:
        say(f"note: {scripts['polargs'].name} holds no `{statement}`: left unscaled")
    settings = request.out / "polargs_settings.json"
    write_json(settings, plugin_settings(request.factor, request.polar_overrides))
    scenes = [_scene_folder(name, request) for name in request.scenes]  # a bad name fails before any training
    records = []
    for scene in scenes:
        for variant in request.variants:
            try:
                records.append(_run_cell(request, scene, variant, scripts, settings, say))
            except PolarInputError as err:  # the other cells go on; a later command retries this one
                say(f"FAILED {scene.name} / {variant}: {err}")
                records.append({"scene": scene.name, "variant": variant, "trainer": request.trainer, "error": str(err)})
    failed = [r for r in records if "error" in r]
    cells = [json.loads(p.read_text()) for p in sorted((request.out / "runs").glob(f"*/{CELL_NAME}"))] + failed
    write_json(request.out / "results.json", {
        "request": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(request).items()},
        "cells": cells, "unscaled_statements": missing, "provenance": provenance(request.command)})
    with atomic_write(request.out / "results.md") as handle:
        handle.write("\n".join(plugin_table(cells)) + "\n")
    return records


def _relative(value: float | None, reference: float | None) -> str:
    if value is None or reference is None or reference == 0:
        return "n/a"
    return f"{100.0 * (value / reference - 1.0):+.1f} %"


def plugin_table(records: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown rows: per scene, the trainer alone, with PolarGS and the change, for each figure;
    a scene with a failed cell gets one row naming the failure instead."""
    by_cell = {(r["scene"], r["variant"]): r for r in records}
    scenes = list(dict.fromkeys(r["scene"] for r in records))
    lines = ["| scene | figure | alone | + PolarGS | change |", "|---|---|---|---|---|"]
    for scene in scenes:
        failed = [f"{v}: {by_cell[(scene, v)]['error']}" for v in VARIANTS if "error" in by_cell.get((scene, v), {})]
        if failed:
            lines.append(f"| {scene} | failed | {'; '.join(failed)} | | |")
            continue
        alone, polar = by_cell.get((scene, "alone"), {}), by_cell.get((scene, "polargs"), {})
        for key, label in _FIGURES:
            a, p = alone.get(key), polar.get(key)
            shown = [("n/a" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)) for v in (a, p)]
            change = _relative(p, a) if key != "dense_rows_final" else ""
            lines.append(f"| {scene} | {label} | {shown[0]} | {shown[1]} | {change} |")
    return lines
