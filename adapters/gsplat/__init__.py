"""PolarGS for gsplat (nerfstudio-project/gsplat 1.5.x and main): strategies plus helpers.

- :class:`PolarDefaultStrategy`, :class:`PolarMCMCStrategy`: gsplat's two strategies with the
  Gaussians of PolarGS's polar-enhanced PatchMatch densification (module Dense) appended after
  their step; :func:`polar_strategy` converts a configured one. :class:`PolarStrategy` composes
  Dense with any inner strategy.
- :func:`attach`, :class:`SimpleTrainerPolar`: what ``adapters/gsplat/patch.py`` inserts into
  gsplat's ``examples/simple_trainer.py``.
- :func:`polar_colors`, :func:`sh_colors`, :func:`polar_backgrounds`: the extra colour channels
  (normal, alpha, depth) rendered in the same ``rasterization`` call.
- :func:`polar_loss`: PolarGS's loss terms (PC, L_n, L_dn, L_scale) from gsplat's outputs.
- :func:`view_from_gsplat`, :func:`gsplat_cameras`: gsplat ``viewmats`` / ``Ks`` <-> ``View``.
- :func:`make_render_fn`: ``render_fn(view)`` over the live parameters (Dense's source views).

Set-up and a training snippet: docs/adapters/gsplat.md. Needs ``pip install polargs_plugin[gsplat]``.
"""

from .cameras import gsplat_cameras, view_from_gsplat
from .render import (
    NUM_AUX,
    RAW_FROM_GSPLAT,
    gaussian_state,
    gsplat_sh,
    make_render_fn,
    polar_backgrounds,
    polar_colors,
    polar_loss,
    render_out_from_gsplat,
    sh_colors,
)
from .strategy import (
    NOT_PER_GAUSSIAN,
    PolarDefaultStrategy,
    PolarMCMCStrategy,
    PolarStrategy,
    nearest_rows,
    polar_strategy,
    rows_from_new,
)
from .trainer import SimpleTrainerPolar, attach, trainer_views

__all__ = [
    "PolarStrategy",
    "PolarDefaultStrategy",
    "PolarMCMCStrategy",
    "polar_strategy",
    "nearest_rows",
    "attach",
    "SimpleTrainerPolar",
    "trainer_views",
    "gsplat_sh",
    "rows_from_new",
    "NOT_PER_GAUSSIAN",
    "NUM_AUX",
    "RAW_FROM_GSPLAT",
    "gaussian_state",
    "make_render_fn",
    "polar_backgrounds",
    "polar_colors",
    "polar_loss",
    "render_out_from_gsplat",
    "sh_colors",
    "gsplat_cameras",
    "view_from_gsplat",
]
