"""Insert the PolarGS hook calls into autonomousvision/gaussian-opacity-fields' (GOF) ``train.py``.

    python adapters/gof/patch.py CHECKOUT [--dry-run] [--revert [--force]]

Verified against GOF 5245b20. GOF's render() needs ``kernel_size``: it is taken from the training
render call and handed to ``attach``. The adapter's densify hook recomputes GOF's 3D filter itself.
What goes where: docs/adapters/patching.md.
"""

import sys

from polargs_plugin.kit.patching import Anchor, main

ANCHORS = (
    Anchor(
        name="render import",
        regex=r"from\s+gaussian_renderer\s+import\s+.*?\brender\b(?:\s+as\s+(?P<render>\w+))?",
        defaults={"render": "render"},
        looks_for="`from gaussian_renderer import render`",
    ),
    Anchor(
        name="last import",
        regex=r"(?:import|from)\s+[\w.]+",
        where="after",
        pick="last",
        lines=("import polargs_adapters.gof as polargs_gof",),
        looks_for="a top-level import line",
    ),
    Anchor(
        name="GaussianModel",
        regex=r"\s*(?P<gaussians>\w+)\s*=\s*GaussianModel\(",
        looks_for="`<gaussians> = GaussianModel(...)`",
    ),
    Anchor(
        name="Scene",
        regex=r"\s*(?P<scene>\w+)\s*=\s*Scene\(\s*(?P<dataset>\w+)\s*,\s*{gaussians}\b",
        looks_for="`<scene> = Scene(<dataset>, <gaussians>)`",
    ),
    Anchor(
        name="training loop",
        regex=r"\s*for\s+(?P<iteration>\w+)\s+in\s+range\(.*\)\s*:$",
        after="Scene",
        same_indent_as="Scene",
        lines=("polar = polargs_gof.attach({scene}, {gaussians}, {pipe}, {render}, kernel_size={kernel_size})",),
        looks_for="`for <iteration> in range(...):` below the Scene line, indented like it",
    ),
    Anchor(
        name="loss backward",
        regex=r"\s*(?P<loss>\w+)\.backward\(\s*\)$",
        inside="training loop",
        lines=("{loss} = {loss} + polar.loss({iteration}, {camera}, {render_pkg})",),
        looks_for="`<loss>.backward()` inside the training loop",
    ),
    Anchor(
        name="render call",
        regex=(
            r"\s*(?P<render_pkg>\w+)\s*=\s*{render}\(\s*(?P<camera>\w+)\s*,\s*{gaussians}\s*,\s*(?P<pipe>\w+)\s*,"
            r"\s*(?P<background>\w+)\s*,\s*(?:kernel_size\s*=\s*)?(?P<kernel_size>[\w.]+)"
            r"(?:\s*,\s*\w+\s*=\s*[^,]+?)*\s*,?\s*\)$"
        ),
        inside="training loop",
        before="loss backward",
        same_indent_as="loss backward",
        looks_for=(
            "`<render_pkg> = render(<camera>, <gaussians>, <pipe>, <bg>, kernel_size=<...>)`"
            " above the backward call, indented like it"
        ),
    ),
    Anchor(
        name="no_grad block",
        regex=r"\s*with\s+torch\.no_grad\(\)\s*:$",
        after="loss backward",
        same_indent_as="loss backward",
        looks_for="`with torch.no_grad():` below the backward call, indented like it",
    ),
    Anchor(
        name="optimizer step",
        regex=r"\s*{gaussians}\.optimizer\.step\(",
        inside="no_grad block",
        pick="last",
        looks_for="`<gaussians>.optimizer.step(...)` inside the no_grad block",
    ),
    Anchor(
        name="checkpoint block",
        regex=r"\s*if\s*\(?\s*{iteration}\s+in\s+\w*checkpoint\w*\s*\)?\s*:$",
        inside="no_grad block",
        after="optimizer step",
        lines=("polar.densify({iteration}, {camera}, {render_pkg})",),
        looks_for="`if (<iteration> in checkpoint_iterations):` after the optimizer step",
    ),
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], ANCHORS, __doc__))
