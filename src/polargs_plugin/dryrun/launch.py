"""The process of one dry run: ``python -m polargs_plugin.dryrun.launch --trainer NAME
--checkout DIR --script FILE --report FILE [--model-path DIR] -- <train.py arguments>``.

It maps CUDA to the CPU (:mod:`.cuda_cpu`), serves the trainer's CUDA extensions from the
stand-ins (:mod:`.finder`; for gsplat also single attributes of the installed package; where
pytorch3d is not installed, ``pytorch3d.transforms`` too), puts the
checkout first on ``sys.path``, installs the probe (:class:`.probe.Probe` on the checkout's
``GaussianModel``, or :class:`.probe_gsplat.GsplatProbe` on gsplat's strategies), runs ``FILE`` as
``__main__`` with the given arguments, checks the checkpoint and writes the probe's report (JSON)
to ``--report``. Exit status 0 when the
script returned, 1 when it failed (the report says where). ``polargs dryrun`` starts it; it is not
meant to be run by hand, though it can be.
"""

from __future__ import annotations

import argparse
import json
import runpy
import sys
from pathlib import Path
from typing import Sequence

from polargs_plugin.dryrun import cuda_cpu
from polargs_plugin.dryrun.finder import install_attributes, install_standins
from polargs_plugin.dryrun.probe import Probe, RunProbe, describe_error
from polargs_plugin.dryrun.trainers import TRAINERS, served_modules
from polargs_plugin.io import atomic_write

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m polargs_plugin.dryrun.launch", description=__doc__)
    parser.add_argument("--trainer", required=True, choices=sorted(TRAINERS))
    parser.add_argument("--checkout", required=True, type=Path, help="the trainer's checkout (its modules)")
    parser.add_argument("--script", required=True, type=Path, help="the train.py to run (the checkout's or a copy)")
    parser.add_argument("--report", required=True, type=Path, help="where the JSON report goes")
    parser.add_argument("--model-path", type=Path, help="the run's output folder (checkpoints)")
    parser.add_argument("arguments", nargs=argparse.REMAINDER, help="-- then the train.py arguments")
    return parser


def _probe(family: str, model_path: Path | None) -> RunProbe:
    if family == "gsplat":
        from polargs_plugin.dryrun.probe_gsplat import GsplatProbe

        return GsplatProbe(model_path)
    return Probe(model_path)


def run(trainer: str, checkout: Path, script: Path, model_path: Path | None, arguments: Sequence[str]) -> dict:
    """Run ``script`` with everything installed; returns the report (also when it failed)."""
    spec = TRAINERS[trainer]
    cuda_cpu.install()
    install_standins(served_modules(spec))
    sys.path.insert(0, str(checkout.resolve()))
    finished = False
    probe = _probe(spec.family, model_path)
    try:
        install_attributes(spec.attributes)
        probe.install()
        sys.argv = [str(script), *arguments]
        runpy.run_path(str(script), run_name="__main__")
        finished = True
    except SystemExit as exit_:
        finished = exit_.code in (None, 0)
        if not finished:
            probe.error = f"{script.name} exited with status {exit_.code}"
    except BaseException as err:  # the report carries the failure; the exit status says it too
        probe.error = describe_error(err)
    probe.finish()
    report = probe.report()
    report["finished"] = finished
    report["checkpoint"] = probe.checkpoint() if finished else {"ok": False, "detail": "the run did not finish"}
    probe.uninstall()
    return report


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    arguments = list(args.arguments)
    if arguments[:1] == ["--"]:
        arguments = arguments[1:]
    report = run(args.trainer, args.checkout, args.script, args.model_path, arguments)
    with atomic_write(args.report) as handle:
        json.dump(report, handle)
    return 0 if report["finished"] else 1


if __name__ == "__main__":
    sys.exit(main())
