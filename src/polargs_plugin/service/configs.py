"""Building a run's settings: a preset, a settings file, then overrides, each checked on the way.

The two configurations of a run are :class:`~polargs_plugin.config.PolarConfig` (the PolarGS
hooks) and :class:`~polargs_plugin.backends.reference.trainer.TrainConfig` (the reference trainer).
Settings files hold nested, partial dicts of their fields::

    {"polar": {"losses": {"alpha_normal": 0.1}}, "train": {"density": {"max_gaussians": 3000}}}

Every function here refuses an unknown key or a value of the wrong kind with a
:class:`~polargs_plugin.io.PolarInputError` naming the file (or option) and the setting.
"""

from __future__ import annotations

import copy
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Mapping, Sequence

from polargs_plugin.config import PolarConfig, polar_schedule_factor
from polargs_plugin.io import PolarInputError

if TYPE_CHECKING:
    from polargs_plugin.backends.reference.trainer import TrainConfig

__all__ = [
    "SCHEDULES", "PRESETS", "SWITCHES", "Settings", "read_settings", "apply_overrides", "polar_config",
    "train_config", "changed_fields", "resolve_device", "ENV_PRESET", "ENV_CONFIG", "ENV_KEEP_NATIVE", "config_from_environment",
]

#: Training schedules: ``cpu`` (the vanilla schedule x factor, minutes on a CPU), ``paper`` (30k).
SCHEDULES: tuple[str, ...] = ("cpu", "paper")
#: The paper's PolarGS values for synthetic data or real captures.
PRESETS: tuple[str, ...] = ("synthetic", "real")
#: The ablation switches of ``polargs train`` (``--no-pc`` ...): switch -> (PolarConfig section, field).
SWITCHES: dict[str, tuple[str, str]] = {
    "no_pc": ("correction", "enabled"),
    "no_dense": ("densify", "enabled"),
    "no_ref_loss": ("losses", "use_ref"),
    "no_normal_loss": ("losses", "use_normal"),
    "no_depth_normal_loss": ("losses", "use_depth_normal"),
    "no_scale_loss": ("losses", "use_scale"),
}

#: Environment of a patched upstream trainer: the preset, a PolarConfig settings file, and "1" to
#: keep the PolarGS loss terms that the trainer's own terms stand in for.
ENV_PRESET = "POLARGS_PRESET"
ENV_CONFIG = "POLARGS_CONFIG"
ENV_KEEP_NATIVE = "POLARGS_KEEP_NATIVE"

_LAYERED = {"polar", "train"}


@dataclass(frozen=True)
class Settings:
    """The overrides of a settings file.

    Attributes:
        polar: nested partial dict of :class:`PolarConfig` fields.
        train: nested partial dict of ``TrainConfig`` fields.
        source: where they come from (the file), for messages.
    """

    polar: dict[str, Any] = field(default_factory=dict)
    train: dict[str, Any] = field(default_factory=dict)
    source: str = "settings"


def read_settings(path: str | os.PathLike | None, bare_polar: bool = False) -> Settings:
    """The overrides of a ``{"polar": {...}, "train": {...}}`` settings file (none for ``path`` None).

    Args:
        path: the JSON file, or None.
        bare_polar: also accept a bare PolarConfig object (the ``PolarConfig.to_dict`` layout),
            as ``polargs preprocess --config`` and ``POLARGS_CONFIG`` do.

    Raises:
        PolarInputError: naming the file: unreadable, not JSON, or not of that layout.
    """
    if path is None:
        return Settings()
    try:
        data = json.loads(Path(path).read_text())
    except OSError as err:
        raise PolarInputError(path, f"cannot read the settings file ({err.strerror or err})") from None
    except ValueError as err:
        raise PolarInputError(path, f"not valid JSON ({err})") from None
    if not isinstance(data, dict):
        expected = 'expected {"polar": {...}, "train": {...}}' + (" or a PolarConfig object" if bare_polar else "")
        raise PolarInputError(path, expected)
    if bare_polar and not (data and set(data) <= _LAYERED):
        return Settings(polar=data, source=str(path))
    for key in data:
        if key not in _LAYERED:
            raise PolarInputError(path, f"unknown key '{key}' (expected {{\"polar\": {{...}}, \"train\": {{...}}}})")
    for key in ("polar", "train"):
        if not isinstance(data.get(key, {}), dict):
            raise PolarInputError(path, f"'{key}' must be an object of settings")
    return Settings(polar=data.get("polar", {}), train=data.get("train", {}), source=str(path))


def _updated(config: Any, overrides: Mapping[str, Any], where: str, source: str) -> Any:
    """``config`` (a dataclass of :mod:`polargs_plugin.config`) with ``overrides`` set on it: an
    unknown key, a value of the wrong kind or out of its range is refused naming ``source`` and
    the setting (``where.section.field``); a refused update leaves ``config`` as it was."""
    if not isinstance(overrides, Mapping):
        raise PolarInputError(source, f"{where}: expected an object of settings, got {json.dumps(overrides)}")
    try:
        return config.update(dict(overrides), where=where)
    except KeyError as err:
        raise PolarInputError(source, str(err.args[0])) from None
    except ValueError as err:
        raise PolarInputError(source, str(err)) from None


def apply_overrides(config: PolarConfig, overrides: Mapping[str, Any], source: str = "settings") -> PolarConfig:
    """A copy of ``config`` with ``overrides`` (nested, partial, checked) set on it."""
    return _updated(copy.deepcopy(config), overrides, "polar", source)


def changed_fields(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """The entries of the nested dict ``b`` that differ from ``a``."""
    out = {}
    for key, value in b.items():
        if isinstance(value, dict):
            sub = changed_fields(a[key], value)
            if sub:
                out[key] = sub
        elif a[key] != value:
            out[key] = value
    return out


def polar_config(
    preset: Literal["synthetic", "real"] = "synthetic",
    factor: float | None = None,
    overrides: Mapping[str, Any] | None = None,
    source: str = "settings",
    switches: Sequence[str] = (),
) -> PolarConfig:
    """The PolarConfig of a run.

    Args:
        preset: the paper's values for ``synthetic`` data or ``real`` captures.
        factor: the run's vanilla schedule factor (``TrainConfig.cpu``): the PolarGS schedules are
            scaled by ``polar_schedule_factor(factor)``; None: the paper's schedules.
        overrides: nested partial dict of fields (checked), set after the preset.
        source: the file or option the overrides come from, for messages.
        switches: names of :data:`SWITCHES` (``no_pc`` ...) turned on, applied last.
    """
    config = PolarConfig.real() if preset == "real" else PolarConfig.synthetic()
    if factor is not None:
        # the schedule fields cpu_demo scales (whatever they are): taken from it, onto the preset
        scaled = PolarConfig.cpu_demo(polar_schedule_factor(factor)).to_dict()
        config.update(changed_fields(PolarConfig.synthetic().to_dict(), scaled))
    config = apply_overrides(config, overrides or {}, source)
    for name in switches:
        section, name_of_field = SWITCHES[name]
        setattr(getattr(config, section), name_of_field, False)
    return config


def train_config(
    schedule: Literal["cpu", "paper"] = "cpu",
    factor: float | None = None,
    overrides: Mapping[str, Any] | None = None,
    source: str = "settings",
    **fields_set: Any,
) -> "TrainConfig":
    """The TrainConfig of a run: the schedule, ``overrides`` (nested, partial, checked), then
    ``fields_set`` (e.g. ``seed``, ``device``, ``iterations`` from command-line flags).

    Args:
        schedule: ``cpu`` (``TrainConfig.cpu(factor)``; factor None: 1/6, 5000 iterations) or
            ``paper`` (vanilla 3DGS, 30k iterations).
        factor: the cpu schedule's factor.
        overrides: nested partial dict of fields.
        source: the file or option the overrides come from, for messages.
    """
    from polargs_plugin.backends.reference.trainer import TrainConfig

    if schedule == "cpu":
        base = TrainConfig.cpu() if factor is None else TrainConfig.cpu(factor)
    else:
        base = TrainConfig.paper()
    config = _updated(base, overrides or {}, "train", source)
    return _updated(config, fields_set, "train", "settings")


def config_from_environment(environ: Mapping[str, str] | None = None, native_terms: Sequence[str] = ()) -> PolarConfig:
    """The PolarConfig of a patched upstream trainer, from its environment: the preset named by
    :data:`ENV_PRESET` (default ``real``), the loss switches ``native_terms`` off (the trainer's
    own terms stand in for them) unless :data:`ENV_KEEP_NATIVE` is ``1``, then the settings file
    :data:`ENV_CONFIG` (a bare PolarConfig or ``{"polar": {...}}``).

    Raises:
        PolarInputError: an unknown preset (naming the variable), an unreadable or invalid file.
    """
    environ = os.environ if environ is None else environ
    preset = environ.get(ENV_PRESET, "real")
    if preset not in PRESETS:
        raise PolarInputError(ENV_PRESET, f"unknown preset {preset!r} (choose one of {', '.join(PRESETS)})")
    config = polar_config(preset)  # type: ignore[arg-type]
    if environ.get(ENV_KEEP_NATIVE, "0") != "1":
        for switch in native_terms:
            setattr(config.losses, switch, False)
    path = environ.get(ENV_CONFIG)
    if path:
        settings = read_settings(path, bare_polar=True)
        config = apply_overrides(config, settings.polar, path)
    return config


def resolve_device(requested: str | None = None) -> str:
    """The torch device of a run: ``requested``, or ``cuda`` when available, else ``cpu``.

    Raises:
        PolarInputError: naming ``--device``: a CUDA device on a machine without one.
    """
    import torch

    device = requested or ("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise PolarInputError("--device", f"{device} is not available on this machine")
    return device
