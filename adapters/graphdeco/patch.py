"""Insert the PolarGS hook calls into graphdeco-inria/gaussian-splatting's ``train.py``.

    python adapters/graphdeco/patch.py CHECKOUT [--dry-run] [--revert [--force]]

Recognises the 2023 loop (472689c, the base GOF and PGSR fork) and the 2024 one (54c035f: exposure,
sparse Adam, depth regulariser). What goes where: docs/adapters/patching.md.
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
        lines=("import polargs_adapters.graphdeco as polargs_graphdeco",),
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
        lines=("polar = polargs_graphdeco.attach({scene}, {gaussians}, {pipe}, {render}{render_extra})",),
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
            r"\s*(?P<background>\w+)(?P<render_extra>(?:\s*,\s*\w+\s*=\s*[^,]+?)*)\s*,?\s*\)$"
        ),
        inside="training loop",
        before="loss backward",
        same_indent_as="loss backward",
        looks_for=(
            "`<render_pkg> = render(<camera>, <gaussians>, <pipe>, <bg>[, key=value...])`"
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
