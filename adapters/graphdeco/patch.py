"""Insert the PolarGS hook calls into graphdeco-inria/gaussian-splatting's ``train.py``.

    python adapters/graphdeco/patch.py CHECKOUT [--dry-run] [--revert] [--force]

Recognises the 2023 loop (472689c, the base GOF and PGSR fork) and the 2024 one (54c035f: exposure,
sparse Adam, depth regulariser); the keyword arguments of the training render call (2024:
``use_trained_exp``, ``separate_sh``) are handed to ``attach``, which runs before the loop: a
keyword whose value is first assigned inside the loop is refused. Relatives with their own
script are refused with a pointer to it: a render call passing ``kernel_size`` (mip-splatting,
GOF) and a loop reading 2DGS's ``rend_normal``. What goes where: docs/adapters/patching.md.
Needs only the standard library (Python 3.8+).
"""

import runpy
import sys
from pathlib import Path

engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))  # standard library only
anchors = engine["load"]("inria_anchors")
main = engine["load"]("patching").main

ANCHORS = anchors.inria_anchors(
    "graphdeco",
    render_tail=r"(?P<render_extra>(?:\s*,\s*\w+\s*=\s*[^,]+?)*)\s*,?\s*\)$",
    render_tail_looks_for="[, key=value...]",
    attach_extra="{render_extra}",
    checks=(
        anchors.render_keyword(
            "kernel_size", "the training render call passes kernel_size, as mip-splatting and GOF do: " + anchors.MIP_SPLATTING
        ),
        anchors.loop_reads(
            "2DGS outputs", anchors.TWODGS_OUTPUTS, refuse="the loop reads 2DGS's outputs: use adapters/twodgs/patch.py"
        ),
    ),
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
