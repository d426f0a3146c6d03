"""The work of one ablation run: train, mesh, evaluate and write the report data into a folder.

:func:`run_pipeline` is what :func:`~polargs_plugin.ablation.cell.run_cell` runs inside the run's
temporary folder; the commands it stands for are `polargs train`, `polargs mesh` and `polargs eval`
with the cell's settings, so a run folder reads back with them.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import platform
import shutil
import time
from pathlib import Path
from typing import Any

from polargs_plugin.ablation.artifacts import CURVES_NAME, EVAL_CULL_DILATION, write_curves, write_report_data
from polargs_plugin.ablation.figures import eval_record, run_figures
from polargs_plugin.ablation.init import initial_points
from polargs_plugin.ablation.resume import Progress, final_loss, make_trainer, plain, resume
from polargs_plugin.ablation.scenes import ensure_scene, gt_mesh_path
from polargs_plugin.ablation.spec import Cell
from polargs_plugin.ablation.variants import DEFAULT_FACTOR, describe
from polargs_plugin.io import PolarInputError, write_json
from polargs_plugin.service.provenance import provenance
from polargs_plugin.service.runs import CHECKPOINT_NAME, MESH_NAME, METRICS_NAME, SUMMARY_NAME

__all__ = ["RUN_FORMAT", "run_pipeline", "now"]

RUN_FORMAT = "polargs-ablation-run-v1"


def now() -> str:
    """The local time, ISO 8601 to the second with its offset."""
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


class _Clock:
    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.last = self.start
        self.times: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.times[name] = round(now - self.last, 3)
        self.last = now

    def total(self) -> dict[str, float]:
        return {**self.times, "total": round(time.perf_counter() - self.start, 3)}


def run_pipeline(cell: Cell, tmp: Path, report: Progress) -> dict[str, Any]:
    """Train, mesh, evaluate and write the report data of ``cell`` into ``tmp``; its summary."""
    import torch

    from polargs_plugin.service.data import DATASET_NOT_FOUND, ReaderOptions, load_dataset

    started = now()
    if cell.threads > 0:
        torch.set_num_threads(cell.threads)
    clock = _Clock()
    report("scene", 0, 1)
    folder = ensure_scene(cell.scene)
    if not folder.exists():
        raise PolarInputError(folder, DATASET_NOT_FOUND)
    gt_mesh = gt_mesh_path(cell.scene)
    clock.lap("scene")
    dataset = load_dataset(str(folder), ReaderOptions(**cell.reader))
    if dataset.pattern:
        print(f"raw mosaics: {dataset.pattern}", flush=True)
    if dataset.sfm_model:
        print(f"SfM: model written to {dataset.sfm_model}", flush=True)
    clock.lap("load")
    trainer, train_cfg, polar_cfg, figures, init_info = _train(cell, dataset.views, tmp, report, clock)
    summary = _summary(cell, folder, dataset, gt_mesh, trainer, train_cfg, polar_cfg, init_info)
    report("mesh", 0, 1)
    _mesh(cell, trainer, dataset.views, tmp)
    clock.lap("mesh")
    report("eval", 0, 1)
    # a scene folder is handed over as `polargs eval --gt FOLDER` takes it: with its whole-scene
    # mesh.ply beside gt_mesh.ply as the occluder; a GT given as NAME=PATH:GT_MESH has none
    eval_gt = gt_mesh if cell.scene.gt_mesh else gt_mesh.parent
    metrics, cull = _evaluate(cell, trainer, dataset, summary, tmp, eval_gt)
    clock.lap("eval")
    report("pictures", 0, 1)
    from polargs_plugin.service.evaluation import gt_meshes

    write_report_data(trainer, tmp, *gt_meshes(eval_gt), cull)
    clock.lap("pictures")
    summary.update(
        provenance=provenance(cell.command),
        started=started,
        finished=now(),
        timings=clock.total(),
        figures=run_figures(metrics, figures, trainer.curve),
        eval=eval_record(metrics, cull, int(cell.eval.get("num_samples", 1_000_000))),
        files=sorted(p.name for p in tmp.iterdir() if p.name != SUMMARY_NAME) + [SUMMARY_NAME],
    )
    write_json(tmp / SUMMARY_NAME, summary)
    print(f"finished {cell.name}: {json.dumps(summary['figures'])}", flush=True)
    return summary


def _train(cell: Cell, views: list, tmp: Path, report: Progress, clock: "_Clock"):
    """Build the cell's trainer, resume its partial checkpoint if any, train; copy the final
    checkpoint into ``tmp`` and write the curves. (trainer, TrainConfig, PolarConfig, figures, init record)."""
    from polargs_plugin.service.configs import resolve_device

    train_cfg, polar_cfg = cell.configs()
    device = resolve_device(cell.device)
    train_cfg.device, train_cfg.progress = device, False
    if polar_cfg is not None and polar_cfg.cache_dir is None:
        polar_cfg.cache_dir = str(Path(cell.out) / "cache" / "polar_maps")
    init_points, init_info = initial_points(cell, views, train_cfg)
    clock.lap("init")
    trainer = make_trainer(views, train_cfg, polar_cfg, init_points, report)
    partial = cell.partial_dir
    try:
        resumed = resume(cell, trainer, partial)
    except Exception as err:  # unreadable or inconsistent: start over with a fresh trainer
        print(f"resume: cannot resume from {partial} ({type(err).__name__}: {err}); starting over", flush=True)
        with contextlib.suppress(FileNotFoundError):
            (partial / CHECKPOINT_NAME).unlink()
        trainer, resumed = make_trainer(views, train_cfg, polar_cfg, init_points, report), False
    every = cell.checkpoint_every
    if every is None:
        from polargs_plugin.service.train import checkpoint_interval

        every = checkpoint_interval(None, train_cfg.iterations)
    trainer.partial = (partial, plain(cell.fingerprint()))
    print(f"training {cell.variant} ({describe(cell.variant)}), {train_cfg.iterations} iterations on {device}"
          + (f", resumed at iteration {trainer.iteration}" if resumed else ""), flush=True)
    figures = trainer.train(checkpoint=partial / CHECKPOINT_NAME, checkpoint_every=every)
    shutil.copyfile(partial / CHECKPOINT_NAME, tmp / CHECKPOINT_NAME)
    figures["seconds"] = trainer.train_seconds()
    figures["loss"] = final_loss(trainer.curve, train_cfg.log_every)  # the same whether resumed or not
    clock.lap("train")
    write_curves(tmp / CURVES_NAME, trainer.curve)
    return trainer, train_cfg, polar_cfg, figures, {**init_info, "device": device}


def _summary(cell: Cell, folder: Path, dataset, gt_mesh: Path, trainer, train_cfg, polar_cfg,
             init_info: dict[str, Any]) -> dict[str, Any]:
    """The run's summary before meshing (the settings; the figures come after the evaluation)."""
    import torch

    device = init_info.pop("device")
    return {
        "format": RUN_FORMAT,
        "name": cell.name,
        "dataset": str(folder),  # what `polargs mesh` / `polargs eval` read
        "dataset_format": dataset.format,
        "reader": dataset.record(),  # ... and how: service.load_dataset(dataset, ReaderOptions(**reader))
        "scene": cell.scene.to_dict(),
        "variant": cell.variant,
        "variant_description": describe(cell.variant),
        "seed": cell.seed,
        "preset": cell.preset,
        "factor": DEFAULT_FACTOR if cell.factor is None and cell.preset == "cpu" else cell.factor,
        "num_views": len(dataset.views),
        **init_info,
        "device": device,
        "device_name": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else platform.processor() or None,
        "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"),
        "resumed_from": trainer.resumes,
        "gt_mesh": str(gt_mesh),
        "cell": cell.to_dict(),  # the plain description that reproduces the run (run_cell)
        "train_config": train_cfg.to_dict(),
        "polar_config": None if polar_cfg is None else polar_cfg.to_dict(),
    }


def _trained_model(trainer):
    """The trained Gaussians as a run folder's checkpoint holds them (what `polargs mesh` renders)."""
    from polargs_plugin.backends.reference.model import GaussianModel

    return GaussianModel.from_checkpoint(trainer.model.checkpoint())


def _mesh(cell: Cell, trainer, views: list, tmp: Path) -> None:
    """tsdf_mesh.ply (and its settings) in canonical order, as `polargs mesh` with the cell's settings."""
    from polargs_plugin.mesh import canonical_mesh_order
    from polargs_plugin.service.mesh import MeshSettings, fuse_model, write_mesh_result

    settings = MeshSettings(preset=cell.mesh.get("preset", "synthetic"), voxel=cell.mesh.get("voxel"),
                            sdf_trunc=cell.mesh.get("sdf_trunc"), depth_trunc=cell.mesh.get("depth_trunc"),
                            alpha_threshold=cell.mesh.get("alpha_threshold", 0.5),
                            min_cluster=cell.mesh.get("min_cluster", 0.05),
                            incidence_trunc=cell.mesh.get("incidence_trunc", MeshSettings.incidence_trunc),
                            partial_alpha=cell.mesh.get("partial_alpha", MeshSettings.partial_alpha),
                            spare_pieces_in_masks=cell.mesh.get("spare_pieces_in_masks", MeshSettings.spare_pieces_in_masks))
    result = fuse_model(_trained_model(trainer), views, settings, source=str(_published(tmp, tmp, cell)))
    write_mesh_result(result, tmp / MESH_NAME)
    canonical_mesh_order(tmp / MESH_NAME)


def _evaluate(cell: Cell, trainer, dataset, summary: dict[str, Any], tmp: Path, eval_gt: Path) -> tuple[dict[str, Any], bool]:
    """metrics.json, as `polargs eval --gt --normals` (views without GT depth maps or normals get the
    ones ray-cast from the GT mesh); (metrics, culled)."""
    from polargs_plugin.service.evaluation import EvalSettings, evaluate, write_metrics
    from polargs_plugin.service.runs import Run

    cull = bool(cell.eval.get("cull", True))
    settings = EvalSettings(gt=eval_gt, normals=True,
                            num_samples=int(cell.eval.get("num_samples", 1_000_000)),
                            units=cell.eval.get("units", "scene units"), cull=cull, cull_dilation=EVAL_CULL_DILATION)
    metrics = evaluate(tmp, settings, run=Run(tmp, _trained_model(trainer), dataset, summary))
    metrics = _published(metrics, tmp, cell)
    write_metrics(metrics, tmp / METRICS_NAME)
    return metrics, cull


def _published(value: Any, tmp: Path, cell: Cell) -> Any:
    """``value`` (a path, or JSON data holding paths) with the paths into the temporary folder
    ``tmp`` made to point into the run folder it becomes, as an absolute path."""
    if isinstance(value, dict):
        return {key: _published(item, tmp, cell) for key, item in value.items()}
    if isinstance(value, list):
        return [_published(item, tmp, cell) for item in value]
    if isinstance(value, (str, Path)):
        path, base = os.path.abspath(value), os.path.abspath(tmp)
        if path == base or path.startswith(base + os.sep):
            published = os.path.normpath(os.path.join(os.path.abspath(cell.run_dir), os.path.relpath(path, base)))
            return Path(published) if isinstance(value, Path) else published
    return value
