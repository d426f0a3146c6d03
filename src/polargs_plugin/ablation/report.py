"""report.md and its PNG figures (matplotlib, Agg, written atomically) for an ablation folder.

Reads the run folders only (summary.json, curves.csv, views.npz, mesh_error.npz, pc_maps.npz)
through :func:`polargs_plugin.ablation.gather.gather`. Per scene (and init):

- ``metrics_*.png``: Chamfer (capped and, where the runs have it, visible-surface) and
  normal MAE per variant, bar = mean over seeds, error bar = sample standard deviation, dots = the seeds;
- ``views_*.png``: two views side by side; rows GT then one per variant; per view rendered colour,
  normal map, depth error against GT depth;
- ``mesh_error_*.png``: the predicted mesh's vertices projected into the first view, coloured by
  signed distance to the GT mesh (blue inside, red outside);
- ``pc_inputs_*.png``: the PC inputs of the two views (s0/2, AoLP, DoLP, specular and overexposed
  masks, I_diff, I_chro), from a run with PC;
- ``curves_*.png``: loss, PSNR, number of Gaussians and Gaussians appended by Dense per iteration.
"""

from __future__ import annotations

import csv
import datetime
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from polargs_plugin.ablation.artifacts import CURVES_NAME
from polargs_plugin.ablation.gather import CLASS_LOSS_RULE, class_loss_lines, find_runs, gather
from polargs_plugin.ablation.variants import DESCRIPTIONS, VARIANTS
from polargs_plugin.io import atomic_path, atomic_write
from polargs_plugin.service.runs import SUMMARY_NAME

__all__ = ["write_report", "REPORT_NAME", "FIGURES_DIR"]

REPORT_NAME = "report.md"
FIGURES_DIR = "figures"
#: The unit the report gives lengths in (the scene's own).
UNITS = "scene units"
NOT_EVALUATED_GREY = (0.62, 0.62, 0.62, 1.0)
COLORS = {"base": "#7f7f7f", "reg": "#1f77b4", "no-dense": "#ff7f0e", "no-pc": "#2ca02c", "full": "#d62728"}


def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


# ----------------------------------------------------------------------------------- loading
def _load_npz(path: Path) -> dict[str, np.ndarray] | None:
    if not path.is_file():
        return None
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def _curves(folder: Path) -> dict[str, np.ndarray]:
    path = folder / CURVES_NAME
    if not path.is_file():
        return {}
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    out = {}
    for key in ("iteration", "loss", "psnr", "num_gaussians", "appended_total"):
        out[key] = np.array([float(r[key]) if r.get(key) not in (None, "") else np.nan for r in rows])
    return out


def _ema(values: np.ndarray, weight: float = 0.1) -> np.ndarray:
    out = np.empty_like(values)
    acc = np.nan
    for i, v in enumerate(values):
        acc = v if not np.isfinite(acc) else (1 - weight) * acc + weight * v
        out[i] = acc
    return out


# ---------------------------------------------------------------------------------- pictures
def _normal_rgb(normal: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(3, H, W) camera-frame normals -> (H, W, 3): x right = red, y up = green, towards the camera = blue."""
    n = normal / np.maximum(np.linalg.norm(normal, axis=0, keepdims=True), 1e-8)
    rgb = (np.stack([n[0], -n[1], -n[2]], axis=-1) + 1) / 2
    rgb[~valid] = 1.0
    return np.clip(rgb, 0, 1)


def _hwc(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, dtype=np.float32)
    if image.shape[0] == 1:
        image = np.repeat(image, 3, axis=0)
    return np.clip(np.moveaxis(image, 0, -1), 0, 1)


def _off(ax) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def _metrics_figure(entries: list[dict], runs: list[dict], path: Path, units: str) -> Path:
    panels = [("chamfer", f"Chamfer ({units})"), ("normal_mae_deg", "normal MAE (deg)")]
    if any(e["chamfer_visible"]["mean"] is not None for e in entries):
        panels.insert(1, ("chamfer_visible", f"visible-surface Chamfer ({units})"))
    fig = _figure(2 + (1 + 0.55 * len(entries)) * len(panels), 3.4)
    axes = fig.subplots(1, len(panels))
    labels = [e["variant"] if len({x["init"] for x in entries}) == 1 else f"{e['variant']}\n{e['init']}" for e in entries]
    for ax, (key, title) in zip(axes, panels):
        x = np.arange(len(entries))
        means = [np.nan if e[key]["mean"] is None else e[key]["mean"] for e in entries]
        errs = [0.0 if e[key]["std"] is None else e[key]["std"] for e in entries]
        ax.bar(x, means, yerr=errs, capsize=4, color=[COLORS.get(e["variant"], "#999999") for e in entries], alpha=0.85)
        for i, e in enumerate(entries):
            seeds = [r[key] for r in runs if (r["variant"], r["init"]) == (e["variant"], e["init"]) and r[key] is not None]
            ax.scatter(np.full(len(seeds), i) + np.linspace(-0.15, 0.15, len(seeds)) if len(seeds) > 1 else [i] * len(seeds),
                       seeds, color="black", s=12, zorder=3)
        ax.set_xticks(x, labels, fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def _depth_error_pixels(d: dict[str, np.ndarray], i: int) -> np.ndarray:
    """(H, W) bool: the pixels of report view ``i`` whose depth error is shown and scaled: inside the
    mask (else where GT depth exists), rendered (alpha > 0.5), and on the GT object's silhouette
    where the run saved it (so a support plane in the mask, e.g. a floor, sets no colour)."""
    pixels = (d[f"{i}/mask"][0] if f"{i}/mask" in d else d[f"{i}/depth_gt"][0] > 0) & (d[f"{i}/alpha"][0] > 0.5)
    if f"{i}/gt_silhouette" in d:
        pixels = pixels & d[f"{i}/gt_silhouette"][0]
    return pixels


def _views_figure(reps: list[tuple[str, Path]], path: Path) -> Path | None:
    data = [(variant, _load_npz(folder / "views.npz")) for variant, folder in reps]
    data = [(v, d) for v, d in data if d is not None]
    if not data:
        return None
    num_views = len({k.split("/")[0] for k in data[0][1]})
    # shared symmetric depth-error range over every variant and view
    errors = []
    for _, d in data:
        for i in range(num_views):
            if f"{i}/depth_gt" in d:
                valid = _depth_error_pixels(d, i)
                errors.append(np.abs(d[f"{i}/depth"][0] - d[f"{i}/depth_gt"][0])[valid])
    flat = np.concatenate(errors) if errors else np.zeros(1)
    vmax = float(np.percentile(flat, 98)) if flat.size else 1.0
    vmax = vmax if vmax > 0 else 1e-3
    cols = 3 * num_views
    fig = _figure(1.6 * cols + 0.8, 1.6 * (len(data) + 1) + 0.3)
    axes = np.atleast_2d(fig.subplots(len(data) + 1, cols))
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="#e8e8e8")
    image = None
    first = data[0][1]
    for i in range(num_views):
        name = str(first[f"{i}/name"])
        ax = axes[0, 3 * i]
        ax.imshow(_hwc(first[f"{i}/target"]))
        ax.set_title(f"{name}: GT colour", fontsize=8)
        mask = first[f"{i}/mask"][0] if f"{i}/mask" in first else np.ones(first[f"{i}/target"].shape[1:], bool)
        if f"{i}/normal_gt" in first:
            axes[0, 3 * i + 1].imshow(_normal_rgb(first[f"{i}/normal_gt"], mask))
        axes[0, 3 * i + 1].set_title("GT normals", fontsize=8)
        if f"{i}/depth_gt" in first:
            depth = np.where(mask, first[f"{i}/depth_gt"][0], np.nan)
            axes[0, 3 * i + 2].imshow(depth, cmap="viridis")
        axes[0, 3 * i + 2].set_title("GT depth", fontsize=8)
    for row, (variant, d) in enumerate(data, start=1):
        for i in range(num_views):
            alpha_ok = d[f"{i}/alpha"][0] > 0.5
            axes[row, 3 * i].imshow(_hwc(d[f"{i}/color"]))
            axes[row, 3 * i + 1].imshow(_normal_rgb(d[f"{i}/normal"], alpha_ok))
            if f"{i}/depth_gt" in d:
                err = np.where(_depth_error_pixels(d, i), d[f"{i}/depth"][0] - d[f"{i}/depth_gt"][0], np.nan)
                image = axes[row, 3 * i + 2].imshow(err, cmap=cmap, vmin=-vmax, vmax=vmax)
        axes[row, 0].set_ylabel(variant, fontsize=9, color=COLORS.get(variant, "black"))
        if row == 1:
            for i in range(num_views):
                axes[row, 3 * i].set_title("colour", fontsize=8)
                axes[row, 3 * i + 1].set_title("normals", fontsize=8)
                axes[row, 3 * i + 2].set_title("depth - GT depth", fontsize=8)
    for ax in axes.flat:
        _off(ax)
    if image is not None:
        fig.colorbar(image, ax=axes[1:, :].ravel().tolist(), shrink=0.6,
                     label="depth error (scene units)\ngrey: no render, or not the object")
    return _save(fig, path)


def _evaluated(err: dict[str, np.ndarray]) -> np.ndarray:
    """(V,) bool: the vertices the evaluation measured (all of them in a run without the flag)."""
    flag = err.get("evaluated")
    return np.ones(len(err["signed_distance"]), bool) if flag is None else flag.astype(bool)


def _mesh_error_figure(reps: list[tuple[str, Path]], path: Path, units: str) -> Path | None:
    """The predicted mesh's vertices seen from the first report view, coloured by their signed
    distance to the GT; vertices outside the evaluated region (a floor the GT leaves out) in grey,
    and the colour scale and the median from the evaluated ones only."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    data = []
    for variant, folder in reps:
        err, views = _load_npz(folder / "mesh_error.npz"), _load_npz(folder / "views.npz")
        if err is not None and views is not None and _evaluated(err).any():
            data.append((variant, err, views, _evaluated(err)))
    if not data:
        return None
    allabs = np.concatenate([np.abs(e["signed_distance"][flag]) for _, e, _, flag in data])
    vmax = float(np.percentile(allabs, 95)) or 1e-3
    scale = ScalarMappable(Normalize(-vmax, vmax), "coolwarm")
    fig = _figure(2.6 * len(data) + 0.8, 2.9)
    axes = np.atleast_1d(fig.subplots(1, len(data)))
    for ax, (variant, err, views, flag) in zip(axes, data):
        K, w2c = views["0/K"], views["0/world_to_camera"]
        height, width = views["0/alpha"].shape[-2:]
        points, dist, evaluated = err["vertices"].astype(np.float64), err["signed_distance"], flag
        if len(points) > 80_000:
            keep = np.random.default_rng(0).choice(len(points), 80_000, replace=False)
            points, dist, evaluated = points[keep], dist[keep], evaluated[keep]
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        front = cam[:, 2] > 1e-6
        cam, dist, evaluated = cam[front], dist[front], evaluated[front]
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        order = np.argsort(-cam[:, 2])  # far first: near vertices are drawn on top
        if "0/mask" in views:
            ax.imshow(np.where(views["0/mask"][0], 0.85, 1.0), cmap="gray", vmin=0, vmax=1, extent=(0, width, height, 0))
        size = max(0.5, 3000 / max(1, len(order)) ** 0.5 / 4)
        # one scatter in depth order, so that near vertices hide far ones; grey where not evaluated
        colors = scale.to_rgba(dist)
        colors[~evaluated] = NOT_EVALUATED_GREY
        ax.scatter(uv[order, 0], uv[order, 1], c=colors[order], s=size, linewidths=0)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_aspect("equal")
        median = np.median(err["signed_distance"][flag])
        ax.set_title(f"{variant}: median {median:+.3g}", fontsize=8, color=COLORS.get(variant, "black"))
        _off(ax)
    fig.colorbar(scale, ax=list(axes), shrink=0.8, label=f"signed distance ({units})\ngrey: not evaluated")
    return _save(fig, path)


def _pc_figure(folder: Path, path: Path) -> Path | None:
    import torch

    from polargs_plugin.viz import aolp_to_rgb, dolp_to_rgb

    maps = _load_npz(folder / "pc_maps.npz")
    if maps is None:
        return None
    indices = sorted({int(k.split("/")[0]) for k in maps})
    titles = ["s0/2", "AoLP (DoLP as value)", "DoLP", "specular mask", "overexposed mask", "I_diff (in mask)", "I_chro (in mask)"]
    fig = _figure(1.6 * len(titles), 1.7 * len(indices) + 0.3)
    axes = np.atleast_2d(fig.subplots(len(indices), len(titles)))
    for row, i in enumerate(indices):
        intensity = _hwc(maps[f"{i}/intensity"])
        aolp, dolp = torch.from_numpy(maps[f"{i}/aolp"]), torch.from_numpy(maps[f"{i}/dolp"])
        spec = maps.get(f"{i}/specular_mask", np.zeros_like(maps[f"{i}/dolp"], bool))[0].astype(bool)
        over = maps.get(f"{i}/overexposed_mask", np.zeros_like(maps[f"{i}/dolp"], bool))[0].astype(bool)

        def inside(key: str, mask: np.ndarray) -> np.ndarray:
            if f"{i}/{key}" not in maps:
                return intensity * 0.3
            return np.where(mask[..., None], _hwc(maps[f"{i}/{key}"]), intensity * 0.3)

        panels = [intensity, aolp_to_rgb(aolp, dolp.clamp(0, 1) ** 0.5, "dark").permute(1, 2, 0).numpy(),
                  dolp_to_rgb(dolp).permute(1, 2, 0).numpy(), spec.astype(float), over.astype(float),
                  inside("i_diff", spec), inside("i_chro", over)]
        for col, (panel, title) in enumerate(zip(panels, titles)):
            ax = axes[row, col]
            ax.imshow(panel, cmap="gray" if panel.ndim == 2 else None, vmin=0, vmax=1)
            if row == 0:
                ax.set_title(title, fontsize=8)
            _off(ax)
    return _save(fig, path)


def _curves_figure(members: list[tuple[str, int, Path]], path: Path) -> Path | None:
    fig = _figure(9, 5.5)
    axes = fig.subplots(2, 2)
    drawn = set()
    plotted = False
    for variant, seed, folder in members:
        c = _curves(folder)
        if not c or not len(c["iteration"]):
            continue
        plotted = True
        label = variant if variant not in drawn else None
        drawn.add(variant)
        color = COLORS.get(variant, "black")
        it = c["iteration"]
        axes[0, 0].plot(it, _ema(c["loss"]), color=color, label=label, lw=1)
        axes[0, 1].plot(it, _ema(c["psnr"]), color=color, lw=1)
        axes[1, 0].plot(it, c["num_gaussians"], color=color, lw=1)
        axes[1, 1].plot(it, c["appended_total"], color=color, lw=1)
    if not plotted:
        return None
    for ax, title in zip(axes.flat, ("loss (EMA 0.1)", "training PSNR (dB, EMA 0.1)", "number of Gaussians",
                                     "Gaussians appended by Dense (cumulative)")):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("iteration", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].set_yscale("log")
    axes[0, 0].legend(fontsize=8)
    return _save(fig, path)


# ------------------------------------------------------------------------------------ report
def _scene_verdict(rows: list[dict[str, Any]], classes: list[dict[str, Any]], scene: str, init: str) -> list[str]:
    """One line per judged pair of the scene: the verdict with both Chamfer figures; then one per
    variant that loses a visibility class against base (``classes``: gather's class_completeness)."""
    losses = class_loss_lines([r for r in classes if r["scene"] == scene and r["init"] == init], with_scene=False)
    lines = []
    for r in (r for r in rows if r["scene"] == scene and r["init"] == init):
        figures = ", ".join(f"{name} {100 * r[key]:+.1f} %" for key, name in (("capped", "Chamfer"),
                            ("visible", "visible Chamfer")) if r[key] is not None)
        word = {"better": "better than", "worse": "worse than", "level": "level (within 1 %) with",
                "disagree": "neither better nor worse than (the Chamfer figures disagree)",
                "capped only": "judged on the capped Chamfer only against"}[r["verdict"]]
        lines.append(f"- `{r['variant']}` is {word} `{r['reference']}`: {figures}")
    out = (["Verdict (better or worse only where both Chamfer figures agree):", ""] + lines + [""]) if lines else []
    if losses:
        out += [CLASS_LOSS_RULE, ""] + losses + [""]
    return out


def write_report(out: str | os.PathLike, results: dict[str, Any] | None = None, command: str | None = None) -> Path:
    """Write ``<out>/report.md`` and ``<out>/figures/*.png``; returns the report's path.

    Args:
        out: the ablation folder.
        results: :func:`gather`'s return value (gathered now when None).
        command: the command line that produced the folder (shown under "Reproduce").
    """
    out = Path(out)
    results = results if results is not None else gather(out)
    rows = results["runs"]
    runs = {folder.name: folder for folder in find_runs(out)}
    lines = _report_head(out, results)
    several_inits = len({r["init"] for r in rows}) > 1
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for init in dict.fromkeys(r["init"] for r in rows if r["scene"] == scene):
            lines += _scene_section(out, results, runs, scene, init, several_inits)
    lines += _report_tail(out, command)
    path = out / REPORT_NAME
    with atomic_write(path) as handle:
        handle.write("\n".join(lines))
    return path


def _report_head(out: Path, results: dict[str, Any]) -> list[str]:
    """The report's title line, the results table with what its columns mean, and the variants."""
    rows = results["runs"]
    commits = sorted({str(r["git_commit"]) for r in rows})
    lines = ["# PolarGS ablation report", ""]
    lines.append(f"Folder `{out}`; {len(rows)} runs; written {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; "
                 f"git commit {', '.join(c[:12] if c != 'None' else 'unknown' for c in commits) or 'unknown'}.")
    lines += ["", "## Results", "", results.get("markdown") or "(no finished runs)", ""]
    lines += [f"Chamfer (accuracy + completeness) / 2 against the GT mesh in {UNITS}, restricted to the observed "
              "object, distances above 5 % of the GT box diagonal dropped (`polargs eval`, docs/evaluation.md); "
              "\"uncapped\": the same means over every point (a missing or sunken part of the mesh shows there); "
              "\"visible Chamfer\": uncapped, over the GT surface that some training view sees in its GT depth map "
              "(ray-cast from the GT mesh where the dataset has none); "
              "median signed distance of the predicted points to the GT surface (negative = inside); "
              "normal MAE = mean angle between rendered and GT normals inside the GT masks "
              "of every training view (GT normals ray-cast from the GT mesh where the dataset has none). "
              "Mean ± sample standard deviation over seeds; \"vs base\" / \"vs reg\": "
              "relative change of the mean (negative = better). Per visibility class (many, few, grazing views): "
              "the class's share of the seen GT surface, the completeness there and \"missing\", the share of the "
              "class's GT points farther than 2 % of the GT box diagonal from the mesh. Per-run figures (also "
              "accuracy uncapped and the fractions the cap dropped): results.csv, results.json.", ""]
    return lines + ["## Variants", ""] + [f"- `{v}`: {DESCRIPTIONS[v]}" for v in VARIANTS] + [""]


def _scene_section(out: Path, results: dict[str, Any], runs: dict[str, Path], scene: str, init: str,
                   several_inits: bool) -> list[str]:
    """One scene's (and initialisation's) section: its settings, figures and verdict."""
    figures = out / FIGURES_DIR
    tag = _slug(scene if not several_inits else f"{scene}-{init}")
    members = [r for r in results["runs"] if r["scene"] == scene and r["init"] == init]
    entries = [e for e in results["table"] if e["scene"] == scene and e["init"] == init]
    reps: list[tuple[str, Path]] = []  # the first seed's run folder of each variant
    for variant in dict.fromkeys(r["variant"] for r in members):
        first = min((r for r in members if r["variant"] == variant), key=lambda r: r["seed"])
        if first["run"] in runs:
            reps.append((variant, runs[first["run"]]))
    seed_note = f"seed {min(r['seed'] for r in members)}"
    lines = [f"## {scene}" + (f" (init {init})" if several_inits else ""), ""]
    summary = json.loads((reps[0][1] / SUMMARY_NAME).read_text()) if reps else {}
    if summary:
        tc = summary.get("train_config", {})
        lines += [f"{summary.get('num_views')} views, preset {summary.get('preset')} (factor {summary.get('factor')}), "
                  f"{tc.get('iterations')} iterations, init {init} (ran: {', '.join(sorted({str(r['init_used']) for r in members}))}), "
                  f"dataset `{summary.get('dataset')}`.", ""]
    made = _metrics_figure(entries, members, figures / f"metrics_{tag}.png", UNITS)
    lines += ["### Chamfer and normal MAE", "", f"![Chamfer and normal MAE per variant]({made.relative_to(out)})", ""]
    lines += _scene_verdict(results.get("verdicts") or [], results.get("class_completeness") or [], scene, init)
    return lines + _scene_pictures(out, reps, members, runs, tag, seed_note)


def _scene_pictures(out: Path, reps: list[tuple[str, Path]], members: list[dict[str, Any]], runs: dict[str, Path],
                    tag: str, seed_note: str) -> list[str]:
    """A scene section's pictures: views, mesh error, PC inputs and training curves."""
    figures, lines = out / FIGURES_DIR, []
    made = _views_figure(reps, figures / f"views_{tag}.png")
    if made:
        lines += ["### Two views per variant", "",
                  f"Rendered colour, normal map (x red, y up green, towards the camera blue) and depth error "
                  f"(rendered median depth - GT depth, blue = in front of the GT surface) where both exist; {seed_note}.", "",
                  f"![views]({made.relative_to(out)})", ""]
    made = _mesh_error_figure(reps, figures / f"mesh_error_{tag}.png", UNITS)
    if made:
        lines += ["### Mesh error", "",
                  f"TSDF mesh vertices seen from the first view, coloured by signed distance to the GT mesh "
                  f"(negative = inside the GT surface); title: median signed distance; {seed_note}.", "",
                  f"![mesh error]({made.relative_to(out)})", ""]
    pc_folder = next((f for v, f in sorted(reps, key=lambda p: p[0] != "full") if (f / "pc_maps.npz").is_file()), None)
    if pc_folder is not None:
        made = _pc_figure(pc_folder, figures / f"pc_inputs_{tag}.png")
        if made:
            lines += ["### PC inputs", "",
                      f"From `{pc_folder.name}`: training colour s0/2, AoLP coloured by hue (brightness = sqrt DoLP), "
                      "DoLP, the specular and overexposed masks, and the colour targets I_diff (specular pixels) and "
                      "I_chro (overexposed pixels) over a dimmed image.", "",
                      f"![PC inputs]({made.relative_to(out)})", ""]
    made = _curves_figure([(r["variant"], r["seed"], runs[r["run"]]) for r in members if r["run"] in runs],
                          figures / f"curves_{tag}.png")
    if made:
        lines += ["### Training curves", "", "One line per run (every seed), coloured by variant.", "",
                  f"![training curves]({made.relative_to(out)})", ""]
    return lines


def _report_tail(out: Path, command: str | None) -> list[str]:
    """Failed runs with their logs, and the command that reproduces the folder."""
    lines: list[str] = []
    failed = sorted(p for p in (out / "logs").glob("*.log") if not (out / p.stem / SUMMARY_NAME).is_file()) if (out / "logs").is_dir() else []
    if failed:
        lines += ["## Failed runs", ""] + [f"- `{p.stem}`: see `{p.relative_to(out)}`" for p in failed] + [""]
    if command:
        lines += ["## Reproduce", "", "```", command, "```", "",
                  "Finished runs are skipped when the command is run again; delete a run folder to redo it.", ""]
    return lines
