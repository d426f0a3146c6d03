"""Insert the PolarGS hook calls into zju3dv/PGSR's ``train.py``.

    python adapters/pgsr/patch.py CHECKOUT [--dry-run] [--revert [--force]]

Verified against PGSR de24f1a. PGSR's render() takes the exposure ``app_model``: its name is taken
from the training render call (which spans two lines upstream) and handed to ``attach``. The
densify hook goes after the optimizer steps, i.e. after the same-iteration multi-view trim.
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
        lines=("import polargs_adapters.pgsr as polargs_pgsr",),
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
        lines=("polar = polargs_pgsr.attach({scene}, {gaussians}, {pipe}, {render}, app_model={app_model})",),
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
            r"\s*(?P<background>\w+)\s*,(?:.*?,)?\s*app_model\s*=\s*(?P<app_model>\w+)\s*(?:,.*)?\)$"
        ),
        inside="training loop",
        before="loss backward",
        same_indent_as="loss backward",
        looks_for=(
            "`<render_pkg> = render(<camera>, <gaussians>, <pipe>, <bg>, ..., app_model=<app_model>, ...)`"
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
