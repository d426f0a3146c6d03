"""The anchors of a graphdeco-family ``train.py`` loop (graphdeco 2023/2024, GOF, PGSR).

These trainers share one loop: ``gaussians = GaussianModel(...)``, ``scene = Scene(dataset,
gaussians)``, ``for iteration in range(...)``, a ``render(camera, gaussians, pipe, bg, ...)`` call,
``loss.backward()``, then a ``with torch.no_grad():`` block with the optimizer step and the
checkpoint save. :func:`inria_anchors` builds the anchor list that inserts the four PolarGS lines
into it (docs/adapters/patching.md); each trainer's ``patch.py`` only says what its render call
looks like after the background argument and what ``attach`` gets from it.
"""

from __future__ import annotations

from polargs_plugin.kit.patching import Anchor

__all__ = ["inria_anchors"]


def inria_anchors(adapter: str, render_tail: str, render_tail_looks_for: str, attach_extra: str = "") -> tuple[Anchor, ...]:
    """Anchors inserting the PolarGS calls of ``polargs_adapters.<adapter>`` into the loop.

    Args:
        adapter: the adapter sub-package (``graphdeco``, ``gof``, ``pgsr``).
        render_tail: regex for the rest of the training render call after ``bg`` up to the
            closing ``)$`` (named groups become names usable in ``attach_extra``).
        render_tail_looks_for: how that tail reads, for the error message.
        attach_extra: text appended to ``attach``'s arguments, e.g. ``", kernel_size={kernel_size}"``.

    Returns:
        The anchors, in the order the engine resolves them.
    """
    module = f"polargs_{adapter}"
    return (
        *_import_anchors(adapter, module),
        *_setup_anchors(module, attach_extra),
        *_step_anchors(render_tail, render_tail_looks_for),
        *_after_step_anchors(),
    )


def _import_anchors(adapter: str, module: str) -> tuple[Anchor, ...]:
    """The render import (its local name) and the adapter's import after the last import line."""
    return (
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
            lines=(f"import polargs_adapters.{adapter} as {module}",),
            looks_for="a top-level import line",
        ),
    )


def _setup_anchors(module: str, attach_extra: str) -> tuple[Anchor, ...]:
    """The model and scene lines (their names) and ``attach`` before the training loop."""
    return (
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
            lines=(f"polar = {module}.attach({{scene}}, {{gaussians}}, {{pipe}}, {{render}}{attach_extra})",),
            looks_for="`for <iteration> in range(...):` below the Scene line, indented like it",
        ),
    )


def _step_anchors(render_tail: str, render_tail_looks_for: str) -> tuple[Anchor, ...]:
    """The loss line before ``backward`` and the render call it takes its names from."""
    return (
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
                r"\s*(?P<background>\w+)" + render_tail
            ),
            inside="training loop",
            before="loss backward",
            same_indent_as="loss backward",
            looks_for=(
                f"`<render_pkg> = render(<camera>, <gaussians>, <pipe>, <bg>{render_tail_looks_for})`"
                " above the backward call, indented like it"
            ),
        ),
    )


def _after_step_anchors() -> tuple[Anchor, ...]:
    """``densify`` after the optimizer step, before the checkpoint block of the no_grad block."""
    return (
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
