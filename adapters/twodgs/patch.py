"""Insert the PolarGS hook calls into hbb1/2d-gaussian-splatting's (2DGS) ``train.py``.

    python adapters/twodgs/patch.py CHECKOUT [--dry-run] [--revert] [--force]

Verified against 2DGS 1920a23. The loop is graphdeco's (2023) with 2DGS's normal-consistency and
distortion terms added to ``total_loss`` and a second ``no_grad`` block (the viewer's) after the
one with the optimizer step; the densify hook goes into the first. A loop that does not read 2DGS's
``rend_normal`` / ``rend_dist`` is refused (not a 2DGS loop). What goes where:
docs/adapters/patching.md. Needs only the standard library (Python 3.8+).
"""

import runpy
import sys
from pathlib import Path

engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))  # standard library only
anchors = engine["load"]("inria_anchors")
main = engine["load"]("patching").main

ANCHORS = anchors.inria_anchors(
    "twodgs",
    render_tail=r"(?P<render_extra>(?:\s*,\s*\w+\s*=\s*[^,]+?)*)\s*,?\s*\)$",
    render_tail_looks_for="[, key=value...]",
    attach_extra="{render_extra}",
    checks=(anchors.loop_reads("2DGS outputs", anchors.TWODGS_OUTPUTS),),
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
