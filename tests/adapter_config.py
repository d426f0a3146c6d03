"""The PolarConfig the adapter tests train with."""

from __future__ import annotations

from polargs_plugin import PolarConfig


def rough_model_config() -> PolarConfig:
    """The synthetic preset for a rough 40-px model after a few steps: Dense every 10 steps from 10
    to 40, L_dn from 20, loose multi-view filters, no planarity test and seeds beyond 0.88 pixel
    footprints (the default 2.5 leaves a rough model's shallow errors alone), so that Dense appends:
    the adapters' plumbing is under test, not PatchMatch's accuracy."""
    cfg = PolarConfig.synthetic()
    cfg.densify.start_iter, cfg.densify.end_iter, cfg.densify.interval = 10, 40, 10
    cfg.losses.depth_normal_from_iter = 20
    cfg.densify.filters.max_relative_depth = 0.05
    cfg.densify.filters.max_reprojection_px = 2.0
    cfg.densify.filters.min_consistent_views = 1
    cfg.densify.seed_max_plane_deviation = None
    cfg.densify.seed_depth_footprints = 0.88
    return cfg
