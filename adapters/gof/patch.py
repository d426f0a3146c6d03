"""Insert the PolarGS hook calls into autonomousvision/gaussian-opacity-fields' (GOF) ``train.py``.

    python adapters/gof/patch.py CHECKOUT [--dry-run] [--revert [--force]]

Verified against GOF 5245b20. GOF's render() needs ``kernel_size``: it is taken from the training
render call and handed to ``attach``. The adapter's densify hook recomputes GOF's 3D filter itself.
What goes where: docs/adapters/patching.md.
"""

import sys

from polargs_plugin.kit.inria_anchors import inria_anchors
from polargs_plugin.kit.patching import main

ANCHORS = inria_anchors(
    "gof",
    render_tail=(
        r"\s*,\s*(?:kernel_size\s*=\s*)?(?P<kernel_size>[\w.]+)"
        r"(?:\s*,\s*\w+\s*=\s*[^,]+?)*\s*,?\s*\)$"
    ),
    render_tail_looks_for=", kernel_size=<...>",
    attach_extra=", kernel_size={kernel_size}",
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
