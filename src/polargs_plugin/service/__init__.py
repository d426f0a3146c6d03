"""The service layer: plain functions under the ``polargs`` commands, the ablation runner, the
examples and the adapters.

Each takes and returns typed objects and prints nothing (notes go to a ``notify`` callback,
progress bars only where asked); errors are one-line
:class:`~polargs_plugin.io.PolarInputError` naming the file, option or setting.

==========================  ===================================================================
read a dataset              :func:`load_dataset` with :class:`ReaderOptions` -> :class:`Dataset`
build the settings          :func:`read_settings`, :func:`polar_config`, :func:`train_config`
fingerprint data            :func:`fingerprint`, :func:`compare_fingerprints`
prepare the maps cache      :func:`prepare_maps_cache` -> :class:`MapsCache`; :func:`preprocess`
generate a bundled scene    :func:`generate_scene_folder` with :class:`SceneRequest`
a patched trainer's inputs  :func:`adapter_inputs` (``POLARGS_DATA`` ...)
train a run                 :func:`train_run` with :class:`TrainRequest` -> :class:`TrainResult`
read a run back             :func:`load_run` -> :class:`Run`
mesh a run                  :func:`mesh_run`, :func:`fuse_model` with :class:`MeshSettings`
evaluate a run or a mesh    :func:`evaluate` with :class:`EvalSettings`, :func:`write_metrics`
==========================  ===================================================================

Example::

    from polargs_plugin import service

    dataset = service.load_dataset("scenes/gps")
    request = service.TrainRequest(dataset="scenes/gps", out=Path("runs/full"),
                                   train=service.train_config("cpu"), polar=service.polar_config("synthetic", 1 / 6))
    service.train_run(request)
    run = service.load_run("runs/full")
    service.mesh_run(run)
    metrics = service.evaluate(Path("runs/full"), service.EvalSettings(gt=Path("scenes/gps"), normals=True))
"""

from polargs_plugin.service.adapters import ENV_DATA, AdapterInputs, adapter_inputs
from polargs_plugin.service.configs import (
    PRESETS, SCHEDULES, SWITCHES, Settings, apply_overrides, config_from_environment, polar_config, read_settings,
    resolve_device, train_config,
)
from polargs_plugin.service.data import Dataset, ReaderOptions, load_dataset, options_from_record
from polargs_plugin.service.evaluation import EvalSettings, evaluate, gt_meshes, metrics_path, write_metrics
from polargs_plugin.service.fingerprints import compare_fingerprints, fingerprint
from polargs_plugin.service.maps import MapsCache, Preprocessed, maps_entries, prepare_maps_cache, preprocess
from polargs_plugin.service.mesh import MeshResult, MeshSettings, fuse_model, mesh_run, write_mesh_result
from polargs_plugin.service.runs import Run, load_run, read_summary
from polargs_plugin.service.scenes import GeneratedScene, SceneRequest, generate_scene_folder, scene_statistics
from polargs_plugin.service.train import (
    StopRequest, TrainingInterrupted, TrainRequest, TrainResult, build_trainer, train_run,
)

__all__ = [
    "ENV_DATA", "AdapterInputs", "adapter_inputs",
    "PRESETS", "SCHEDULES", "SWITCHES", "Settings", "apply_overrides", "config_from_environment", "polar_config",
    "read_settings", "resolve_device", "train_config",
    "Dataset", "ReaderOptions", "load_dataset", "options_from_record",
    "EvalSettings", "evaluate", "gt_meshes", "metrics_path", "write_metrics",
    "compare_fingerprints", "fingerprint",
    "MapsCache", "Preprocessed", "maps_entries", "prepare_maps_cache", "preprocess",
    "MeshResult", "MeshSettings", "fuse_model", "mesh_run", "write_mesh_result",
    "Run", "load_run", "read_summary",
    "GeneratedScene", "SceneRequest", "generate_scene_folder", "scene_statistics",
    "StopRequest", "TrainingInterrupted", "TrainRequest", "TrainResult", "build_trainer", "train_run",
]
