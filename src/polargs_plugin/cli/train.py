"""``polargs train``: train the bundled reference 3D Gaussian Splatting backend on a dataset.

The run-folder contract (docs/cli.md): ``checkpoint.pt`` (resumable), ``fingerprint.json`` (what
the run is trained on: cameras and image content, checked by ``--resume``), ``maps/`` (the
PolarGS maps cache), ``summary.json`` (settings and final figures, written when training
finishes) and, while a training runs, ``train.lock``. Every error is one line ``error: FILE:
problem`` on stderr (exit status 2); Ctrl-C / SIGTERM stop after the current iteration with a
final checkpoint (exit status 130 / 143).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import shlex
import signal
import sys
import time
from pathlib import Path
from typing import Any

from polargs_plugin.io import FolderLock, PolarInputError, atomic_write, check_writable
from polargs_plugin.cli.argtypes import non_negative_int, positive_float, positive_int

CHECKPOINT_NAME = "checkpoint.pt"
SUMMARY_NAME = "summary.json"
FINGERPRINT_NAME = "fingerprint.json"
LOCK_NAME = "train.lock"
MAPS_NAME = "maps"
PREPROCESSED_NAME = "preprocessed"  # `polargs preprocess DATASET` writes DATASET/preprocessed/maps
FINGERPRINT_FORMAT = "polargs-data-fingerprint-v1"

SCHEDULES = ("cpu", "paper")
PRESETS = ("synthetic", "real")
PATTERNS = ("auto", "mono", "rgb")
#: --no-X switch -> (PolarConfig path, value)
SWITCHES: dict[str, tuple[str, ...]] = {
    "no_pc": ("correction", "enabled"),
    "no_dense": ("densify", "enabled"),
    "no_ref_loss": ("losses", "use_ref"),
    "no_normal_loss": ("losses", "use_normal"),
    "no_depth_normal_loss": ("losses", "use_depth_normal"),
    "no_scale_loss": ("losses", "use_scale"),
}
#: Default periodic checkpoint: this many per run (every 10 % of the iterations).
CHECKPOINTS_PER_RUN = 10

_DESCRIPTION = """\
Train 3D Gaussians on a polarimetric dataset with the bundled reference trainer (vanilla 3D
Gaussian Splatting on the s0/2 colour images), optionally with the PolarGS hooks (reflection-aware
colour losses and polar-guided PatchMatch densification).

DATASET is a dataset folder in any supported format (detected automatically), or
synthetic:NAME to render one of the bundled synthetic scenes on the fly (24 views, 128x128).

Two independent choices:
  --schedule cpu|paper   how long and how big the TRAINING is: cpu = the vanilla schedule x1/6
                         (5000 iterations, SH degree 1, <= 6000 Gaussians from density control,
                         no opacity reset) for a CPU in minutes, with PolarGS' own schedules x1/2
                         (Dense 500-3500 every 50, L_dn from 3500; --factor F: x F and x min(1, 3F));
                         paper = vanilla 3DGS (30k iterations, SH degree 3, no cap), for a GPU.
  --preset synthetic|real  the paper's PolarGS VALUES for synthetic data (lambda1 = 0.02, alpha =
                         0.2, perspective azimuth model) or for real captures (lambda1 = 0.2,
                         alpha = 0.1, orthographic).
Then --config FILE.json ({"polar": {...}, "train": {...}}: any PolarConfig / TrainConfig field,
nested as in summary.json) and the --no-* switches are applied, in that order.

Run folder RUN_DIR: checkpoint.pt (every 10 % of the run and at the end; --resume continues it),
fingerprint.json (cameras + image content of the data, checked on --resume), maps/ (the PolarGS
maps cache: maps that `polargs preprocess DATASET` left in DATASET/preprocessed/maps, or that a
previous run left here, are reused), summary.json (every setting incl. the full PolarConfig, and
the final figures: training-view PSNR, number of Gaussians, time), train.lock while it runs.
Ctrl-C (or SIGTERM) stops after the current iteration, writes the checkpoint and prints the
command that resumes. See docs/cli.md.

Examples:
  polargs train synthetic:glossy_plane_sphere --out runs/base --no-polar
  polargs train my_scene/ --out runs/polar --preset real --iters 3000
  polargs train captures/ --out runs/raw --preset real --pattern auto --bit-depth 12 --sfm
  polargs train my_scene/ --out runs/nodense --no-dense --config polar.json
  polargs train my_scene/ --out runs/polar --resume --iters 6000
"""


# ------------------------------------------------------------------------------ options






def _bit_depth(text: str) -> int:
    value = positive_int(text)
    if not 1 <= value <= 16:
        raise argparse.ArgumentTypeError(f"must be between 1 and 16, got {text}")
    return value


def add_reader_options(p: argparse.ArgumentParser) -> None:
    """Options of the dataset readers, shared by every command that reads data (train,
    preprocess; the names for ablate / demo: --format, --pattern, --bit-depth, --sfm,
    --no-pattern-check)."""
    g = p.add_argument_group("reading the dataset")
    g.add_argument("--format", default="auto", metavar="FMT",
                   help="dataset format: auto (detect, default), polargs, neisf, pandora, nersp, polar")
    g.add_argument("--pattern", choices=PATTERNS, default=None,
                   help="raw mosaics (a polar folder's raw/): mono (IMX250MZR), rgb (IMX250MYR) or auto (told from "
                   "the frames; default). A given pattern is checked against every frame: a mono frame read as "
                   "rgb is an error")
    g.add_argument("--no-pattern-check", action="store_true",
                   help="do not check --pattern against the frames (a colour frame of a grey, white-balanced scene "
                   "looks mono)")
    g.add_argument("--bit-depth", type=_bit_depth, default=None, metavar="BITS",
                   help="significant bits of integer images, e.g. 12 for 12-bit data in 16-bit files "
                   "(default: the file's dtype, 8 or 16)")
    g.add_argument("--sfm", action=argparse.BooleanOptionalAction, default=False,
                   help="a polar folder without a COLMAP model: run SfM (pycolmap, the sfm extra) and write "
                   "sparse/0; needs at least 3 overlapping views (default: --no-sfm, a missing model is an error)")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train the reference Gaussian Splatting backend (with or without PolarGS)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset folder, or synthetic:NAME for a bundled scene")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder (see above)")
    p.add_argument("--schedule", choices=SCHEDULES, default=None,
                   help="training schedule: cpu (5000 iterations, minutes on a CPU) or paper (30k, a GPU) (default cpu)")
    p.add_argument("--preset", choices=PRESETS + SCHEDULES, default=None, metavar="{synthetic,real}",
                   help="PolarGS values of the paper for synthetic data or real captures (default synthetic); "
                   "the old --preset cpu|paper still selects the schedule, with a note")
    p.add_argument("--factor", type=positive_float, default=None, metavar="F",
                   help="vanilla schedule factor of --schedule cpu (default 1/6: 5000 iterations; the PolarGS "
                        "schedules get min(1, 3F): Dense 500-3500 every 50, L_dn from 3500)")
    p.add_argument("--iters", type=positive_int, default=None, metavar="N", help="number of iterations (default: the schedule's)")
    p.add_argument(
        "--polar",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="use the PolarGS hooks (--no-polar: plain 3DGS, the ablation baseline; "
        "default: PolarGS when polargs_plugin.hooks is available)",
    )
    g = p.add_argument_group("PolarGS ablation switches (applied after --preset and --config)")
    g.add_argument("--no-pc", action="store_true", help="no photometric correction (module PC; PolarConfig.correction.enabled)")
    g.add_argument("--no-dense", action="store_true", help="no polar PatchMatch densification (module Dense; densify.enabled)")
    g.add_argument("--no-ref-loss", action="store_true", help="no reflection-aware colour loss L_ref (losses.use_ref)")
    g.add_argument("--no-normal-loss", action="store_true", help="no normal loss L_n (losses.use_normal)")
    g.add_argument("--no-depth-normal-loss", action="store_true", help="no depth-normal loss L_dn (losses.use_depth_normal)")
    g.add_argument("--no-scale-loss", action="store_true", help="no flatness loss L_scale (losses.use_scale)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                   help='settings file {"polar": {...}, "train": {...}}: any PolarConfig / TrainConfig field, nested '
                   "(e.g. {\"train\": {\"density\": {\"max_gaussians\": 3000}}}); unknown keys are an error")
    p.add_argument("--maps-cache", type=Path, default=None, metavar="DIR",
                   help="PolarGS maps cache (a folder of maps, or a `polargs preprocess --out` folder holding maps/); "
                   "default RUN_DIR/maps, seeded from DATASET/preprocessed/maps when that exists")
    p.add_argument("--seed", type=int, default=0, help="random seed; equal seeds give identical runs (default 0)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt (same data: checked)")
    p.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda (default: cuda if available)")
    p.add_argument(
        "--checkpoint-every", type=non_negative_int, default=None, metavar="N",
        help="save the checkpoint every N iterations (default: every 10 %% of the run; 0: only at the end)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_reader_options(p)
    p.set_defaults(func=run)


# ------------------------------------------------------------------------------ data
def reader_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The reader options given on the command line (only those given)."""
    kwargs: dict[str, Any] = {}
    if getattr(args, "pattern", None) is not None:
        kwargs["pattern"] = args.pattern
    if getattr(args, "bit_depth", None) is not None:
        kwargs["bit_depth"] = args.bit_depth
    if getattr(args, "sfm", False):
        kwargs["sfm"] = True
    if getattr(args, "no_pattern_check", False):
        kwargs["check_pattern"] = False
    return kwargs


_FLAGS = {"pattern": "--pattern", "bit_depth": "--bit-depth", "sfm": "--sfm", "check_pattern": "--no-pattern-check"}


def load_dataset(spec: str, fmt: str = "auto", info: dict | None = None, **options: Any) -> list:
    """Views of ``spec``: a dataset folder (format detected) or ``synthetic:NAME``.

    Args:
        spec: the DATASET argument.
        fmt: dataset format or "auto".
        info: a dict filled with ``format`` and, for polar folders, what the reader found
            (``pattern``, ``colour_evidence``, ``model``, ``sfm``).
        **options: reader options (``pattern``, ``bit_depth``, ``sfm``, ``check_pattern``);
            for a polar folder with raw mosaics ``pattern`` defaults to "auto". An option the
            dataset's reader does not take is an error naming the option.

    ``summary.json``'s ``reader`` entry holds the options that reproduce a run's views:
    ``load_dataset(summary["dataset"], **summary["reader"])``.
    """
    info = {} if info is None else info
    if spec.startswith("synthetic:"):
        from polargs_plugin.data.synthetic import SCENE_NAMES, generate_scene

        if options:
            flags = ", ".join(_FLAGS.get(k, k) for k in options)
            raise PolarInputError(spec, f"{flags} apply to dataset folders, not to a bundled synthetic scene")
        name = spec.split(":", 1)[1]
        if name not in SCENE_NAMES:
            raise PolarInputError(spec, f"unknown synthetic scene '{name}' (known: {', '.join(SCENE_NAMES)})")
        info["format"] = "synthetic"
        return generate_scene(name, num_views=24, width=128, height=128).views
    path = Path(spec)
    if not path.exists():
        raise PolarInputError(path, "dataset not found")
    from polargs_plugin.data.registry import FORMATS, detect_format, load_views, reader_options

    if fmt != "auto" and fmt not in FORMATS:
        raise PolarInputError(path, f"--format {fmt}: unknown format (known: auto, {', '.join(FORMATS)})")
    fmt = detect_format(path) if fmt == "auto" else fmt
    info["format"] = fmt
    known = reader_options(fmt)
    unknown = [k for k in options if k not in known]
    if unknown:
        flags = ", ".join(_FLAGS.get(k, k) for k in unknown)
        raise PolarInputError(path, f"{flags}: only for polar folders (images or raw mosaics with a COLMAP model); this is a {fmt} dataset")
    kwargs = dict(options)
    if "info" in known:
        kwargs.setdefault("pattern", "auto")
        kwargs["info"] = info
    return load_views(path, fmt, **kwargs)


def reader_record(args: argparse.Namespace, info: dict) -> dict[str, Any]:
    """The reader options that read the same views again (for summary.json; no SfM: its model is
    written in the dataset folder)."""
    record: dict[str, Any] = {}
    if info.get("format") not in (None, "synthetic") and args.format != "auto":
        record["fmt"] = args.format
    if info.get("pattern") is not None:
        record["pattern"] = info["pattern"]
    if args.bit_depth is not None:
        record["bit_depth"] = args.bit_depth
    if args.no_pattern_check:
        record["check_pattern"] = False
    return record


def fingerprint(views: list) -> dict[str, Any]:
    """What a run is trained on, per view: name, size, camera (K, world_to_camera) and image
    content (SHA-256 of the Stokes and mask, and an 8x8 thumbnail of s0 for a tolerant check)."""
    import torch
    import torch.nn.functional as F

    entries = []
    for view in views:
        digest = hashlib.sha256()
        for tensor in (view.stokes, view.mask):
            if tensor is None:
                digest.update(b"none")
                continue
            array = tensor.detach().cpu().contiguous().numpy()
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(array.tobytes())
        s0 = view.stokes[0].detach().cpu().float()
        thumb = F.adaptive_avg_pool2d(s0.mean(0, keepdim=True)[None], (8, 8))[0, 0]
        entries.append({
            "name": view.name,
            "size": [int(view.width), int(view.height)],
            "K": view.K.detach().cpu().double().reshape(-1).tolist(),
            "world_to_camera": view.world_to_camera.detach().cpu().double().reshape(-1).tolist(),
            "image_sha256": digest.hexdigest(),
            "thumbnail": [round(float(v), 6) for v in thumb.reshape(-1)],
        })
    del torch
    return {"format": FINGERPRINT_FORMAT, "views": entries}


def compare_fingerprints(stored: dict[str, Any], current: dict[str, Any]) -> str | None:
    """None when ``current`` is the data of ``stored`` (tolerant to float noise), else the problem."""
    old, new = stored.get("views", []), current["views"]
    old_names, new_names = [v.get("name") for v in old], [v["name"] for v in new]
    if old_names != new_names:
        return (
            f"this run was trained on {len(old_names)} views ({', '.join(map(str, old_names[:5]))}"
            f"{', ...' if len(old_names) > 5 else ''}), the dataset has {len(new_names)} "
            f"({', '.join(new_names[:5])}{', ...' if len(new_names) > 5 else ''})"
        )

    def close(a: list, b: list, tolerance: float) -> bool:
        if len(a) != len(b):
            return False
        scale = max([abs(x) for x in a + b] + [1e-12])
        return all(abs(x - y) <= tolerance * scale for x, y in zip(a, b))

    cameras, images = [], []
    for a, b in zip(old, new):
        if a.get("size") != b["size"] or not close(a.get("K", []), b["K"], 1e-6) or not close(
            a.get("world_to_camera", []), b["world_to_camera"], 1e-6
        ):
            cameras.append(b["name"])
        if a.get("image_sha256") != b["image_sha256"] and not close(a.get("thumbnail", []), b["thumbnail"], 1e-3):
            images.append(b["name"])
    if not cameras and not images:
        return None
    parts = []
    for what, names in (("cameras", cameras), ("images", images)):
        if names:
            parts.append(f"the {what} of {len(names)} of {len(new)} views ({', '.join(names[:5])}{', ...' if len(names) > 5 else ''})")
    return " and ".join(parts) + " differ from those this run was trained on"


# ------------------------------------------------------------------------------ settings
def _check_merge(config: Any, override: Any, where: str, source: str) -> dict[str, Any]:
    """The settings of the dataclass ``config`` as a dict, with ``override`` (a nested, partial
    dict) merged in: unknown keys and values that do not fit their field's type raise
    (:func:`polargs_plugin.config.check_setting`)."""
    from dataclasses import asdict, fields, is_dataclass
    from typing import get_type_hints

    from polargs_plugin.config import check_setting

    if not isinstance(override, dict):
        raise PolarInputError(source, f"{where}: expected an object of settings, got {json.dumps(override)}")
    merged = {f.name: getattr(config, f.name) for f in fields(config)}
    hints = get_type_hints(type(config))
    for key, value in override.items():
        if key not in merged:
            raise PolarInputError(source, f"unknown key '{where}.{key}' (known: {', '.join(sorted(merged))})")
        if is_dataclass(merged[key]):
            merged[key] = _check_merge(merged[key], value, f"{where}.{key}", source)
            continue
        try:
            merged[key] = check_setting(value, hints[key], f"{where}.{key}")
        except ValueError as err:
            raise PolarInputError(source, str(err)) from None
    return {key: asdict(value) if is_dataclass(value) else value for key, value in merged.items()}


def load_config_file(path: Path | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(polar overrides, train overrides)`` of a ``{"polar": {...}, "train": {...}}`` file."""
    if path is None:
        return {}, {}
    try:
        data = json.loads(Path(path).read_text())
    except OSError as err:
        raise PolarInputError(path, f"cannot read the settings file ({err.strerror or err})") from None
    except ValueError as err:
        raise PolarInputError(path, f"not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise PolarInputError(path, 'expected {"polar": {...}, "train": {...}}')
    for key in data:
        if key not in ("polar", "train"):
            raise PolarInputError(path, f"unknown key '{key}' (expected {{\"polar\": {{...}}, \"train\": {{...}}}})")
    for key in ("polar", "train"):
        if not isinstance(data.get(key, {}), dict):
            raise PolarInputError(path, f"'{key}' must be an object of settings")
    return data.get("polar", {}), data.get("train", {})


def polar_config(preset: str, factor: float | None, overrides: dict[str, Any], source: str, switches: dict[str, bool] | None = None):
    """The PolarConfig of a run: the paper preset, its schedules scaled for a vanilla schedule
    factor ``factor`` (``polar_schedule_factor``; None: not scaled, the paper schedule),
    ``overrides`` (checked), then the ablation switches."""
    from polargs_plugin.config import PolarConfig, polar_schedule_factor

    config = PolarConfig.real() if preset == "real" else PolarConfig.synthetic()
    if factor is not None:
        # The schedule fields cpu_demo scales (whatever they are): taken from it, onto the preset.
        scaled, plain = PolarConfig.cpu_demo(polar_schedule_factor(factor)).to_dict(), PolarConfig.synthetic().to_dict()
        config.update(_changed(plain, scaled))
    data = _check_merge(config, overrides, "polar", source)
    config = PolarConfig.from_dict(data)
    for name, on in (switches or {}).items():
        if on:
            section, field = SWITCHES[name]
            setattr(getattr(config, section), field, False)
    return config


def _changed(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for key, value in b.items():
        if isinstance(value, dict):
            sub = _changed(a[key], value)
            if sub:
                out[key] = sub
        elif a[key] != value:
            out[key] = value
    return out


def train_config(schedule: str, factor: float | None, overrides: dict[str, Any], source: str, extra: dict[str, Any]):
    """The TrainConfig of a run: the schedule, ``overrides`` (checked), then ``extra`` (flags)."""
    from polargs_plugin.backends.reference.trainer import TrainConfig

    if schedule == "cpu":
        base = TrainConfig.cpu() if factor is None else TrainConfig.cpu(factor)
    else:
        base = TrainConfig.paper()
    data = _check_merge(base, overrides, "train", source)
    data.update(extra)
    try:
        return TrainConfig.from_dict(data)
    except (TypeError, ValueError) as err:
        raise PolarInputError(source, f"invalid train settings ({err})") from None


# ------------------------------------------------------------------------------ maps cache
def _maps_entries(views: list, config, folder: Path) -> dict[str, Path]:
    """{view name: its cache file in ``folder``} for the maps of ``config``."""
    from polargs_plugin.hooks import maps_cache_file, maps_cache_key

    return {view.name: maps_cache_file(folder, view, maps_cache_key(view, config)) for view in views}


def prepare_maps_cache(views: list, config, out: Path, given: Path | None, dataset: str) -> tuple[Path, str]:
    """Choose the maps cache of a run (and seed it); returns (folder, what to print)."""
    import shutil

    if given is not None:
        folder = given / MAPS_NAME if (given / MAPS_NAME).is_dir() else given
        check_writable(folder)
        entries = _maps_entries(views, config, folder)
        found = sum(path.is_file() for path in entries.values())
        return folder, f"maps: {found} of {len(views)} views cached in {folder}" + ("" if found == len(views) else ", the others computed now")
    folder = out / MAPS_NAME
    entries = _maps_entries(views, config, folder)
    found = sum(path.is_file() for path in entries.values())
    copied, source_dir = 0, None
    if found < len(views) and not dataset.startswith("synthetic:"):
        source_dir = Path(dataset) / PREPROCESSED_NAME / MAPS_NAME
        if source_dir.is_dir():
            for view in views:
                target = entries[view.name]
                source = source_dir / target.name
                if not target.is_file() and source.is_file():
                    folder.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source, target)
                    copied += 1
    if copied:
        return folder, f"maps: reused {copied} of {len(views)} views from {source_dir} (`polargs preprocess`), copied into {folder}"
    if found:
        return folder, f"maps: reused {found} of {len(views)} views from {folder}"
    return folder, f"maps: computing {len(views)} views (cached in {folder})"


# ------------------------------------------------------------------------------ stopping
class _Stop:
    """SIGINT / SIGTERM: the first asks the training to stop after the current iteration (raised
    as KeyboardInterrupt at the step boundary); a second stops at once."""

    def __init__(self) -> None:
        self.signal: int | None = None
        self.hard = False
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        if self.signal is not None or not self.armed:
            self.signal = signum
            self.hard = True
            raise KeyboardInterrupt
        self.signal = signum
        print(f"\n{signal.Signals(signum).name}: stopping after this iteration (again to stop at once)", file=sys.stderr, flush=True)

    armed = False

    def install(self) -> None:
        for signum in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[signum] = signal.signal(signum, self._handler)
            except (ValueError, OSError):  # not the main thread
                pass

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            with contextlib.suppress(ValueError, OSError):
                signal.signal(signum, handler)
        self._previous.clear()

    def wrap_step(self, trainer) -> None:
        step = trainer.step

        def step_then_check():
            logs = step()
            if self.signal is not None:
                raise KeyboardInterrupt
            return logs

        trainer.step = step_then_check
        self.armed = True

    @property
    def exit_status(self) -> int:
        return 128 + int(self.signal if self.signal is not None else signal.SIGINT)


def _resume_command(args: argparse.Namespace) -> str:
    argv = [a for a in getattr(args, "_argv", None) or [] if a != "--resume"]
    if not argv or argv[0] != "train":
        argv = ["train", args.dataset, "--out", str(args.out)]
    return shlex.join(["polargs", *argv, "--resume"])


# ------------------------------------------------------------------------------ run
def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from polargs_plugin.backends.reference.trainer import TrainingDiverged

    schedule, preset = args.schedule, args.preset
    if preset in SCHEDULES:  # the old meaning of --preset
        if schedule is not None and schedule != preset:
            return _fail(f"--preset {preset}: the old name of --schedule {preset}, which contradicts --schedule {schedule}")
        print(f"note: --preset {preset} is now --schedule {preset} (--preset chooses the PolarGS values: synthetic or real)",
              file=sys.stderr)
        schedule, preset = preset, None
    schedule, preset = schedule or "cpu", preset or "synthetic"
    switches = {name: bool(getattr(args, name, False)) for name in SWITCHES}
    used = [f"--{name.replace('_', '-')}" for name, on in switches.items() if on]
    if args.polar is False and used:
        return _fail(f"{', '.join(used)}: switches of the PolarGS hooks, which --no-polar turns off")
    if args.factor is not None and schedule != "cpu":
        return _fail("--factor: scales the cpu schedule only (drop it, or use --schedule cpu)")
    source = str(args.config) if args.config is not None else "settings"
    out = Path(args.out)
    checkpoint = out / CHECKPOINT_NAME
    created = not out.exists()
    stop = _Stop()
    lock = None
    stage = "before training started"
    trainer = None
    try:
        # settings first: a typo costs nothing
        polar_overrides, train_overrides = load_config_file(args.config)
        import torch

        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise PolarInputError("--device", f"{device} is not available on this machine")
        extra = {"seed": args.seed, "device": device, "progress": not args.quiet}
        if args.iters is not None:
            extra["iterations"] = args.iters
        config = train_config(schedule, args.factor if schedule == "cpu" else None, train_overrides, source, extra)
        factor = config.schedule_scale if schedule == "cpu" else None
        hooks_wanted = args.polar is not False
        pconfig = polar_config(preset, factor, polar_overrides, source, switches) if hooks_wanted else None
        if pconfig is None and polar_overrides:
            raise PolarInputError(source, "has \"polar\" settings but --no-polar trains without the PolarGS hooks")
        # the run folder: writable, ours, and in the state --resume says
        check_writable(out)
        lock = FolderLock(out / LOCK_NAME, command=shlex.join(["polargs", *(getattr(args, "_argv", None) or ["train"])]))
        lock.acquire()
        if lock.note:
            print(f"note: {lock.note}", file=sys.stderr)
        stop.install()
        if checkpoint.exists() and not args.resume:
            raise PolarInputError(checkpoint, "exists; pass --resume to continue it or choose another --out")
        if args.resume and not checkpoint.exists():
            raise PolarInputError(checkpoint, "--resume given but the file does not exist")
        info: dict[str, Any] = {}
        views = load_dataset(args.dataset, args.format, info, **reader_kwargs(args))
        if not views:
            raise PolarInputError(args.dataset, "the dataset holds no views")
        if info.get("pattern"):
            evidence = info.get("colour_evidence") or {}
            how = "given" if args.pattern not in (None, "auto") else "told from the frames"
            print(f"raw mosaics: {info['pattern']} ({how}; Bayer colour structure in "
                  f"{', '.join(f'{100 * v:.0f} %' for v in list(evidence.values())[:4] if v is not None) or '-'} of bright blocks)")
        if info.get("sfm"):
            print(f"SfM: model written to {info.get('model')}")
        prints = fingerprint(views)
        fingerprint_path = out / FINGERPRINT_NAME
        if args.resume:
            if fingerprint_path.is_file():
                try:
                    stored = json.loads(fingerprint_path.read_text())
                except (OSError, ValueError) as err:
                    raise PolarInputError(fingerprint_path, f"unreadable ({err}); delete it to resume without the data check") from None
                problem = compare_fingerprints(stored, prints)
                if problem is not None:
                    raise PolarInputError(fingerprint_path, f"--resume on other data than {args.dataset} was: {problem}; "
                                          "resume with the original data or choose another --out")
            else:
                print(f"note: {fingerprint_path}: missing (an older run); only the view names are checked", file=sys.stderr)
        hooks = _make_hooks(args.polar, pconfig)
        maps_note = None
        if hooks is not None:
            cache, maps_note = prepare_maps_cache(views, hooks.config, out, args.maps_cache, args.dataset)
            hooks.config.cache_dir = str(cache)
        from polargs_plugin.backends.reference.trainer import Trainer

        try:
            trainer = Trainer(views, config, hooks=hooks)
        except ValueError as err:
            raise PolarInputError(source, str(err)) from None
        if maps_note:
            print(maps_note)
        if args.resume:
            trainer.load_checkpoint(checkpoint)
        if trainer.iteration >= config.iterations:
            raise PolarInputError(checkpoint, f"already at iteration {trainer.iteration}; give a larger --iters to continue")
        every = args.checkpoint_every
        if every is None:
            every = max(1, math.ceil(config.iterations / CHECKPOINTS_PER_RUN))
        if not args.resume or not fingerprint_path.is_file():
            with atomic_write(fingerprint_path) as f:
                json.dump({**prints, "dataset": args.dataset}, f)
        stop.wrap_step(trainer)
        stage = "during training"
        start = time.perf_counter()
        figures = trainer.train(checkpoint=checkpoint, checkpoint_every=every)
        stage = "after training"
    except KeyboardInterrupt:
        return _interrupted(args, stop, trainer, checkpoint, stage, out, created)
    except TrainingDiverged as err:  # the last periodic checkpoint (if any) predates the bad values
        return _fail(f"{args.out}: training stopped: {err}")
    except PolarInputError as err:
        if stage == "before training started" and created:
            _remove_if_empty(out, lock)
        return _fail(str(err))
    except OSError as err:
        where = err.filename or args.out
        return _fail(f"{where}: {err.strerror or err}")
    finally:
        stop.restore()
        if lock is not None:
            lock.release()
            if created and stage == "before training started":
                _remove_if_empty(out, None)
    summary = {
        "dataset": args.dataset,
        "dataset_format": info.get("format"),
        "reader": reader_record(args, info),
        "num_views": len(views),
        "polar": hooks is not None,
        "schedule": schedule,
        "preset": preset if hooks is not None else None,
        "switches": used,
        "config_file": None if args.config is None else str(args.config),
        "resumed": bool(args.resume),
        "checkpoint": str(checkpoint),
        "checkpoint_every": every,
        "maps_cache": None if hooks is None else hooks.config.cache_dir,
        "wall_seconds": time.perf_counter() - start,
        **figures,
        "config": config.to_dict(),
        "polar_config": None if hooks is None else hooks.config.to_dict(),
    }
    try:
        with atomic_write(out / SUMMARY_NAME) as f:
            json.dump(summary, f, indent=2)
    except OSError as err:
        return _fail(f"{out / SUMMARY_NAME}: cannot write ({err.strerror or err}); the checkpoint is saved")
    print(
        f"done: {figures['iterations']} iterations, {figures['num_gaussians']} Gaussians, "
        f"training-view PSNR {figures['psnr']:.2f} dB, {figures['seconds']:.0f} s -> {out}"
    )
    return 0


def _remove_if_empty(out: Path, lock: FolderLock | None) -> None:
    if lock is not None:
        lock.release()
    with contextlib.suppress(OSError):
        out.rmdir()  # only succeeds when empty: a folder this command created and left unused


def _interrupted(args, stop: _Stop, trainer, checkpoint: Path, stage: str, out: Path, created: bool) -> int:
    status = stop.exit_status
    fresh = not args.resume
    if trainer is None or stage != "during training" or (trainer.iteration == 0 and fresh):
        print(f"interrupted {stage if stage != 'during training' else 'before the first iteration'}; "
              "nothing trained, no checkpoint written", file=sys.stderr)
        if fresh:
            with contextlib.suppress(OSError):
                (out / FINGERPRINT_NAME).unlink()
            if created:
                _remove_if_empty(out, None)
        return status
    if stop.hard:
        # stopped inside an iteration: its state may be half-updated, so it is not saved
        if checkpoint.is_file():
            print(f"interrupted during iteration {trainer.iteration + 1}; {checkpoint} keeps the last periodic "
                  f"checkpoint; resume with: {_resume_command(args)}", file=sys.stderr)
        else:
            with contextlib.suppress(OSError):
                (out / FINGERPRINT_NAME).unlink()
            print(f"interrupted during iteration {trainer.iteration + 1}, before the first periodic checkpoint; "
                  "nothing to resume", file=sys.stderr)
        return status
    try:
        trainer.save_checkpoint(checkpoint)
    except OSError as err:
        print(f"error: {checkpoint}: interrupted at iteration {trainer.iteration} but the checkpoint could not be "
              f"written ({err.strerror or err})", file=sys.stderr)
        return status
    print(f"interrupted at iteration {trainer.iteration}; resume with: {_resume_command(args)}", file=sys.stderr)
    return status


def _make_hooks(polar: bool | None, config):
    """PolarHooks for ``--polar`` (required) or the default (when importable); None otherwise."""
    if polar is False:
        return None
    try:
        from polargs_plugin.hooks import PolarHooks
    except ImportError as err:
        if polar:
            raise PolarInputError("--polar", f"needs polargs_plugin.hooks, which cannot be imported ({err})") from None
        print(f"note: PolarGS hooks unavailable ({err}); training plain 3DGS", file=sys.stderr)
        return None
    try:
        return PolarHooks(config)
    except (TypeError, ValueError) as err:
        raise PolarInputError("settings", f"invalid PolarGS settings ({err})") from None
