"""The trainers a dry run knows: which stand-ins each imports and how its schedule is shrunk.

Each :class:`TrainerSpec` names the upstream module names the trainer imports (served by the
stand-ins), the attributes of installed packages replaced by stand-ins (gsplat's CUDA entry
points), the command-line arguments of its training script that shrink its schedule so that,
within a few hundred iterations, its own densification and pruning run several times, and the
Dense window of the PolarGS settings (``POLARGS_CONFIG``) that overlaps it. :data:`FALLBACKS`
are served to every trainer, but only where the package they stand in for is not installed
(``pytorch3d.transforms``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from polargs_plugin.dryrun.finder import is_installed

__all__ = ["TrainerSpec", "TRAINERS", "schedule_arguments", "shrunk_schedule_arguments", "shrink_literals",
           "UPSTREAM_SCHEDULE", "gsplat_arguments", "trainer_arguments", "dense_settings",
           "STANDINS", "FALLBACKS", "served_modules"]

STANDINS = "polargs_plugin.dryrun.standins"

_KNN = {"simple_knn": f"{STANDINS}.simple_knn", "simple_knn._C": f"{STANDINS}.simple_knn"}

#: Pure-Python packages a trainer imports that a dry run serves only where they are not installed:
#: top-level package -> the stand-ins of it and its sub-modules (:func:`served_modules`).
FALLBACKS: dict[str, dict[str, str]] = {
    "pytorch3d": {"pytorch3d": f"{STANDINS}.pytorch3d_transforms",
                  "pytorch3d.transforms": f"{STANDINS}.pytorch3d_transforms"},
}

_GSPLAT_MODULES = {
    "gsplat.cuda._backend": f"{STANDINS}.gsplat_backend",
    "fused_ssim": f"{STANDINS}.fused_ssim",
    "torchmetrics.image.lpip": f"{STANDINS}.lpips",
}
_GSPLAT_ATTRIBUTES = {
    "gsplat.rendering:rasterization": f"{STANDINS}.gsplat:rasterization",
    "gsplat:rasterization": f"{STANDINS}.gsplat:rasterization",
    "gsplat.distributed:cli": f"{STANDINS}.gsplat:single_process_cli",
    "gsplat.strategy.ops:compute_relocation": f"{STANDINS}.gsplat:compute_relocation",
    "gsplat.strategy.ops:quat_scale_to_covar_preci": f"{STANDINS}.gsplat:quat_scale_to_covar_preci",
}


@dataclass(frozen=True)
class TrainerSpec:
    """One upstream trainer as a dry run drives it.

    Attributes:
        name: the ``--trainer`` name.
        description: the repository and commit it was written against.
        standins: upstream module name -> stand-in module.
        adapter: the ``polargs_adapters`` sub-package its patch script inserts.
        extra_arguments: ``train.py`` arguments beyond the shared schedule (trainer-only switches).
        from_middle: ``train.py`` options naming the iteration a trainer's own geometry terms start
            at; a dry run sets them to the middle of the run so that those terms run too.
        family: ``"inria"`` (graphdeco's ``train.py`` and its forks: ``GaussianModel``,
            ``-s``/``-m``) or ``"gsplat"`` (gsplat's ``examples/simple_trainer.py``: a ``Runner``,
            tyro arguments, gsplat strategies).
        script: the training script, relative to the checkout.
        attributes: ``"module:attribute"`` of an installed package -> ``"stand-in module:attribute"``
            that replaces it in the dry run's process.
        subcommand: the script's first argument (simple_trainer's strategy preset).
        upstream_options: ``train.py`` options beyond the shared schedule that name an iteration,
            with their upstream defaults: a run of the whole schedule shrunk by a factor
            (:func:`shrunk_schedule_arguments`) scales them by it.
        hard_coded: statements of the training script that hold an iteration number as a literal
            (``iteration > 7000``): a shrunk run scales the number in its copy of the script
            (:func:`shrink_literals`).
    """

    name: str
    description: str
    standins: dict[str, str]
    adapter: str
    extra_arguments: tuple[str, ...] = field(default=())
    from_middle: tuple[str, ...] = field(default=())
    family: Literal["inria", "gsplat"] = "inria"
    script: str = "train.py"
    attributes: dict[str, str] = field(default_factory=dict)
    subcommand: tuple[str, ...] = field(default=())
    upstream_options: dict[str, int] = field(default_factory=dict)
    hard_coded: tuple[str, ...] = field(default=())


TRAINERS: dict[str, TrainerSpec] = {
    spec.name: spec
    for spec in (
        TrainerSpec(
            "graphdeco",
            "graphdeco-inria/gaussian-splatting, 2024 (54c035f: inverse depth, antialiasing)",
            {"diff_gaussian_rasterization": f"{STANDINS}.graphdeco_2024", **_KNN},
            "graphdeco",
            ("--disable_viewer",),
        ),
        TrainerSpec(
            "graphdeco-2023",
            "graphdeco-inria/gaussian-splatting, 2023 (472689c: colour and radii only)",
            {"diff_gaussian_rasterization": f"{STANDINS}.graphdeco_2023", **_KNN},
            "graphdeco",
        ),
        TrainerSpec(
            "gof",
            "autonomousvision/gaussian-opacity-fields (5245b20)",
            {"diff_gaussian_rasterization": f"{STANDINS}.gof", **_KNN},
            "gof",
            from_middle=("--distortion_from_iter", "--depth_normal_from_iter"),
            upstream_options={"--distortion_from_iter": 15000, "--depth_normal_from_iter": 15000},
        ),
        TrainerSpec(
            "pgsr",
            "zju3dv/PGSR (de24f1a)",
            {"diff_plane_rasterization": f"{STANDINS}.plane", **_KNN},
            "pgsr",
            from_middle=("--single_view_weight_from_iter", "--multi_view_weight_from_iter"),
            upstream_options={"--single_view_weight_from_iter": 7000, "--multi_view_weight_from_iter": 7000},
        ),
        TrainerSpec(
            "2dgs",
            "hbb1/2d-gaussian-splatting (1920a23)",
            {"diff_surfel_rasterization": f"{STANDINS}.surfel", **_KNN},
            "twodgs",
            hard_coded=("iteration > 7000", "iteration > 3000"),  # L_normal's and L_dist's starts
        ),
        TrainerSpec(
            "gsplat",
            "nerfstudio-project/gsplat examples/simple_trainer.py, DefaultStrategy (v1.5.3 and main 90d7b4b)",
            _GSPLAT_MODULES, "gsplat", ("--disable_viewer", "--data_factor", "1"), family="gsplat",
            script="simple_trainer.py", attributes=_GSPLAT_ATTRIBUTES, subcommand=("default",),
        ),
        TrainerSpec(
            "gsplat-mcmc",
            "nerfstudio-project/gsplat examples/simple_trainer.py, MCMCStrategy (v1.5.3 and main 90d7b4b)",
            _GSPLAT_MODULES, "gsplat", ("--disable_viewer", "--data_factor", "1"), family="gsplat",
            script="simple_trainer.py", attributes=_GSPLAT_ATTRIBUTES, subcommand=("mcmc",),
        ),
    )
}


def served_modules(spec: TrainerSpec) -> dict[str, str]:
    """Upstream module name -> stand-in of everything a dry run of ``spec`` serves: its CUDA
    extensions' stand-ins, and the :data:`FALLBACKS` of packages this environment lacks."""
    table = dict(spec.standins)
    for package, modules in FALLBACKS.items():
        if not is_installed(package):
            table.update(modules)
    return table


def schedule_arguments(spec: TrainerSpec, iterations: int, interval: int) -> list[str]:
    """``train.py`` arguments of the graphdeco family that shrink its schedule to ``iterations``:
    densification every ``interval`` from ``interval`` to 80 % of the run, the opacity reset once,
    right after the last densification (a reset shortly before a prune would prune everything that
    had no time to recover, as 3000 iterations between them upstream never do), the position learning-rate decay over the run, a checkpoint one interval before the
    end, no test renders, then the trainer's own extra arguments."""
    densify_until = max(2 * interval, int(0.8 * iterations))
    return [
        "--iterations", str(iterations),
        "--position_lr_max_steps", str(iterations),
        "--densify_from_iter", str(interval),
        "--densify_until_iter", str(densify_until),
        "--densification_interval", str(interval),
        "--opacity_reset_interval", str(densify_until - 1),
        "--test_iterations", str(iterations + 1),
        "--save_iterations", str(iterations),
        "--checkpoint_iterations", str(iterations - interval),
        *spec.extra_arguments,
        *[item for flag in spec.from_middle for item in (flag, str(iterations // 2))],
    ]


#: The graphdeco family's schedule (graphdeco, GOF, PGSR and 2DGS share these defaults); its
#: opacity reset (every 3000) is left out of a shrunk run (:func:`shrunk_schedule_arguments`).
UPSTREAM_SCHEDULE = {"iterations": 30_000, "densify_from_iter": 500, "densify_until_iter": 15_000,
                     "densification_interval": 100}


def _scaled(iteration: int, factor: float) -> int:
    """An upstream iteration count in a run shrunk by ``factor`` (at least 1)."""
    return max(1, round(iteration * factor))


def shrunk_schedule_arguments(spec: TrainerSpec, factor: float) -> list[str]:
    """``train.py`` arguments of the graphdeco family for its whole schedule with every iteration
    count multiplied by ``factor`` (``UPSTREAM_SCHEDULE`` and the trainer's
    ``upstream_options``; intervals at least 1), and no opacity reset, as the reference trainer's
    CPU preset: after a reset the opacities need about a hundred steps to climb back above the
    prune threshold (upstream's densification interval), and a shrunk interval prunes them before
    (in 2DGS at 1/6 every Gaussian). The run saves its Gaussians at the last iteration and a
    checkpoint there, and renders no test views.

    >>> " ".join(shrunk_schedule_arguments(TRAINERS["graphdeco-2023"], 1 / 6)[:4])
    '--iterations 5000 --densify_from_iter 83'
    """
    if spec.family != "inria":
        raise ValueError(f"{spec.name}: only the graphdeco family's schedule can be shrunk here")
    iterations = _scaled(UPSTREAM_SCHEDULE["iterations"], factor)
    return [
        *[item for name, value in UPSTREAM_SCHEDULE.items() for item in (f"--{name}", str(_scaled(value, factor)))],
        "--position_lr_max_steps", str(iterations),
        "--opacity_reset_interval", str(iterations + 1),
        "--test_iterations", str(iterations + 1),
        "--save_iterations", str(iterations),
        "--checkpoint_iterations", str(iterations),
        *spec.extra_arguments,
        *[item for flag, value in spec.upstream_options.items() for item in (flag, str(_scaled(value, factor)))],
    ]


def shrink_literals(spec: TrainerSpec, text: str, factor: float) -> tuple[str, list[str]]:
    """``text`` (the training script) with the iteration of each of ``spec.hard_coded``'s
    statements multiplied by ``factor``, and the statements it does not hold (left as they are)."""
    missing = []
    for statement in spec.hard_coded:
        head, _, number = statement.rpartition(" ")
        text, count = re.subn(re.escape(statement) + r"(?!\d)", f"{head} {_scaled(int(number), factor)}", text)
        if not count:
            missing.append(statement)
    return text, missing


def gsplat_arguments(spec: TrainerSpec, iterations: int, interval: int) -> list[str]:
    """simple_trainer.py arguments (tyro) that shrink its schedule to ``iterations`` steps: the
    strategy's refinement every ``interval`` steps from ``interval`` to 80 % of the run (the
    DefaultStrategy's opacity reset right after it), a checkpoint one interval before the end (and
    simple_trainer's own at the last step), no evaluation, no viewer."""
    refine_until = max(2 * interval, int(0.8 * iterations))
    strategy = [
        "--strategy.refine-start-iter", str(interval),
        "--strategy.refine-stop-iter", str(refine_until),
        "--strategy.refine-every", str(interval),
    ]
    if spec.subcommand == ("default",):
        strategy += ["--strategy.reset-every", str(refine_until - 1)]
    return [
        *spec.subcommand,
        "--max_steps", str(iterations),
        "--eval_steps", str(iterations + 1),
        "--save_steps", str(iterations - interval),
        "--ply_steps", str(iterations + 1),
        *strategy,
        *spec.extra_arguments,
    ]


def trainer_arguments(spec: TrainerSpec, scene_input: Path, model_path: Path, port: int, iterations: int,
                      interval: int) -> list[str]:
    """The whole command line of the trainer's script: its input scene (COLMAP layout), its output
    folder, a free port for its viewer, then the shrunk schedule."""
    if spec.family == "gsplat":
        return [*gsplat_arguments(spec, iterations, interval), "--data_dir", str(scene_input),
                "--result_dir", str(model_path), "--port", str(port)]
    return ["-s", str(scene_input), "-m", str(model_path), "--port", str(port),
            *schedule_arguments(spec, iterations, interval)]


def dense_settings(iterations: int, interval: int) -> dict:
    """The PolarGS settings (``POLARGS_CONFIG``) of a dry run: Dense every ``interval`` from the
    second native densification to 70 % of the run (so the native densification and pruning
    handle the appended Gaussians several times), L_dn from the middle.

    A dry run checks the plumbing, not where Dense seeds: after a few dozen iterations on a small
    scene the paper's filters may keep no pixel at all, so they are relaxed (one consistent source
    within 2 px and 5 % depth, seeds wherever PatchMatch's depth differs from the render's)."""
    return {
        "polar": {
            "densify": {
                "start_iter": 2 * interval, "end_iter": max(2 * interval, int(0.7 * iterations)), "interval": interval,
                "seed_depth_footprints": 0.0, "seed_max_plane_deviation": None, "seed_behind_surface": True,
                "filters": {"min_consistent_views": 1, "max_reprojection_px": 2.0, "max_relative_depth": 0.05,
                            "max_polar_residual": 1.0, "max_photometric_cost": 2.0},
            },
            "losses": {"depth_normal_from_iter": iterations // 2},
        }
    }
