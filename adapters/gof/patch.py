"""Insert the PolarGS hook calls into autonomousvision/gaussian-opacity-fields' (GOF) ``train.py``.

    python adapters/gof/patch.py CHECKOUT [--dry-run] [--revert] [--force]

Verified against GOF 5245b20. GOF's render() needs ``kernel_size``: it is taken from the training
render call and handed to ``attach``. The adapter's densify hook recomputes GOF's 3D filter itself.
mip-splatting's loop, whose render call also passes ``subpixel_offset``, is refused.
What goes where: docs/adapters/patching.md. Needs only the standard library (Python 3.8+).
"""

import runpy
import sys
from pathlib import Path

engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))  # standard library only
anchors = engine["load"]("inria_anchors")
main = engine["load"]("patching").main

ANCHORS = anchors.inria_anchors(
    "gof",
    render_tail=(
        r"\s*,\s*(?:kernel_size\s*=\s*)?(?P<kernel_size>[\w.]+)"
        r"(?:\s*,\s*\w+\s*=\s*[^,]+?)*\s*,?\s*\)$"
    ),
    render_tail_looks_for=", kernel_size=<...>",
    attach_extra=", kernel_size={kernel_size}",
    checks=(anchors.render_keyword("subpixel_offset", anchors.MIP_SPLATTING),),
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
