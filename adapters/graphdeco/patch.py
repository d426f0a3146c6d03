"""Insert the PolarGS hook calls into graphdeco-inria/gaussian-splatting's ``train.py``.

    python adapters/graphdeco/patch.py CHECKOUT [--dry-run] [--revert [--force]]

Recognises the 2023 loop (472689c, the base GOF and PGSR fork) and the 2024 one (54c035f: exposure,
sparse Adam, depth regulariser); the keyword arguments of the training render call (2024:
``use_trained_exp``, ``separate_sh``) are handed to ``attach``. What goes where:
docs/adapters/patching.md.
"""

import sys

from polargs_plugin.kit.inria_anchors import inria_anchors
from polargs_plugin.kit.patching import main

ANCHORS = inria_anchors(
    "graphdeco",
    render_tail=r"(?P<render_extra>(?:\s*,\s*\w+\s*=\s*[^,]+?)*)\s*,?\s*\)$",
    render_tail_looks_for="[, key=value...]",
    attach_extra="{render_extra}",
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
