"""Settings a user can trust: every constrained field refuses a bad value when the config is built,
in one line naming the field, the value and what is allowed — from Python (constructors,
``from_dict``, ``update``, the hooks' and the trainer's door) and from the command line
(``polargs train --config``, ``polargs ablate --polar-set / --train-set``)."""

from __future__ import annotations

import json
import re
import typing
from dataclasses import fields, is_dataclass

import pytest
import torch

from polargs_plugin.backends.reference.model import LearningRates
from polargs_plugin.backends.reference.strategy import DensityConfig
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.cli import main
from polargs_plugin.config import (
    AzimuthModel,
    CorrectionConfig,
    DensifyConfig,
    FilterConfig,
    IntermediateDolp,
    LossConfig,
    NccBackend,
    PatchMatchConfig,
    PolarConfig,
    polar_schedule_factor,
)
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.threads import ThreadPolicy
from polargs_plugin.types import View

# (root, dotted path, a bad value of the field's own type, what the message says is allowed).
# "{parent}" stands for the path of the field's config ("densify." from PolarConfig, "" from
# DensifyConfig itself).
BAD_VALUES = [
    ("polar", "correction.specular_dolp", (0.9, 0.3), "a pair (low, high) with 0 <= low <= high <= 1"),
    ("polar", "correction.overexposed_dolp", (-0.1, 0.1), "a pair (low, high) with 0 <= low <= high <= 1"),
    ("polar", "correction.intensity_range", (0.6, 1.5), "a pair (low, high) with 0 <= low <= high <= 1"),
    ("polar", "correction.mahalanobis_threshold", 0.0, "> 0"),
    ("polar", "correction.propagation_radius", -1, "a non-negative integer"),
    ("polar", "correction.propagation_step", 0, "a positive integer"),
    ("polar", "correction.pri_saturation", 0.0, "in (0, 1]"),
    ("polar", "correction.rho_d", -1.0, "> 0 or null"),
    ("polar", "correction.white_level", 0.0, "> 0"),
    ("polar", "correction.stokes_tolerance", -0.01, ">= 0"),
    ("polar", "correction.max_impossible_fraction", 1.5, "in [0, 1]"),
    ("polar", "losses.lambda_ref", -1.0, ">= 0"),
    ("polar", "losses.alpha_normal", -0.1, ">= 0"),
    ("polar", "losses.beta_depth_normal", -0.05, ">= 0"),
    ("polar", "losses.gamma_scale", -50.0, ">= 0"),
    ("polar", "losses.ssim_weight", 1.2, "in [0, 1]"),
    ("polar", "losses.depth_normal_from_iter", -1, "a non-negative integer"),
    ("polar", "losses.normal_until_after_dense", -1, "a non-negative integer or null"),
    ("polar", "losses.normal_hold_deg", 0.0, "in (0, 180] degrees or null"),
    ("polar", "losses.normal_hold_deg", 200.0, "in (0, 180] degrees or null"),
    ("polar", "losses.alpha_polar_normal", -0.1, ">= 0"),
    ("polar", "losses.polar_normal_min_dolp", 1.5, "in [0, 1]"),
    ("polar", "losses.polar_normal_zenith_min_dolp", -0.05, "in [0, 1]"),
    ("polar", "losses.polar_normal_refractive_index", 1.0, "> 1"),
    ("polar", "densify.start_iter", -1, "a non-negative integer"),
    ("polar", "densify.end_iter", 500, ">= {parent}start_iter (1000)"),
    ("polar", "densify.interval", 0, "a positive integer"),
    ("polar", "densify.interval", -100, "a positive integer"),
    ("polar", "densify.stride", 0, "a positive integer"),
    ("polar", "densify.max_new_per_call", -1, "a non-negative integer"),
    ("polar", "densify.budget_fraction", -0.1, ">= 0 or null"),
    ("polar", "densify.initial_opacity", 1.0, "in (0, 1)"),
    ("polar", "densify.alpha_threshold", -0.1, "in [0, 1]"),
    ("polar", "densify.seed_depth_footprints", -0.5, ">= 0"),
    ("polar", "densify.seed_max_plane_deviation", -0.04, ">= 0 or null"),
    ("polar", "densify.thin_scale_ratio", 0.0, "in (0, 1]"),
    ("polar", "densify.patchmatch.num_sources", 0, "a positive integer"),
    ("polar", "densify.patchmatch.iterations", -1, "a non-negative integer"),
    ("polar", "densify.patchmatch.window_radius", 0, "a positive integer"),
    ("polar", "densify.patchmatch.window_radius", -5, "a positive integer"),
    ("polar", "densify.patchmatch.window_step", 0, "a positive integer"),
    ("polar", "densify.patchmatch.sigma_color", 0.0, "> 0"),
    ("polar", "densify.patchmatch.lambda_aolp", -0.02, ">= 0"),
    ("polar", "densify.patchmatch.lambda_normal_depth", -0.05, ">= 0"),
    ("polar", "densify.patchmatch.tau", 0.0, "> 0"),
    ("polar", "densify.patchmatch.sigma_dolp", -0.5, "> 0"),
    ("polar", "densify.patchmatch.depth_perturbation", 1.0, "in [0, 1)"),
    ("polar", "densify.patchmatch.top_k_sources", 0, "a positive integer"),
    ("polar", "densify.patchmatch.propagation_distances", (1, 2), "a non-empty list of odd positive integers"),
    ("polar", "densify.patchmatch.propagation_distances", (), "a non-empty list of odd positive integers"),
    ("polar", "densify.patchmatch.refine_depth_range", -0.05, ">= 0"),
    ("polar", "densify.patchmatch.refine_normal_deg", 181.0, "in [0, 180] degrees"),
    ("polar", "densify.patchmatch.chunk_elements", 0, "a positive integer"),
    ("polar", "densify.filters.max_reprojection_px", -1.0, ">= 0"),
    ("polar", "densify.filters.max_relative_depth", -0.01, ">= 0"),
    ("polar", "densify.filters.min_consistent_views", -1, "a non-negative integer"),
    ("polar", "densify.filters.max_polar_residual", -0.3, ">= 0"),
    ("polar", "densify.filters.polar_dolp_reference", 0.0, "> 0"),
    ("polar", "densify.filters.max_photometric_cost", 2.5, "in [0, 2]"),
    ("polar", "densify.filters.max_incidence_deg", 0.0, "in (0, 90] or null"),
    ("polar", "densify.filters.max_incidence_deg", 95.0, "in (0, 90] or null"),
    ("train", "iterations", 0, "a positive integer"),
    ("train", "iterations", -10, "a positive integer"),
    ("train", "schedule_scale", 0.0, "> 0"),
    ("train", "sh_degree", 4, "an integer in [0, 3]"),
    ("train", "sh_increase_every", 0, "a positive integer"),
    ("train", "background", (0.0, 1.5, 0.0), "a list of numbers each in [0, 1]"),
    ("train", "mask_edge_band", -1, "a non-negative integer"),
    ("train", "num_init_points", 0, "a positive integer"),
    ("train", "init_resolution", 0, "a positive integer"),
    ("train", "initial_opacity", 0.0, "in (0, 1)"),
    ("train", "eps2d", -0.3, ">= 0"),
    ("train", "tile_size", 0, "a positive integer"),
    ("train", "device", "gpu", "a torch device such as 'cpu' or 'cuda:0'"),
    ("train", "log_every", 0, "a positive integer"),
    ("train", "lrs.means_init", -1.6e-4, ">= 0"),
    ("train", "lrs.means_final", 0.0, "> 0 while means_init is > 0 (0 only together with it)"),
    ("train", "lrs.means_delay_mult", 1.5, "in [0, 1]"),
    ("train", "lrs.means_delay_steps", -1, "a non-negative integer"),
    ("train", "lrs.means_max_steps", 0, "a positive integer"),
    ("train", "lrs.sh_dc", -2.5e-3, ">= 0"),
    ("train", "lrs.sh_rest", -1e-4, ">= 0"),
    ("train", "lrs.opacity_logits", -0.025, ">= 0"),
    ("train", "lrs.log_scales", -5e-3, ">= 0"),
    ("train", "lrs.quats", -1e-3, ">= 0"),
    ("train", "density.grow_grad2d", -2e-4, ">= 0"),
    ("train", "density.grow_scale3d", -0.01, ">= 0"),
    ("train", "density.split_samples", 0, "a positive integer"),
    ("train", "density.split_scale_divisor", 0.0, "> 0"),
    ("train", "density.prune_opa", 1.0, "in [0, 1)"),
    ("train", "density.prune_scale3d", 0.0, "> 0"),
    ("train", "density.prune_screen_px", -20.0, "> 0"),
    ("train", "density.prune_screen_fraction", 0.0, "in (0, 1] or null"),
    ("train", "density.refine_start", -1, "a non-negative integer"),
    ("train", "density.refine_stop", -1, "a non-negative integer"),
    ("train", "density.refine_every", 0, "a positive integer"),
    ("train", "density.reset_every", 0, "a positive integer"),
    ("train", "density.max_gaussians", -1, "a non-negative integer or null"),
    ("train", "threads.threads", 0, "a positive integer or null"),
]

# (root, dotted path, a value outside the field's Literal, the allowed values as the message lists them).
BAD_MODES = [
    ("polar", "correction.intermediate_dolp", "literal", "'none', 'specular', 'overexposed', 'by_saturation'"),
    ("polar", "correction.overexposed_rule", "clipped", "'saturated', 'paper'"),
    ("polar", "densify.patchmatch.azimuth_model", "ortho", "'orthographic', 'perspective'"),
    ("polar", "densify.patchmatch.ncc_backend", "cuda", "'auto', 'torch', 'numba'"),
    ("polar", "densify.filters.azimuth_model", "weak", "'orthographic', 'perspective'"),
    ("train", "backend", "cuda", "'auto', 'torch', 'numba'"),
    ("train", "order", "depth", "'center', 'ray'"),
    ("train", "threads.numba_layer", "openmp", "'workqueue', 'omp', 'tbb', 'default'"),
    ("train", "threads.wait_policy", "spin", "'passive', 'active' or null"),
]

# Values on the edges of what is allowed, or special values a field documents: all accepted.
EDGE_VALUES = [
    ("polar", {"correction": {"specular_dolp": (0.3, 0.3), "rho_d": 0.5, "pri_saturation": 1.0, "propagation_radius": 0}}),
    ("polar", {"losses": {"ssim_weight": 1.0, "normal_hold_deg": 180.0, "normal_until_after_dense": None,
                          "alpha_normal": 0.0, "depth_normal_from_iter": 0}}),
    ("polar", {"losses": {"normal_hold_deg": None, "ssim_weight": 0.0}}),
    ("polar", {"losses": {"use_polar_normal": True, "alpha_polar_normal": 0.0, "polar_normal_min_dolp": 0.0,
                          "polar_normal_zenith_min_dolp": 1.0, "polar_normal_refractive_index": 1.0001}}),
    ("polar", {"densify": {"start_iter": 7000, "end_iter": 7000, "max_new_per_call": 0, "seed_max_plane_deviation": None,
                           "thin_scale_ratio": 1.0, "alpha_threshold": 0.0}}),
    ("polar", {"densify": {"patchmatch": {"iterations": 0, "depth_perturbation": 0.0, "refine_normal_deg": 180.0,
                                          "sigma_spatial": -3.0, "propagation_distances": (1,), "seed": -1}}}),
    ("polar", {"densify": {"filters": {"min_consistent_views": 0, "max_photometric_cost": 2.0}}}),
    ("train", {"sh_degree": 0, "background": (1.0, 1.0, 1.0), "device": "cuda:1", "seed": -5}),
    ("train", {"lrs": {"means_init": 0.0, "means_final": 0.0}, "density": {"max_gaussians": 0, "refine_stop": 0}}),
    ("train", {"threads": {"threads": None, "wait_policy": None}}),
]

SECTIONS = {
    "polar": {"": PolarConfig, "correction": CorrectionConfig, "losses": LossConfig, "densify": DensifyConfig,
              "densify.patchmatch": PatchMatchConfig, "densify.filters": FilterConfig},
    "train": {"": TrainConfig, "lrs": LearningRates, "density": DensityConfig, "threads": ThreadPolicy},
}
ROOTS = {"polar": PolarConfig, "train": TrainConfig}


def _nested(path: str, value) -> dict:
    """``"a.b.c", v`` -> ``{"a": {"b": {"c": v}}}``."""
    *sections, key = path.split(".")
    data = {key: value}
    for section in reversed(sections):
        data = {section: data}
    return data


def _message(path: str, value, allowed: str, where: str = "") -> str:
    full = f"{where}.{path}" if where else path
    parent = full.rpartition(".")[0]
    return f"{full}: must be {allowed.replace('{parent}', parent + '.' if parent else '')}, got {value!r}"


def _leaves(data: dict, where: str = ""):
    """``{"a": {"b": 1}}`` -> ``("a.b", 1)``."""
    for key, value in data.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{where}{key}.")
        else:
            yield f"{where}{key}", value


def _get(config, path: str):
    for name in path.split("."):
        config = getattr(config, name)
    return config


def _ids(table):
    return [f"{root}.{path}={value!r}" for root, path, value, _ in table]


def _refused(call, message: str, error=ValueError) -> None:
    with pytest.raises(error) as err:
        call()
    text = err.value.args[0] if error is KeyError else str(err.value)
    assert text == message and "\n" not in text


# --------------------------------------------------------------------------------- from Python
def _is_mode(hint) -> bool:
    return any(typing.get_origin(h) is typing.Literal for h in (hint, *typing.get_args(hint)))


def test_every_constrained_field_has_a_bad_value_in_the_table():
    def constrained(config, where=""):
        hints = typing.get_type_hints(type(config))
        for f in fields(config):
            value = getattr(config, f.name)
            if is_dataclass(value):
                yield from constrained(value, f"{where}{f.name}.")
            elif "allowed" in f.metadata or _is_mode(hints[f.name]):
                yield f"{where}{f.name}"

    declared = {(root, path) for root, cls in ROOTS.items() for path in constrained(cls())}
    tested = {(root, path) for root, path, *_ in BAD_VALUES + BAD_MODES}
    assert declared == tested


@pytest.mark.parametrize("root, path, value, allowed", BAD_VALUES, ids=_ids(BAD_VALUES))
def test_a_bad_value_is_refused_in_one_line_naming_field_value_and_range(root, path, value, allowed):
    cls = ROOTS[root]
    message = _message(path, value, allowed)
    _refused(lambda: cls.from_dict(_nested(path, value)), message)
    _refused(lambda: cls.from_dict(_nested(path, value), where=root), _message(path, value, allowed, root))
    # update: on a refusal the preset keeps every value, the valid ones given with the bad one too
    preset = PolarConfig.synthetic() if root == "polar" else TrainConfig.cpu()
    before = preset.to_dict()
    data = _nested(path, value)
    data["seed" if root == "train" else "cache_dir"] = 7 if root == "train" else "elsewhere"
    _refused(lambda: preset.update(data), message)
    assert preset.to_dict() == before
    # the constructor of the config that holds the field names it from there
    section, _, name = path.rpartition(".")
    _refused(lambda: SECTIONS[root][section](**{name: value}), _message(name, value, allowed))


def _view() -> View:
    stokes = torch.zeros(3, 3, 8, 8)
    stokes[0] = 1.0
    K = torch.tensor([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]], dtype=torch.float64)
    return View(name="v0", K=K, world_to_camera=torch.eye(4, dtype=torch.float64), stokes=stokes)


@pytest.mark.parametrize("root, path, value, allowed", BAD_VALUES, ids=_ids(BAD_VALUES))
def test_a_value_reassigned_after_building_is_refused_at_the_door(root, path, value, allowed):
    """Attributes can be reassigned after a config was built: PolarHooks and Trainer check again."""
    config = PolarConfig.synthetic() if root == "polar" else TrainConfig.cpu(num_init_points=10, progress=False)
    section, _, name = path.rpartition(".")
    setattr(_get(config, section) if section else config, name, value)
    door = (lambda: PolarHooks(config)) if root == "polar" else (lambda: Trainer([_view()], config))
    _refused(door, _message(path, value, allowed, "config"))


@pytest.mark.parametrize("root, path, value, allowed", BAD_MODES, ids=_ids(BAD_MODES))
def test_a_mode_outside_its_literal_is_refused_naming_the_allowed_modes(root, path, value, allowed):
    message = f"{path}: expected one of {allowed}, got {value!r}"
    _refused(lambda: ROOTS[root].from_dict(_nested(path, value)), message)
    section, _, name = path.rpartition(".")
    _refused(lambda: SECTIONS[root][section](**{name: value}), f"{name}: expected one of {allowed}, got {value!r}")


def test_the_mode_literals_are_the_values_the_code_accepts():
    from polargs_plugin.backends.reference.rasterizer import resolve_backend
    from polargs_plugin.correction.masks import INTERMEDIATE_CHOICES
    from polargs_plugin.densify.patchmatch import _resolve_backend
    from polargs_plugin.optics import AZIMUTH_MODELS

    assert typing.get_args(AzimuthModel) == AZIMUTH_MODELS
    assert typing.get_args(IntermediateDolp) == INTERMEDIATE_CHOICES
    cpu = torch.device("cpu")
    assert {_resolve_backend(name, cpu) for name in typing.get_args(NccBackend)} <= {"torch", "numba"}
    with pytest.raises(ValueError, match="unknown NCC backend"):
        _resolve_backend("cuda", cpu)
    assert {resolve_backend(name, cpu) for name in typing.get_args(typing.get_type_hints(TrainConfig)["backend"])} <= {"torch", "numba"}


@pytest.mark.parametrize("root, data", EDGE_VALUES, ids=[json.dumps(d, default=str)[:60] for _, d in EDGE_VALUES])
def test_values_on_the_edges_of_the_ranges_are_accepted(root, data):
    config = ROOTS[root].from_dict(data)
    assert config == ROOTS[root]().update(data)
    for path, value in _leaves(data):
        assert _get(config, path) == value


def test_the_presets_and_the_defaults_are_valid():
    presets = [PolarConfig(), PolarConfig.synthetic(), PolarConfig.real(), PolarConfig.cpu_demo(),
               PolarConfig.cpu_demo(polar_schedule_factor(0.002)), TrainConfig(), TrainConfig.paper(), TrainConfig.cpu(),
               TrainConfig.cpu(0.002), CorrectionConfig(), LossConfig(), DensifyConfig(), PatchMatchConfig(),
               FilterConfig(), LearningRates(), DensityConfig(), ThreadPolicy()]
    for config in presets:
        assert config.validate() is config
        assert type(config).from_dict(config.to_dict()) == config
    assert PolarConfig.cpu_demo().densify.interval == 50 and TrainConfig.cpu().iterations == 5000


def test_a_preset_scaled_to_nothing_is_refused():
    with pytest.raises(ValueError, match=re.escape("iterations: must be a positive integer, got 0")):
        TrainConfig.cpu(1e-5)
    assert TrainConfig.cpu(1e-5, iterations=10).iterations == 10  # overrides come in before the check
    with pytest.raises(ValueError, match=re.escape("losses.depth_normal_from_iter: must be a non-negative integer, got -7000")):
        PolarConfig.cpu_demo(-1)


def test_wrong_kinds_and_unknown_keys():
    _refused(lambda: DensifyConfig(interval="100"), "interval: expected an integer, got '100'")
    _refused(lambda: DensifyConfig(enabled=1), "enabled: expected true or false, got 1")
    _refused(lambda: PolarConfig(densify=PatchMatchConfig()), "densify: expected DensifyConfig settings, got PatchMatchConfig")
    _refused(lambda: PolarConfig.from_dict({"losses": {"alpha_normal": float("nan")}}),
             "losses.alpha_normal: expected a number, got nan")
    _refused(lambda: TrainConfig.from_dict({"lrs": 0.1}, where="train"), "train.lrs: expected a dict of settings, got 0.1")
    known = sorted(f.name for f in fields(DensityConfig))
    _refused(lambda: TrainConfig.from_dict({"density": {"max_gaussian": 10}}),
             f"density: unknown setting 'max_gaussian' (known: {known})", KeyError)
    # JSON lists become the fields' tuples, integers in number fields numbers
    config = TrainConfig.from_dict({"background": [1, 1, 1], "schedule_scale": 1})
    assert config.background == (1.0, 1.0, 1.0) and isinstance(config.schedule_scale, float)


def test_every_field_is_documented_in_its_class_docstring():
    for sections in SECTIONS.values():
        for cls in sections.values():
            attributes = cls.__doc__.split("Attributes:", 1)[1]
            for f in fields(cls):
                assert re.search(rf"^\s+{f.name}:", attributes, re.M), f"{cls.__name__}.{f.name} is not documented"


# ------------------------------------------------------------------------------ from the command line
CLI_CASES = [
    pytest.param("polar", "densify.interval", 0, "must be a positive integer, got 0"),
    pytest.param("polar", "correction.specular_dolp", [0.9, 0.3],
                 "must be a pair (low, high) with 0 <= low <= high <= 1, got (0.9, 0.3)"),
    pytest.param("polar", "densify.patchmatch.azimuth_model", "ortho",
                 "expected one of 'orthographic', 'perspective', got 'ortho'"),
    pytest.param("train", "iterations", 0, "must be a positive integer, got 0"),
    pytest.param("train", "density.max_gaussians", -1, "must be a non-negative integer or null, got -1"),
    pytest.param("train", "backend", "cuda", "expected one of 'auto', 'torch', 'numba', got 'cuda'"),
]


@pytest.mark.parametrize("dataset", ["synthetic:glossy_plane_sphere", "missing-folder"])
@pytest.mark.parametrize("section, path, value, problem", CLI_CASES)
def test_train_refuses_a_bad_settings_file_before_reading_data(tmp_path, capsys, dataset, section, path, value, problem):
    """One line naming the file, the field and the value; exit status 2; no run folder. A dataset
    folder that does not exist is not reported: the settings are checked before any data is read."""
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({section: _nested(path, value)}))
    out = tmp_path / "run"
    if dataset == "missing-folder":
        dataset = str(tmp_path / "no_such_dataset")
    status = main(["train", dataset, "--out", str(out), "--config", str(settings), "--quiet"])
    err = capsys.readouterr().err
    assert err.strip() == f"error: {settings}: {section}.{path}: {problem}"
    assert status == 2 and not out.exists()


@pytest.mark.parametrize("flag, assignment, problem", [
    ("--polar-set", "densify.interval=0", "densify.interval: must be a positive integer, got 0"),
    ("--polar-set", "densify.patchmatch.window_radius=-1", "densify.patchmatch.window_radius: must be a positive integer, got -1"),
    ("--train-set", "iterations=0", "iterations: must be a positive integer, got 0"),
    ("--train-set", "density.max_gaussians=-5", "density.max_gaussians: must be a non-negative integer or null, got -5"),
    ("--polar-set", "densify.filters.azimuth_model=weak",
     "densify.filters.azimuth_model: expected one of 'orthographic', 'perspective', got 'weak'"),
])
def test_ablate_refuses_a_bad_override_before_training(tmp_path, capsys, flag, assignment, problem):
    out = tmp_path / "grid"
    status = main(["ablate", "--scenes", "glossy_plane_sphere", "--variants", "full", "--out", str(out), flag, assignment,
                   "--quiet"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and "\n" not in err
    assert err.startswith("error: ") and err.endswith(problem)
    assert not out.exists() or not any(out.iterdir())  # nothing trained, no run folder
