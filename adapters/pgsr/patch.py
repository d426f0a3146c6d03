"""Insert the PolarGS hook calls into zju3dv/PGSR's ``train.py``.

    python adapters/pgsr/patch.py CHECKOUT [--dry-run] [--revert] [--force]

Verified against PGSR de24f1a. PGSR's render() takes the exposure ``app_model``: its name is taken
from the training render call (which spans two lines upstream) and handed to ``attach``. The
densify hook goes after the optimizer steps, i.e. after the same-iteration multi-view trim.
What goes where: docs/adapters/patching.md. Needs only the standard library (Python 3.8+).
"""

import runpy
import sys
from pathlib import Path

engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))  # standard library only
anchors = engine["load"]("inria_anchors")
main = engine["load"]("patching").main

ANCHORS = anchors.inria_anchors(
    "pgsr",
    render_tail=r"\s*,(?:.*?,)?\s*app_model\s*=\s*(?P<app_model>\w+)\s*(?:,.*)?\)$",
    render_tail_looks_for=", ..., app_model=<app_model>, ...",
    attach_extra=", app_model={app_model}",
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
