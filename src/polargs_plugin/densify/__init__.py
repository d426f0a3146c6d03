"""Module Dense: polar-enhanced PatchMatch, consistency filters, seeding, the scheduled densifier."""

from polargs_plugin.densify.densifier import PolarDensifier
from polargs_plugin.densify.filters import consistency_filter, polar_residual, reprojection_check
from polargs_plugin.densify.patchmatch import PatchMatchResult, azimuth_cost, patchmatch
from polargs_plugin.densify.seeding import frames_from_normals, seed_gaussians, seed_mask
from polargs_plugin.densify.view_selection import scene_center, select_sources

__all__ = [
    "PolarDensifier",
    "PatchMatchResult",
    "patchmatch",
    "azimuth_cost",
    "consistency_filter",
    "polar_residual",
    "reprojection_check",
    "seed_gaussians",
    "seed_mask",
    "frames_from_normals",
    "select_sources",
    "scene_center",
]
