"""Gather an ablation folder's run folders (and nothing else) into results.csv, results.json and
results.md: one row per run, and per (scene, variant, init) the mean and spread over seeds.

Spread = sample standard deviation over seeds (n - 1 in the denominator; shown as "–" for a
single seed). "vs base" / "vs reg" are relative changes of the means against the same scene and
init's base / reg rows (negative = better for Chamfer and normal MAE).

Two Chamfer figures judge a variant: the DTU-style capped one and the uncapped one over the GT
surface some training view sees (``chamfer_visible``, docs/evaluation.md). The **verdict** calls a
variant better (or worse) than another on a scene only where both agree, and says where they
disagree; the means over scenes, the completeness per visibility class and what Dense's appended
Gaussians bought are tabled beside it.

Per visibility class (many, few, grazing; :func:`class_completeness`), a variant **loses** the
class against base where the class holds at least :data:`MIN_CLASS_SHARE` of the seen GT surface
and the variant's mean completeness there is worse than base's by more than the larger of the two
seed spreads and by more than :data:`LEVEL`; with a single seed on either side (no spread to go
by), by more than :data:`CLASS_LOSS_ONE_SEED`. The verdict names every such variant.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from polargs_plugin.ablation.figures import VISIBILITY_CLASSES, chamfer_figures
from polargs_plugin.ablation.pipeline import RUN_FORMAT
from polargs_plugin.ablation.variants import VARIANTS
from polargs_plugin.io import atomic_write
from polargs_plugin.service.runs import SUMMARY_NAME

__all__ = ["find_runs", "gather", "format_table", "format_results", "verdicts", "LEVEL", "scene_means", "dense_budget", "METRICS", "RESULT_FILES",
           "VERDICT_PAIRS", "class_completeness", "class_loss_lines", "MIN_CLASS_SHARE", "CLASS_LOSS_ONE_SEED", "CLASS_LOSS_RULE"]

RESULT_FILES = ("results.csv", "results.json", "results.md")
#: Figures compared with base and reg (``<key>_vs_base``, ``<key>_vs_reg``).
COMPARED = ("chamfer", "chamfer_visible", "normal_mae_deg")
#: Relative changes below this, in both Chamfer figures, are "level" in the verdict: a change of
#: the float rounding alone moves a run's figures by about a percent (docs/results.md).
LEVEL = 0.01
#: A visibility class holding less of the seen GT surface than this is shown but not compared: its
#: completeness is a mean over too few samples, and a loss there costs the object little.
MIN_CLASS_SHARE = 0.05
#: With a single seed (no spread), a variant loses a visibility class against base where its class
#: completeness is worse by more than this relative change (about the spread of two seeds' class figures).
CLASS_LOSS_ONE_SEED = 0.05
#: The rule above in words (results.md's and report.md's verdicts).
CLASS_LOSS_RULE = ("Visibility classes lost against base (completeness in the class worse than base's by more than the "
                   "larger seed spread and by more than 1 %, or by more than 5 % with one seed; classes under 5 % of "
                   "the seen surface are not compared):")
#: (variant, reference) pairs the verdict judges, where both were run.
VERDICT_PAIRS: tuple[tuple[str, str], ...] = (
    ("full", "base"), ("full", "reg"), ("no-dense", "reg"), ("no-pc", "reg"), ("full", "no-dense"), ("full", "no-pc"))

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
    # over the GT surface some training view sees, uncapped; completeness per visibility class
    ("chamfer_visible", "visible Chamfer", ".4g"),
    ("completeness_visible", "visible completeness", ".4g"),
    ("visible_fraction", "GT share seen", ".3f"),
    *((f"completeness_{name}", f"completeness, {name}", ".4g") for name in VISIBILITY_CLASSES),
    *((f"share_{name}", f"share, {name}", ".3f") for name in VISIBILITY_CLASSES),
    # the share of the class's GT samples farther than 2 % of the GT box diagonal from the mesh
    *((f"missing_{name}", f"missing, {name}", ".3f") for name in VISIBILITY_CLASSES),
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
    flat = {**chamfer, **chamfer_figures(chamfer)}
    return {**{key: flat.get(key) for key, _, _ in METRICS if key in flat}, **figures}


def _row(folder: Path) -> dict[str, Any]:
    s = json.loads((folder / SUMMARY_NAME).read_text())
    f = _figures(folder, s)
    row = {"scene": s["scene"]["name"], "variant": s["variant"], "init": s.get("init"), "init_used": s.get("init_used"),
           "seed": s["seed"]}
    row.update({key: f.get(key) for key, _, _ in METRICS})
    row.update(total_seconds=s.get("timings", {}).get("total"), iterations=f.get("iterations"),
               git_commit=_commit(s), run=folder.name)
    return row


def _commit(summary: dict[str, Any]) -> str | None:
    """The source commit a run recorded (under ``provenance``; at the top level in run folders
    written before the provenance record)."""
    record = summary.get("provenance") or summary
    return (record.get("git") or {}).get("commit")


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

    Returns ``{"runs": [row, ...], "table": [group, ...], "verdicts": [...], "scene_means": [...],
    "dense_budget": [...], "class_completeness": [...], "markdown": str}``; a group has scene,
    variant, init, seeds, ``<metric>: {mean, std, min, max, n}`` and the relative changes
    ``<key>_vs_base`` and ``<key>_vs_reg`` for the keys of :data:`COMPARED`; :func:`verdicts`,
    :func:`scene_means`, :func:`dense_budget` and :func:`class_completeness` describe the other four.
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
            for key in COMPARED:
                e[f"{key}_vs_{ref}"] = None if other is None or other is e else _relative(e[key]["mean"], other[key]["mean"])
    results = {"runs": rows, "table": table, "verdicts": verdicts(table), "scene_means": scene_means(table),
               "dense_budget": dense_budget(table), "class_completeness": class_completeness(table)}
    markdown = format_results(results)
    results["markdown"] = markdown
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
            json.dump({key: results[key] for key in ("runs", "table", "verdicts", "scene_means", "dense_budget",
                                                     "class_completeness")},
                      handle, indent=2)
        with atomic_write(out / "results.md") as handle:
            handle.write(markdown + "\n")
    return results


def _cell(stats: dict[str, Any], fmt: str) -> str:
    if stats["mean"] is None:
        return "n/a"
    spread = "–" if stats["std"] is None else format(stats["std"], fmt)
    return f"{format(stats['mean'], fmt)} ± {spread}"


def _percent(value: float | None, digits: int = 0) -> str:
    return "" if value is None else f"{100 * value:+.{digits}f} %"


def format_table(table: list[dict[str, Any]]) -> str:
    """The Markdown table: per scene, variant and init, mean ± spread over seeds."""
    if not table:
        return "(no finished runs)"
    several_inits = _several_inits(table)
    head = ["scene", "variant"] + (["init"] if several_inits else []) + [
        "seeds", "Chamfer", "vs base", "vs reg", "visible Chamfer", "vs base", "vs reg", "Chamfer uncapped",
        "completeness uncapped", "median signed distance", "normal MAE (deg)", "vs base", "vs reg", "F-score",
        "PSNR (dB)", "Gaussians", "appended", "train (s)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for e in table:
        cells = [e["scene"], e["variant"]] + ([_init_label(e)] if several_inits else []) + [
            str(len(e["seeds"])),
            _cell(e["chamfer"], ".4g"), _percent(e["chamfer_vs_base"]), _percent(e["chamfer_vs_reg"]),
            _cell(e["chamfer_visible"], ".4g"), _percent(e["chamfer_visible_vs_base"]), _percent(e["chamfer_visible_vs_reg"]),
            _cell(e["chamfer_uncapped"], ".4g"), _cell(e["completeness_uncapped"], ".4g"),
            _cell(e["signed_distance_median"], ".3g"),
            _cell(e["normal_mae_deg"], ".2f"), _percent(e["normal_mae_deg_vs_base"]), _percent(e["normal_mae_deg_vs_reg"]),
            _cell(e["fscore"], ".3f"), _cell(e["psnr"], ".2f"), _cell(e["num_gaussians"], ".0f"),
            _cell(e["appended_total"], ".0f"), _cell(e["train_seconds"], ".0f"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _several_inits(table: list[dict[str, Any]]) -> bool:
    return len({e["init"] for e in table}) > 1 or any(e["init_used"] != [e["init"]] for e in table)


def _init_label(e: dict[str, Any]) -> str:
    return e["init"] if e["init_used"] == [e["init"]] else f"{e['init']} (ran: {', '.join(e['init_used'])})"


def _mean(e: dict[str, Any] | None, key: str) -> float | None:
    return None if e is None else e[key]["mean"]


def verdicts(table: list[dict[str, Any]], pairs: tuple[tuple[str, str], ...] = VERDICT_PAIRS) -> list[dict[str, Any]]:
    """Per scene, init and pair (variant, reference) of :data:`VERDICT_PAIRS` that both ran: the
    relative change of the capped Chamfer (``capped``), of the visible-surface Chamfer
    (``visible``) and of the normal MAE (``normals``), and the ``verdict``: ``level`` where both
    Chamfer figures moved by less than :data:`LEVEL`, else ``better`` / ``worse`` where both moved
    the same way, ``disagree`` where they did not (``capped only`` without the visible figure)."""
    by_key = {(e["scene"], e["variant"], e["init"]): e for e in table}
    out = []
    for scene, init in dict.fromkeys((e["scene"], e["init"]) for e in table):
        for variant, reference in pairs:
            this, other = by_key.get((scene, variant, init)), by_key.get((scene, reference, init))
            if this is None or other is None:
                continue
            capped = _relative(_mean(this, "chamfer"), _mean(other, "chamfer"))
            visible = _relative(_mean(this, "chamfer_visible"), _mean(other, "chamfer_visible"))
            normals = _relative(_mean(this, "normal_mae_deg"), _mean(other, "normal_mae_deg"))
            if capped is None or visible is None:
                verdict = "capped only"
            elif abs(capped) < LEVEL and abs(visible) < LEVEL:
                verdict = "level"
            elif capped < 0 and visible < 0:
                verdict = "better"
            elif capped > 0 and visible > 0:
                verdict = "worse"
            else:
                verdict = "disagree"
            out.append({"scene": scene, "init": init, "variant": variant, "reference": reference, "capped": capped,
                        "visible": visible, "normals": normals, "verdict": verdict})
    return out


def scene_means(table: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per variant and init, the means over the scenes where every variant of the table ran: capped
    and visible Chamfer, normal MAE, Gaussians appended; the relative changes of those means
    against base and reg; and the worst scene's relative change of the visible Chamfer against reg."""
    variants = list(dict.fromkeys(e["variant"] for e in table))
    by_key = {(e["scene"], e["variant"], e["init"]): e for e in table}
    out = []
    for init in dict.fromkeys(e["init"] for e in table):
        scenes = [s for s in dict.fromkeys(e["scene"] for e in table) if all((s, v, init) in by_key for v in variants)]
        if not scenes:
            continue
        means: dict[str, dict[str, Any]] = {}
        for variant in variants:
            entries = [by_key[(s, variant, init)] for s in scenes]
            row: dict[str, Any] = {"variant": variant, "init": init, "scenes": scenes}
            for key in ("chamfer", "chamfer_visible", "normal_mae_deg", "appended_total"):
                values = [_mean(e, key) for e in entries]
                row[key] = sum(values) / len(values) if all(v is not None for v in values) else None
            reg = [by_key.get((s, "reg", init)) for s in scenes]
            worst = [_relative(_mean(e, "chamfer_visible"), _mean(r, "chamfer_visible")) for e, r in zip(entries, reg)]
            row["worst_visible_vs_reg"] = max(worst) if worst and all(w is not None for w in worst) and variant != "reg" else None
            means[variant] = row
        for row in means.values():
            for ref in ("base", "reg"):
                other = means.get(ref)
                for key in COMPARED:
                    row[f"{key}_vs_{ref}"] = None if other is None or other is row else _relative(row[key], other[key])
            out.append(row)
    return out


def dense_budget(table: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """What Dense's appended Gaussians bought, per scene and init: for no-pc against reg and for full
    against no-dense (the same variant without Dense), the Gaussians appended (mean over seeds), the
    relative change of the visible Chamfer, and that change per thousand appended Gaussians."""
    by_key = {(e["scene"], e["variant"], e["init"]): e for e in table}
    out = []
    for (scene, variant, init), e in by_key.items():
        reference = {"no-pc": "reg", "full": "no-dense"}.get(variant)
        other = by_key.get((scene, reference, init))
        if other is None:
            continue
        appended = _mean(e, "appended_total")
        change = _relative(_mean(e, "chamfer_visible"), _mean(other, "chamfer_visible"))
        per_thousand = None if change is None or not appended else change / (appended / 1000)
        out.append({"scene": scene, "init": init, "variant": variant, "reference": reference, "appended": appended,
                    "visible_change": change, "change_per_thousand": per_thousand})
    return out


def class_completeness(table: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scene, init, visibility class (where the runs have the class figures) and variant: the
    class's ``share`` of the seen GT surface (mean over the scene's groups: it depends on the GT and
    the views only), ``compared`` (share >= :data:`MIN_CLASS_SHARE`), the variant's ``seeds``,
    ``completeness`` and ``completeness_std`` (mean and spread over seeds), its relative changes
    ``vs_base`` / ``vs_reg`` (None for the reference itself), ``missing`` (mean over seeds of the
    share of the class's GT samples farther than 2 % of the GT box diagonal from the mesh) and
    ``loses_to_base`` (module docstring; None for base, for a class not compared or without base)."""
    by_key = {(e["scene"], e["variant"], e["init"]): e for e in table}
    out = []
    for scene, init in dict.fromkeys((e["scene"], e["init"]) for e in table):
        entries = [e for e in table if (e["scene"], e["init"]) == (scene, init)]
        base, reg = by_key.get((scene, "base", init)), by_key.get((scene, "reg", init))
        for name in VISIBILITY_CLASSES:
            key = f"completeness_{name}"
            shares = [share for share in (_mean(e, f"share_{name}") for e in entries) if share is not None]
            if not shares:
                continue
            share = sum(shares) / len(shares)
            compared = share >= MIN_CLASS_SHARE
            for e in entries:
                changes = {f"vs_{ref}": None if other is None or other is e else _relative(_mean(e, key), _mean(other, key))
                           for ref, other in (("base", base), ("reg", reg))}
                loses = _loses_class(e[key], base[key]) if compared and base is not None and base is not e else None
                out.append({"scene": scene, "init": init, "class": name, "share": share, "compared": compared,
                            "variant": e["variant"], "seeds": e[key]["n"], "completeness": e[key]["mean"],
                            "completeness_std": e[key]["std"], **changes, "missing": _mean(e, f"missing_{name}"),
                            "loses_to_base": loses})
    return out


def _loses_class(this: dict[str, Any], base: dict[str, Any]) -> bool | None:
    """Whether a class completeness (``{mean, std}`` over seeds) is worse than base's beyond the
    noise (module docstring); None where either has no mean."""
    change = _relative(this["mean"], base["mean"])
    if change is None:
        return None
    if this["std"] is None or base["std"] is None:
        return change > CLASS_LOSS_ONE_SEED
    return change > LEVEL and this["mean"] - base["mean"] > max(this["std"], base["std"])


def class_loss_lines(rows: list[dict[str, Any]], with_scene: bool = True) -> list[str]:
    """Markdown bullets naming each variant of ``rows`` (:func:`class_completeness`) that loses a
    visibility class against base, with the change and the missing shares; one line saying that
    none does where the rows compared some class against base and none lost."""
    lines = []
    for r in rows:
        if not r["loses_to_base"]:
            continue
        base = next(b for b in rows if (b["scene"], b["init"], b["class"], b["variant"]) == (r["scene"], r["init"], r["class"], "base"))
        rule = "one seed: more than 5 %" if r["completeness_std"] is None or base["completeness_std"] is None else \
            "beyond the seeds' spread"
        where = f" on {r['scene']}" if with_scene else ""
        lines.append(f"- `{r['variant']}` loses the `{r['class']}` class ({_number(100 * r['share'], '.0f')} % of the seen "
                     f"surface) against `base`{where}: completeness {_percent(r['vs_base'], 1)} ({rule}), missing "
                     f"{_share(r['missing'])} against base's {_share(base['missing'])}")
    if not lines and any(r["loses_to_base"] is not None for r in rows):
        lines.append("- no variant loses a visibility class (of at least 5 % of the seen surface) against `base`")
    return lines


def _verdict_table(rows: list[dict[str, Any]]) -> str:
    head = ["scene", "variant", "against", "Chamfer", "visible Chamfer", "normal MAE", "verdict"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        verdict = {"better": "better", "worse": "worse", "level": "level (both within 1 %)",
                   "disagree": "**the Chamfer figures disagree**",
                   "capped only": "capped Chamfer only (no visible-surface Chamfer)"}[r["verdict"]]
        lines.append(f"| {r['scene']} | {r['variant']} | {r['reference']} | {_percent(r['capped'], 1)} | "
                     f"{_percent(r['visible'], 1)} | {_percent(r['normals'], 1)} | {verdict} |")
    return "\n".join(lines)


def _means_table(rows: list[dict[str, Any]]) -> str:
    head = ["variant", "scenes", "Chamfer", "visible Chamfer", "vs base", "vs reg", "worst scene vs reg",
            "normal MAE (deg)", "vs base", "vs reg", "appended"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        lines.append("| " + " | ".join([
            r["variant"], str(len(r["scenes"])), _number(r["chamfer"], ".4g"), _number(r["chamfer_visible"], ".4g"),
            _percent(r["chamfer_visible_vs_base"], 1), _percent(r["chamfer_visible_vs_reg"], 1),
            _percent(r["worst_visible_vs_reg"], 1), _number(r["normal_mae_deg"], ".2f"),
            _percent(r["normal_mae_deg_vs_base"], 1), _percent(r["normal_mae_deg_vs_reg"], 1),
            _number(r["appended_total"], ".0f")]) + " |")
    return "\n".join(lines)


def _classes_table(rows: list[dict[str, Any]], several_inits: bool) -> str:
    head = ["scene"] + (["init"] if several_inits else []) + [
        "class", "share of seen", "variant", "seeds", "completeness", "vs base", "vs reg", "missing", "against base"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        share = _number(r["share"], ".3f") + ("" if r["compared"] else " (under 5 %: not compared)")
        against = {True: "**loses**", False: "holds"}.get(r["loses_to_base"], "")
        cells = [r["scene"]] + ([str(r["init"])] if several_inits else []) + [
            r["class"], share, r["variant"], str(r["seeds"]),
            _cell({"mean": r["completeness"], "std": r["completeness_std"]}, ".4g"),
            _percent(r["vs_base"], 1), _percent(r["vs_reg"], 1), _share(r["missing"]), against]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _share(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.1f} %"


def _budget_table(rows: list[dict[str, Any]]) -> str:
    head = ["scene", "variant", "against", "appended", "visible Chamfer", "per 1000 appended"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['variant']} | {r['reference']} | {_number(r['appended'], '.0f')} | "
                     f"{_percent(r['visible_change'], 1)} | {_percent(r['change_per_thousand'], 2)} |")
    return "\n".join(lines)


def format_results(results: dict[str, Any]) -> str:
    """results.md: the table (:func:`format_table`), then the verdict, the means over scenes, the
    completeness per visibility class and Dense's appends, where there is something to show."""
    table = results["table"]
    classes = results.get("class_completeness") or []
    losses = class_loss_lines(classes)
    parts = [format_table(table)]
    if results.get("verdicts") or losses:
        parts += ["### Verdict", "A variant is better (worse) than another on a scene only where the capped Chamfer "
                  "and the visible-surface Chamfer both fall (rise), level where both move by less than 1 %; where "
                  "they move apart the table says so. Relative changes of the means over seeds."]
        parts += [_verdict_table(results["verdicts"])] if results.get("verdicts") else []
        parts += [CLASS_LOSS_RULE, "\n".join(losses)] if losses else []
    if len(results.get("scene_means") or []) > 1 and len(results["scene_means"][0]["scenes"]) > 1:
        parts += ["### Means over the scenes", "Relative changes of the means over scenes; \"worst scene vs reg\": the "
                  "largest relative change of the visible Chamfer against reg on a single scene.",
                  _means_table(results["scene_means"])]
    if classes:
        parts += ["### Completeness by visibility class", "Per scene and class of the GT points seen by >= 4 views at "
                  "incidence < 70 deg (many), by 1-3 (few), only at grazing angles (grazing): the class's share of the "
                  "seen GT surface, each variant's uncapped completeness there (mean ± spread over seeds) with its "
                  "relative change against base and reg (negative = better), and \"missing\": the share of the class's "
                  "GT points farther than 2 % of the GT box diagonal from the mesh (mean over seeds). \"against base\": "
                  "whether the variant loses the class (see the verdict); classes under 5 % of the seen surface are "
                  "shown but not compared.", _classes_table(classes, _several_inits(table))]
    if results.get("dense_budget"):
        parts += ["### What Dense's appended Gaussians bought", "Visible-surface Chamfer against the same variant "
                  "without Dense, and that change per thousand Gaussians appended.", _budget_table(results["dense_budget"])]
    return "\n\n".join(parts)


def _number(value: float | None, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


if __name__ == "__main__":  # python -m polargs_plugin.ablation.gather OUT
    import sys

    print(gather(sys.argv[1])["markdown"])
