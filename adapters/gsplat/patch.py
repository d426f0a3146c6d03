"""Insert the PolarGS calls into gsplat's ``examples/simple_trainer.py`` (nerfstudio-project/gsplat).

    python adapters/gsplat/patch.py GSPLAT_CHECKOUT [--dry-run] [--revert] [--force]

GSPLAT_CHECKOUT is the repository (its ``examples/simple_trainer.py`` is patched), its
``examples/`` folder, or the file itself.

Verified against v1.5.3 and main (90d7b4b, version 1.6.0). Three lines: the adapter's import
after gsplat's strategy import; ``<runner>.polar = polargs_gsplat.attach(<runner>)`` in
``Runner.__init__`` just above the strategy's ``check_sanity`` (it turns the configured
DefaultStrategy / MCMCStrategy into its PolarGS subclass, which the trainer's ``isinstance``
dispatch accepts, and Dense then runs inside ``step_post_backward``); and the loss hook just
above ``loss.backward()`` of the training loop, after ``step_pre_backward``, with the names of
the training render call (``rasterize_splats`` in 1.5.3, ``stage.render`` on main).
What goes where: docs/adapters/gsplat.md. Needs only the standard library (Python 3.8+).
"""

import runpy
import sys
from pathlib import Path

engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))  # standard library only
patching = engine["load"]("patching")
Anchor = patching.Anchor

ANCHORS = (
    Anchor(
        name="strategy import",
        regex=r"from\s+gsplat\.strategy\s+import\s+.*\bDefaultStrategy\b",
        where="after",
        lines=("import polargs_adapters.gsplat as polargs_gsplat",),
        looks_for="`from gsplat.strategy import DefaultStrategy, MCMCStrategy`",
    ),
    Anchor(
        name="check_sanity",
        regex=r"\s*(?P<runner>\w+)\.cfg\.strategy\.check_sanity\(\s*(?P=runner)\.splats\s*,\s*(?P=runner)\.optimizers\s*\)$",
        lines=("{runner}.polar = polargs_gsplat.attach({runner})",),
        looks_for="`self.cfg.strategy.check_sanity(self.splats, self.optimizers)` in Runner.__init__",
    ),
    Anchor(
        name="progress bar",
        regex=r"\s*(?P<pbar>\w+)\s*=\s*tqdm\.tqdm\(\s*range\(",
        after="check_sanity",
        looks_for="`pbar = tqdm.tqdm(range(...))` before the training loop",
    ),
    Anchor(
        name="training loop",
        regex=r"\s*for\s+(?P<step>\w+)\s+in\s+{pbar}\s*:$",
        after="progress bar",
        looks_for="`for step in pbar:`",
    ),
    Anchor(
        name="render call",
        regex=(
            r"\s*(?P<renders>\w+)\s*,\s*(?P<alphas>\w+)\s*,\s*(?P<info>\w+)\s*=\s*"
            r"{runner}\.(?:rasterize_splats|stage\.render)\("
            r"(?=.*\bcamtoworlds\s*=\s*(?P<camtoworlds>\w+)\s*[,)])"
            r"(?=.*\bKs\s*=\s*(?P<Ks>\w+)\s*[,)])"
            r"(?=.*\bimage_ids\s*=\s*(?P<image_ids>\w+)\s*[,)])"
        ),
        inside="training loop",
        looks_for=(
            "`renders, alphas, info = self.rasterize_splats(camtoworlds=..., Ks=..., ..., image_ids=...)`"
            " (or `self.stage.render(...)`) inside the training loop"
        ),
    ),
    Anchor(
        name="step_pre_backward",
        regex=r"\s*{runner}\.cfg\.strategy\.step_pre_backward\(",
        inside="training loop",
        after="render call",
        looks_for="`self.cfg.strategy.step_pre_backward(...)` after the render call",
    ),
    Anchor(
        name="loss backward",
        regex=r"\s*(?P<loss>\w+)\.backward\(\s*\)$",
        inside="training loop",
        after="step_pre_backward",
        lines=("{loss} = {loss} + {runner}.polar.loss({step}, {image_ids}, {camtoworlds}, {Ks}, {renders}, {alphas}, {info})",),
        looks_for="`loss.backward()` after step_pre_backward, inside the training loop",
    ),
    Anchor(
        name="step_post_backward",
        regex=r"\s*{runner}\.cfg\.strategy\.step_post_backward\(",
        inside="training loop",
        after="loss backward",
        pick="first",
        looks_for="`self.cfg.strategy.step_post_backward(...)` after the backward call (Dense runs in it)",
    ),
)

if __name__ == "__main__":
    sys.exit(patching.main(sys.argv[1:], ANCHORS, __doc__, filename="simple_trainer.py", subfolders=("examples",)))
