"""The anchors of a graphdeco-family ``train.py`` loop (graphdeco 2023/2024, GOF, PGSR, 2DGS).

These trainers share one loop: ``gaussians = GaussianModel(...)``, ``scene = Scene(dataset,
gaussians)``, ``for iteration in range(...)``, a ``render(camera, gaussians, pipe, bg, ...)`` call,
``loss.backward()``, then a ``with torch.no_grad():`` block with the optimizer step and the
checkpoint save (2DGS has a second ``no_grad`` block after it, for its viewer). :func:`inria_anchors`
builds the anchor list that inserts the four PolarGS lines into it (docs/adapters/patching.md);
each trainer's ``patch.py`` only says what its render call looks like after the background
argument, what ``attach`` gets from it, and which loops it must refuse.

Standard library only, like :mod:`.patching` (patch scripts run before the trainer's environment
is complete).
"""

from __future__ import annotations

from typing import Mapping, Sequence

from .patching import Anchor

__all__ = ["inria_anchors", "loop_reads", "render_keyword", "MIP_SPLATTING", "TWODGS_OUTPUTS"]

MIP_SPLATTING = (
    "mip-splatting's loop is not supported (its renderer outputs colour only: no depth, normal or alpha"
    " for the geometric terms); GOF, its surface-reconstruction successor, is: adapters/gof/patch.py"
)
"""Why mip-splatting (autonomousvision/mip-splatting) is refused, in the error line."""

TWODGS_OUTPUTS = {"rend_normal": "2DGS's rendered normal", "rend_dist": "2DGS's depth distortion"}
"""Keys of the render package only 2DGS's loop reads (they tell a 2DGS loop from graphdeco's)."""


def inria_anchors(
    adapter: str,
    render_tail: str,
    render_tail_looks_for: str,
    attach_extra: str = "",
    checks: Sequence[Anchor] = (),
) -> tuple[Anchor, ...]:
    """Anchors inserting the PolarGS calls of ``polargs_adapters.<adapter>`` into the loop.

    Args:
        adapter: the adapter sub-package (``graphdeco``, ``gof``, ``pgsr``, ``twodgs``).
        render_tail: regex for the rest of the training render call after ``bg`` up to the
            closing ``)$`` (named groups become names usable in ``attach_extra``).
        render_tail_looks_for: how that tail reads, for the error message.
        attach_extra: text appended to ``attach``'s arguments, e.g. ``", kernel_size={kernel_size}"``.
        checks: anchors that tell this trainer's loop from its relatives' (:func:`render_keyword`,
            :func:`loop_reads`), located after the render call: refusing ones, or locating ones
            that only have to be found.

    Returns:
        The anchors, in the order the engine resolves them.
    """
    module = f"polargs_{adapter}"
    return (
        *_import_anchors(adapter, module),
        *_setup_anchors(module, attach_extra),
        *_step_anchors(render_tail, render_tail_looks_for),
        *checks,
        *_after_step_anchors(),
    )


def render_keyword(keyword: str, refuse: str) -> Anchor:
    """A refusing anchor: the training render call passes ``keyword=`` (mip-splatting's
    ``kernel_size`` and ``subpixel_offset`` tell its loop from graphdeco's and GOF's)."""
    return Anchor(
        name=f"render call with {keyword}",
        regex=r"\s*\w+\s*=\s*{render}\(.*\b" + keyword + r"\s*=",
        inside="training loop",
        before="loss backward",
        same_indent_as="loss backward",
        refuse=refuse,
    )


def loop_reads(name: str, keys: Mapping[str, str], refuse: str = "") -> Anchor:
    """An anchor on a statement of the loop reading ``<render_pkg>[key]`` for one of ``keys``
    (key -> what it is). Without ``refuse`` it must be found (the loop is this trainer's, e.g.
    2DGS's ``rend_normal``); with ``refuse`` finding it refuses the file (another trainer's loop)."""
    pattern = "|".join(keys)
    return Anchor(
        name=name,
        regex=r".*\b{render_pkg}\s*\[\s*['\"](?:" + pattern + r")['\"]\s*\]",
        inside="training loop",
        pick="first",
        refuse=refuse,
        looks_for=" or ".join(f"`<render_pkg>['{key}']` ({what})" for key, what in keys.items()) + " inside the loop",
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
            pick="first",
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
