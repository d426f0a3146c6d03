"""Gather an ablation folder's run folders (and nothing else) into results.csv, results.json and
results.md: one row per run, and per (scene, variant, init) the mean and spread over seeds.

Spread = sample standard deviation over seeds (n - 1 in the denominator; shown as "–" for a
single seed). "vs base" / "vs reg" are relative changes of the means against the same scene and
init's base / reg rows (negative = better for Chamfer and normal MAE).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from polargs_plugin.ablation.cell import RUN_FORMAT, SUMMARY_NAME
from polargs_plugin.ablation.variants import VARIANTS
from polargs_plugin.io import atomic_write

__all__ = ["find_runs", "gather", "format_table", "METRICS", "RESULT_FILES"]

RESULT_FILES = ("results.csv", "results.json", "results.md")

#: (key in summary["figures"], column title, format) of the aggregated metrics.
METRICS: tuple[tuple[str, str, str], ...] = (
    ("chamfer", "Chamfer", ".4g"),
    ("accuracy", "accuracy", ".4g"),
    ("completeness", "completeness", ".4g"),
    # without the outlier cap, and what the cap dropped (docs/evaluation.md): a mesh that misses
    # part of the object, or sits inside it, shows here and not in the capped means
    ("chamfer_uncapped", "Chamfer uncapped", ".4g"),
    ("accuracy_uncapped", "accuracy uncapped", ".4g"),
    ("completeness_uncapped", "completeness uncapped", ".4g"),
    ("accuracy_outliers", "accuracy outliers", ".3f"),
    ("completeness_outliers", "completeness outliers", ".3f"),
    ("signed_distance_median", "median signed distance", ".3g"),
    ("fscore", "F-score", ".3f"),
    ("normal_mae_deg", "normal MAE (deg)", ".2f"),
    ("psnr", "PSNR (dB)", ".2f"),
    ("num_gaussians", "Gaussians", ".0f"),
    ("appended_total", "appended by Dense", ".0f"),
    ("train_seconds", "train (s)", ".0f"),
)
_ROW_KEYS = ("scene", "variant", "init", "init_used", "seed") + tuple(k for k, _, _ in METRICS) + (
    "total_seconds", "iterations", "git_commit", "run")


def find_runs(out: str | os.PathLike) -> list[Path]:
    """Run folders directly under ``out``: folders (not hidden) with an ablation summary.json."""
    out = Path(out)
    if not out.is_dir():
        return []
    runs = []
    for folder in sorted(out.iterdir()):
        summary = folder / SUMMARY_NAME
        if folder.name.startswith(".") or not summary.is_file():
            continue
        try:
            if json.loads(summary.read_text()).get("format") == RUN_FORMAT:
                runs.append(folder)
        except (OSError, ValueError):
            continue
    return runs


def _figures(folder: Path, summary: dict[str, Any]) -> dict[str, Any]:
    """summary["figures"]; for runs written before the uncapped means were copied there, the
    Chamfer figures it lacks come from the run's metrics.json (`polargs eval` always wrote them)."""
    figures = dict(summary.get("figures") or {})
    if all(key in figures for key, _, _ in METRICS):
        return figures
    try:
        chamfer = json.loads((folder / "metrics.json").read_text()).get("chamfer") or {}
    except (OSError, ValueError):
        return figures
    return {**{key: chamfer.get(key) for key, _, _ in METRICS if key in chamfer}, **figures}


def _row(folder: Path) -> dict[str, Any]:
    s = json.loads((folder / SUMMARY_NAME).read_text())
    f = _figures(folder, s)
    row = {"scene": s["scene"]["name"], "variant": s["variant"], "init": s.get("init"), "init_used": s.get("init_used"),
           "seed": s["seed"]}
    row.update({key: f.get(key) for key, _, _ in METRICS})
    row.update(total_seconds=s.get("timings", {}).get("total"), iterations=f.get("iterations"),
               git_commit=(s.get("git") or {}).get("commit"), run=folder.name)
    return row


def _stats(values: list[float]) -> dict[str, Any]:
    values = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not values:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else None
    return {"mean": mean, "std": std, "min": min(values), "max": max(values), "n": len(values)}


def _relative(value: float | None, reference: float | None) -> float | None:
    if value is None or reference is None or reference == 0:
        return None
    return (value - reference) / abs(reference)


def gather(out: str | os.PathLike, write: bool = True) -> dict[str, Any]:
    """Read every run folder of ``out``; write results.csv / .json / .md (atomically) if ``write``.

    Returns ``{"runs": [row, ...], "table": [group, ...], "markdown": str}``; a group has
    scene, variant, init, seeds, ``<metric>: {mean, std, min, max, n}`` and the relative
    changes ``chamfer_vs_base``, ``chamfer_vs_reg``, ``normal_mae_deg_vs_base``, ``normal_mae_deg_vs_reg``.
    """
    out = Path(out)
    rows = [_row(folder) for folder in find_runs(out)]
    scene_order = list(dict.fromkeys(r["scene"] for r in rows))
    order = {v: i for i, v in enumerate(VARIANTS)}
    rows.sort(key=lambda r: (scene_order.index(r["scene"]), str(r["init"]), order.get(r["variant"], 99), r["seed"]))
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["variant"], r["init"]), []).append(r)
    table = []
    for (scene, variant, init), members in groups.items():
        entry: dict[str, Any] = {"scene": scene, "variant": variant, "init": init,
                                 "init_used": sorted({str(m["init_used"]) for m in members}),
                                 "seeds": [m["seed"] for m in members]}
        for key, _, _ in METRICS:
            entry[key] = _stats([m[key] for m in members])
        table.append(entry)
    by_key = {(e["scene"], e["variant"], e["init"]): e for e in table}
    for e in table:
        for ref in ("base", "reg"):
            other = by_key.get((e["scene"], ref, e["init"]))
            for key in ("chamfer", "normal_mae_deg"):
                e[f"{key}_vs_{ref}"] = None if other is None or other is e else _relative(e[key]["mean"], other[key]["mean"])
    markdown = format_table(table)
    results = {"runs": rows, "table": table, "markdown": markdown}
    if write:
        out.mkdir(parents=True, exist_ok=True)
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(_ROW_KEYS))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in _ROW_KEYS})
        with atomic_write(out / "results.csv") as handle:
            handle.write(buffer.getvalue())
        with atomic_write(out / "results.json") as handle:
            json.dump({"runs": rows, "table": table}, handle, indent=2)
        with atomic_write(out / "results.md") as handle:
            handle.write(markdown + "\n")
    return results


def _cell(stats: dict[str, Any], fmt: str) -> str:
    if stats["mean"] is None:
        return "n/a"
    spread = "–" if stats["std"] is None else format(stats["std"], fmt)
    return f"{format(stats['mean'], fmt)} ± {spread}"


def _percent(value: float | None) -> str:
    return "" if value is None else f"{100 * value:+.0f} %"


def format_table(table: list[dict[str, Any]]) -> str:
    """The Markdown table: per scene, variant and init, mean ± spread over seeds."""
    if not table:
        return "(no finished runs)"
    several_inits = len({e["init"] for e in table}) > 1 or any(e["init_used"] != [e["init"]] for e in table)
    head = ["scene", "variant"] + (["init"] if several_inits else []) + [
        "seeds", "Chamfer", "vs base", "vs reg", "Chamfer uncapped", "completeness uncapped", "median signed distance",
        "normal MAE (deg)", "vs base", "vs reg", "F-score", "PSNR (dB)", "Gaussians", "train (s)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for e in table:
        init = e["init"] if e["init_used"] == [e["init"]] else f"{e['init']} (ran: {', '.join(e['init_used'])})"
        cells = [e["scene"], e["variant"]] + ([init] if several_inits else []) + [
            str(len(e["seeds"])),
            _cell(e["chamfer"], ".4g"), _percent(e["chamfer_vs_base"]), _percent(e["chamfer_vs_reg"]),
            _cell(e["chamfer_uncapped"], ".4g"), _cell(e["completeness_uncapped"], ".4g"),
            _cell(e["signed_distance_median"], ".3g"),
            _cell(e["normal_mae_deg"], ".2f"), _percent(e["normal_mae_deg_vs_base"]), _percent(e["normal_mae_deg_vs_reg"]),
            _cell(e["fscore"], ".3f"), _cell(e["psnr"], ".2f"), _cell(e["num_gaussians"], ".0f"), _cell(e["train_seconds"], ".0f"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":  # python -m polargs_plugin.ablation.gather OUT
    import sys

    print(gather(sys.argv[1])["markdown"])
