"""The figures of a run's ``summary.json``: the evaluation's (metrics.json) and the training's, flat.

docs/evaluation.md says what each figure measures; :mod:`polargs_plugin.ablation.gather` tabulates them.
"""

from __future__ import annotations

from typing import Any

__all__ = ["VISIBILITY_CLASSES", "chamfer_figures", "run_figures", "eval_record"]


#: The visibility classes whose completeness and share a run's figures carry.
VISIBILITY_CLASSES = ("many", "few", "grazing")


def chamfer_figures(chamfer: dict[str, Any]) -> dict[str, Any]:
    """The visible-surface figures of a metrics.json ``chamfer`` entry, flat: ``chamfer_visible``,
    ``completeness_visible``, ``visible_fraction``, ``completeness_<class>``, ``share_<class>`` and
    ``missing_<class>`` (the share of the class's GT samples farther than ``missing_dist`` from the
    mesh) for the classes many, few, grazing (None where the evaluation had neither GT depth maps
    nor cameras and a GT mesh to ray-cast them from, or, for ``missing_<class>``, predates it)."""
    by_class = chamfer.get("completeness_by_visibility") or {}
    shares = chamfer.get("visibility_shares") or {}
    missing = chamfer.get("missing_by_visibility") or {}
    return {
        "chamfer_visible": chamfer.get("chamfer_visible"),
        "completeness_visible": chamfer.get("completeness_visible"),
        "visible_fraction": chamfer.get("visible_fraction"),
        **{f"completeness_{name}": by_class.get(name) for name in VISIBILITY_CLASSES},
        **{f"share_{name}": shares.get(name) for name in VISIBILITY_CLASSES},
        **{f"missing_{name}": missing.get(name) for name in VISIBILITY_CLASSES},
    }


def run_figures(metrics: dict[str, Any], figures: dict[str, Any], curve: list[dict[str, float]]) -> dict[str, Any]:
    """The summary's ``figures``: the evaluation's and the training's."""
    chamfer = metrics.get("chamfer") or {}
    return {
        "chamfer": chamfer.get("chamfer"),
        "accuracy": chamfer.get("accuracy"),
        "completeness": chamfer.get("completeness"),
        # the same means without the outlier cap, the fractions the cap dropped and the median
        # signed distance (outside positive): a mesh inside the GT shows there, not in the capped means
        "chamfer_uncapped": chamfer.get("chamfer_uncapped"),
        "accuracy_uncapped": chamfer.get("accuracy_uncapped"),
        "completeness_uncapped": chamfer.get("completeness_uncapped"),
        "accuracy_outliers": chamfer.get("accuracy_outliers"),
        "completeness_outliers": chamfer.get("completeness_outliers"),
        "signed_distance_median": chamfer.get("signed_distance_median"),
        # the uncapped Chamfer over the GT surface some view sees, and the completeness of the GT
        # points seen by many views, by few and only at grazing angles (docs/evaluation.md)
        **chamfer_figures(chamfer),
        "fscore": chamfer.get("fscore"),
        "precision": chamfer.get("precision"),
        "recall": chamfer.get("recall"),
        "normal_mae_deg": metrics.get("normal_mae_deg"),
        "psnr": figures["psnr"],
        "loss": figures["loss"],
        "iterations": figures["iterations"],
        "num_gaussians": figures["num_gaussians"],
        "appended_total": int(sum(row["appended"] for row in curve)),
        "train_seconds": figures["seconds"],
        "units": chamfer.get("units", "scene units"),
    }


def eval_record(metrics: dict[str, Any], cull: bool, num_samples: int) -> dict[str, Any]:
    """The summary's ``eval``: how the run was evaluated (culling, samples, the distance cap and F-score
    threshold, the normals' region, and where the GT depth maps and normals came from: the dataset's
    own or ray-cast from the GT mesh)."""
    chamfer = metrics.get("chamfer") or {}
    return {"culled": cull, "num_samples": num_samples, "max_dist": chamfer.get("max_dist"),
            "fscore_threshold": chamfer.get("fscore_threshold"), "normal_region": metrics.get("normal_region"),
            "depth_source": (chamfer.get("visibility_classes") or {}).get("source"),
            "normal_source": metrics.get("normal_source")}
