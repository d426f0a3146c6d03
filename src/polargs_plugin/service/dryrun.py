"""A dry run of a patched upstream trainer (``polargs dryrun``; docs/adapters/dryrun.md).

:func:`dry_run` first checks that the environment has every module the trainer's script
requires (:mod:`polargs_plugin.dryrun.requirements`), then makes a small scene the trainer reads (``generate --export colmap``, cached in
the work folder), writes the PolarGS settings that shrink Dense's window to the run, then starts
:mod:`polargs_plugin.dryrun.launch` twice with the trainer's own ``train.py`` and a shrunk
schedule: once patched (the checkout's ``train.py``) and once unpatched (a copy without the marked
lines, in the work folder; the checkout is never written). It returns one :class:`Check` per
line the command prints.
"""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from statistics import mean
from typing import Callable, Sequence

from polargs_plugin.dryrun.requirements import install_command, missing_modules
from polargs_plugin.dryrun.trainers import TRAINERS, dense_settings, served_modules, trainer_arguments
from polargs_plugin.io import PolarInputError, atomic_write, write_json
from polargs_plugin.kit.patching import is_marked, strip_marked
from polargs_plugin.service.provenance import provenance
from polargs_plugin.service.runs import SUMMARY_NAME
from polargs_plugin.service.scenes import SceneRequest, generate_scene_folder

__all__ = ["DryRunRequest", "Check", "DryRunResult", "dry_run", "verdict", "describe", "write_summary", "WARMUP_STEPS",
           "SUMMARY_FORMAT", "launch_trainer", "train_script", "environment", "free_port"]

#: Steps left out of the step-time ratio (numba compilation, first allocations).
WARMUP_STEPS = 10


@dataclass(frozen=True)
class DryRunRequest:
    """One dry run.

    Attributes:
        checkout: the trainer's checkout, its ``train.py`` patched by ``adapters/<name>/patch.py``.
        trainer: a name of :data:`polargs_plugin.dryrun.trainers.TRAINERS`.
        workdir: where the scene, the settings, the outputs and the logs go (kept afterwards).
        iterations: training iterations of each run (>= 4 * interval).
        interval: iterations between the trainer's densifications and between Dense calls.
        train_arguments: more ``train.py`` arguments, after the dry run's own (they win).
        scene: the bundled scene to train on.
        views, width, height: its size.
        compare: also run the unpatched copy (for the step-time ratio).
        timeout: seconds each run may take.
        command: the command line, recorded in the work folder's ``summary.json`` (None: this
            process's).
    """

    checkout: Path
    trainer: str
    workdir: Path
    iterations: int = 300
    interval: int = 30
    train_arguments: tuple[str, ...] = ()
    scene: str = "bumpy_mixed"
    views: int = 16
    width: int = 64
    height: int = 48
    compare: bool = True
    timeout: float = 1800.0
    command: str | None = None


@dataclass
class Check:
    """One line of the verdict.

    Attributes:
        name: what was checked.
        ok: True passed, False failed, None information only.
        detail: the figures behind it.
    """

    name: str
    ok: bool | None
    detail: str


@dataclass
class DryRunResult:
    """What :func:`dry_run` found.

    Attributes:
        checks: the verdict, one :class:`Check` per line.
        reports: the probe's report of each run ("patched", "unpatched").
        logs: each run's output file.
    """

    checks: list[Check]
    reports: dict[str, dict] = field(default_factory=dict)
    logs: dict[str, Path] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """No check failed."""
        return all(check.ok is not False for check in self.checks)


def train_script(checkout: Path, trainer: str) -> tuple[Path, str]:
    """The checkout's training script for ``trainer`` and its text, refused (PolarInputError
    naming the file) when missing, unpatched, not compilable or importing modules this
    environment lacks."""
    if trainer not in TRAINERS:
        raise PolarInputError("--trainer", f"unknown trainer {trainer!r} (choose one of {', '.join(sorted(TRAINERS))})")
    spec = TRAINERS[trainer]
    script = checkout / spec.script
    if not script.is_file():
        where = "the folder holding it (gsplat: examples/)" if spec.family == "gsplat" else "the trainer's checkout folder"
        raise PolarInputError(checkout, f"has no {spec.script} (give {where})")
    text = script.read_text(encoding="utf-8", errors="surrogateescape")
    if not any(is_marked(line) for line in text.splitlines()):
        adapter = spec.adapter
        raise PolarInputError(script, f"is not patched: run `python adapters/{adapter}/patch.py {checkout}` first")
    _check_compiles(script, text)
    _check_imports(checkout, script, trainer)
    return script, text


def _check_imports(checkout: Path, script: Path, trainer: str) -> None:
    """Refuse a checkout whose training script requires modules this environment lacks, naming
    them all in one line with the command that installs them: a run would stop at the first."""
    missing = missing_modules(checkout, script, served_modules(TRAINERS[trainer]))
    if missing:
        raise PolarInputError(checkout, f"{script.name} imports modules this environment lacks: {', '.join(missing)}"
                                        f" — install them with: {install_command(missing)}")


def _check_compiles(script: Path, text: str) -> None:
    """Refuse a trainer Python cannot compile, naming its file and line: a run of it would stop
    at once, and every check after would only repeat that."""
    try:
        compile(text, str(script), "exec")
    except SyntaxError as err:  # IndentationError and TabError are SyntaxErrors too
        where = f"{script}:{err.lineno}" if err.lineno else str(script)
        raise PolarInputError(where, f"Python cannot compile it: {type(err).__name__}: {err.msg}") from None


def _scene(request: DryRunRequest) -> Path:
    """The work folder's scene (made once; a later dry run in the same folder reuses it)."""
    folder = request.workdir / f"scene-{request.scene}-{request.views}x{request.width}x{request.height}"
    if not (folder / "colmap" / "sparse" / "0" / "cameras.txt").is_file():
        scene = SceneRequest(request.scene, views=request.views, width=request.width, height=request.height)
        generate_scene_folder(scene, folder, overwrite=folder.exists(), export="colmap")
    return folder


def free_port() -> int:
    """A free local TCP port for the trainer's viewer socket (graphdeco-family ``--port``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _package_paths() -> list[str]:
    """Folders that make ``polargs_plugin`` and ``polargs_adapters`` importable in the child."""
    paths = []
    for name in ("polargs_plugin", "polargs_adapters"):
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            raise PolarInputError(name, "is not importable: install polargs_plugin (it brings polargs_adapters)")
        paths.append(str(Path(next(iter(spec.submodule_search_locations))).parent))
    return list(dict.fromkeys(paths))


def environment(scene: Path, settings: Path) -> dict[str, str]:
    """The environment of a launch: this one, with the scene (``POLARGS_DATA``), the synthetic
    preset, the PolarGS settings file and the paths that make the package importable."""
    env = dict(os.environ)
    env.update(POLARGS_DATA=str(scene), POLARGS_PRESET="synthetic", POLARGS_CONFIG=str(settings))
    env["PYTHONPATH"] = os.pathsep.join([*_package_paths(), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _run(label: str, script: Path, request: DryRunRequest, scene: Path, env: dict[str, str], port: int
         ) -> tuple[dict, Path]:
    """One launch; returns its report (a failure report when it wrote none) and its log."""
    spec = TRAINERS[request.trainer]
    model_path = request.workdir / f"run-{label}"
    arguments = [*trainer_arguments(spec, scene / "colmap", model_path, port, request.iterations, request.interval),
                 *request.train_arguments]
    return launch_trainer(request.trainer, request.checkout, script, arguments, model_path, request.workdir, label, env,
                          request.timeout)


def launch_trainer(trainer: str, checkout: Path, script: Path, arguments: Sequence[str], model_path: Path, workdir: Path,
                   label: str, env: dict[str, str], timeout: float) -> tuple[dict, Path]:
    """Run ``script`` (the checkout's training script or a copy) with ``arguments`` in the dry
    run's process (:mod:`polargs_plugin.dryrun.launch`), its output in ``model_path``, its report
    and log in ``workdir`` under ``label``; returns the report (a failure report when it wrote
    none) and the log's path."""
    report_path = workdir / f"report-{label}.json"
    log_path = workdir / f"{label}.log"
    report_path.unlink(missing_ok=True)
    command = [sys.executable, "-m", "polargs_plugin.dryrun.launch", "--trainer", trainer,
               "--checkout", str(checkout), "--script", str(script), "--report", str(report_path),
               "--model-path", str(model_path), "--", *arguments]
    with open(log_path, "w") as log:
        try:
            subprocess.run(command, cwd=checkout, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=timeout,
                           check=False)
        except subprocess.TimeoutExpired:
            return {"finished": False, "error": f"no result within {timeout:.0f} s"}, log_path
    if not report_path.is_file():
        return {"finished": False, "error": f"the run wrote no report (see {log_path})"}, log_path
    return json.loads(report_path.read_text()), log_path


def dry_run(request: DryRunRequest, progress: Callable[[str], None] | None = None) -> DryRunResult:
    """Run the patched and (with ``compare``) unpatched ``train.py`` of ``request.checkout`` and
    check them (module docstring).

    Raises:
        PolarInputError: an unknown trainer, no ``train.py``, an unpatched one or one Python cannot
            compile (naming its file and line), one that requires modules this environment lacks
            (naming them all and the command that installs them), too few iterations.
    """
    say = progress or (lambda message: None)
    # the runs start in the checkout: relative paths would be read from there
    request = replace(request, checkout=request.checkout.resolve(), workdir=request.workdir.resolve())
    if request.iterations < 4 * request.interval or request.interval < 1:
        raise PolarInputError("--iters", f"needs at least 4 intervals of {request.interval} iterations")
    script, text = train_script(request.checkout, request.trainer)
    request.workdir.mkdir(parents=True, exist_ok=True)
    say(f"scene: {request.scene}, {request.views} views of {request.width}x{request.height}")
    scene = _scene(request)
    settings = request.workdir / "polargs_settings.json"
    with atomic_write(settings) as handle:
        json.dump(dense_settings(request.iterations, request.interval), handle, indent=1)
    env, port = environment(scene, settings), free_port()
    runs = [("patched", script)]
    if request.compare:
        unpatched = request.workdir / f"{script.stem}_unpatched.py"
        with atomic_write(unpatched) as handle:
            handle.write(strip_marked(text))
        runs.append(("unpatched", unpatched))
    result = DryRunResult(checks=[])
    for label, path in runs:
        say(f"{label}: {request.iterations} iterations of {script}")
        result.reports[label], result.logs[label] = _run(label, path, request, scene, env, port)
    result.checks = verdict(result.reports, request.iterations)
    write_summary(request, result)
    return result


#: What the work folder's ``summary.json`` holds (:func:`write_summary`).
SUMMARY_FORMAT = "polargs-dryrun-v1"


def write_summary(request: DryRunRequest, result: DryRunResult) -> Path:
    """``workdir/summary.json``: the request, the verdict, the runs' reports and logs, and the
    provenance (library versions, commit, command line, machine, threads). Returns its path."""
    summary = {
        "format": SUMMARY_FORMAT,
        "request": {key: str(value) if isinstance(value, Path) else value for key, value in asdict(request).items()},
        "ok": result.ok,
        "checks": [asdict(check) for check in result.checks],
        "reports": result.reports,
        "logs": {label: str(path) for label, path in result.logs.items()},
        "provenance": provenance(request.command),
    }
    path = request.workdir / SUMMARY_NAME
    write_json(path, summary)
    return path


def _mean_step(report: dict) -> float | None:
    steps = report.get("step_seconds") or []
    steps = steps[WARMUP_STEPS:] if len(steps) > 2 * WARMUP_STEPS else steps
    return mean(steps) if steps else None


def verdict(reports: dict[str, dict], iterations: int) -> list[Check]:
    """The checks of the runs' reports (``patched`` required, ``unpatched`` optional)."""
    checks = []
    for label, report in reports.items():
        done = report.get("iterations", 0)
        detail = f"{label}: {done}/{iterations} iterations"
        if report.get("error"):
            detail += f"; {report['error'].splitlines()[-1]}"
        checks.append(Check(f"finished ({label})", bool(report.get("finished")) and done >= iterations - 1, detail))
    for label, report in reports.items():
        first, last = report.get("loss_first"), report.get("loss_last")
        finite = bool(report.get("losses_finite")) and report.get("iterations", 0) > 0
        detail = f"{label}: first {first}, last {last}" if finite else \
            f"{label}: not finite from iteration {report.get('first_nonfinite')}"
        checks.append(Check(f"loss finite ({label})", finite, detail))
    checks.append(_dense_check(reports["patched"]))
    for label, report in reports.items():
        problems = report.get("problems") or []
        detail = "every per-Gaussian statistic and optimizer state had one row per Gaussian after every step" \
            if not problems else f"{len(problems)} problem(s), first: {problems[0]}"
        checks.append(Check(f"per-Gaussian state ({label})", report.get("iterations", 0) > 0 and not problems, detail))
    checkpoint = reports["patched"].get("checkpoint") or {"ok": False, "detail": "no checkpoint check"}
    checks.append(Check("checkpoint (patched)", bool(checkpoint["ok"]), checkpoint["detail"]))
    if "unpatched" in reports:
        patched, unpatched = _mean_step(reports["patched"]), _mean_step(reports["unpatched"])
        detail = "no step times" if not (patched and unpatched) else \
            f"{patched * 1000:.1f} ms / {unpatched * 1000:.1f} ms = {patched / unpatched:.2f}x (CPU stand-ins, not a GPU figure)"
        checks.append(Check("step time patched / unpatched", None, detail))
    return checks


def _dense_check(report: dict) -> Check:
    """Dense appended rows, the trainer's own densification ran after the first append, and
    rows of Dense were still there at the end."""
    rounds = report.get("dense_rounds") or []
    appended = sum(count for _, count in rounds)
    first = next((it for it, count in rounds if count > 0), None)
    later = [it for it in report.get("native_densify") or [] if first is not None and it >= first]
    left = report.get("dense_rows_final")
    detail = (f"{appended} Gaussians appended in {sum(1 for _, c in rounds if c > 0)}/{len(rounds)} Dense calls; "
              f"{len(later)} native densify/prune passes after the first append; "
              f"{left if left is not None else 'unknown'} of Dense's rows left at the end "
              f"({report.get('gaussians_initial')} -> {report.get('gaussians_final')} Gaussians)")
    if report.get("rows_lost"):
        detail += f"; rows not tracked after {report['rows_lost']}"
    ok = appended > 0 and bool(later) and bool(left)
    return Check("Dense appended and survived (patched)", ok, detail)


def describe(checks: Sequence[Check]) -> list[str]:
    """One printed line per check: ``ok``, ``FAIL`` or ``info``, the name, the figures."""
    word = {True: "ok  ", False: "FAIL", None: "info"}
    width = max((len(c.name) for c in checks), default=0)
    return [f"{word[c.ok]}  {c.name:<{width}}  {c.detail}" for c in checks]
