"""The reference trainer: vanilla 3DGS optimisation with the PolarGS hook points.

One iteration (1-based, as in vanilla 3DGS ``train.py``):

1. position learning rate for this iteration; SH degree + 1 every ``sh_increase_every``;
2. pick the next view of a shuffled stack (refilled when empty);
3. render, clamp the colour to [0, 1], base loss ``(1 - w) L1 + w (1 - SSIM)`` against the
   training colour ``s0 / 2`` (outside the object mask replaced by the background colour; a
   band of ``mask_edge_band`` pixels around the mask left out),
   computed by :func:`polargs_plugin.losses.photometric_loss`, the colour loss the hooks'
   reflective replacement assumes;
4. **loss hook**: ``extra, logs = hooks.loss(it, view, render, gaussians)``; ``loss += extra``;
5. ``backward()``; densification statistics; Adam step;
6. under ``no_grad``: vanilla density control, then the **densify hook**
   ``hooks.densify(it, view, render_fn, gaussians)`` where ``hooks.densify_due(it)``, whose result
   is appended.

With ``hooks=None`` no PolarGS code runs at all: that is the Base of every ablation.
``hooks.preprocess(views)`` runs once before the first iteration.

The random state (global torch / numpy / python generators, which the split sampling and the
hooks use, plus the view-order generator) is seeded from ``TrainConfig.seed`` and saved in
checkpoints, so a resumed run continues exactly like an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import random
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from polargs_plugin.backends.reference.model import (
    PARAM_NAMES,
    GaussianModel,
    LearningRates,
    init_points_from_masks,
    scene_extent,
)
from polargs_plugin.backends.reference.binning import DEFAULT_TILE_SIZE
from polargs_plugin.backends.reference.projection import DEFAULT_EPS2D
from polargs_plugin.backends.reference.rasterizer import Backend, CompositeOrder
from polargs_plugin.backends.reference.strategy import DensityConfig, DensityControl
from polargs_plugin.config import CPU_FACTOR, VANILLA_SSIM_WEIGHT, CheckedConfig, above, at_least, satisfies, within
from polargs_plugin.io import PolarInputError, atomic_torch_save, torch_error_line
from polargs_plugin.losses import photometric_loss
from polargs_plugin.threads import ThreadPolicy
from polargs_plugin.types import GaussianState, RenderOut, TrainingHooks, View, validate_view

__all__ = ["TrainConfig", "Trainer", "TrainingHooks", "TrainingDiverged", "StepLogs", "CHECKPOINT_FORMAT", "read_checkpoint"]

CHECKPOINT_FORMAT = "polargs-reference-checkpoint-v1"


class TrainingDiverged(RuntimeError):
    """Training produced a non-finite loss or parameter; the message names the iteration and the tensor.

    Raised before the bad values could reach a checkpoint (the last one written stays valid)."""


CPU_EPS2D = 0.1  # the CPU preset's screen dilation (pixels^2), TrainConfig.cpu
CPU_PRUNE_SCREEN_FRACTION = 20 / 128  # the CPU preset's screen-size prune, as a share of the image width
# The progress bar's remaining time comes from the rate averaged over the last ~1/this iterations
# (tqdm's smoothing): long enough to spread the periodic Dense calls, short enough to follow the
# model's growth.
_RATE_SMOOTHING = 0.01


def _is_torch_device(name: str, config: Any) -> bool:
    try:
        torch.device(name)
    except (RuntimeError, ValueError):
        return False
    return True


@dataclass
class TrainConfig(CheckedConfig):
    """Reference-trainer settings. Defaults are vanilla 3DGS (30k iterations, SH degree 3).

    Iterations are 1-based. Use :meth:`cpu` for short CPU runs, :meth:`paper` for the vanilla
    schedule; every field is checked when the config is built and again by :class:`Trainer`
    (:class:`~polargs_plugin.config.CheckedConfig`).

    Attributes:
        iterations: optimisation steps of a run; >= 1. Default and vanilla 30000.
        schedule_scale: the ONE factor that shortens every schedule: the density-control start /
            stop / interval / opacity-reset interval, the SH-degree interval and the length of
            the position learning-rate decay; > 0. Default 1 (vanilla); :meth:`cpu` sets 1/6.
        sh_degree: highest spherical-harmonics degree of the colours; in [0, 3]. Default and
            vanilla 3.
        sh_increase_every: the active SH degree grows by one every this many iterations (times
            ``schedule_scale``); >= 1. Default and vanilla 1000.
        seed: seed of the torch, numpy and python generators and of the view order (any
            integer). Default 0.
        background: RGB colour, in [0, 1], the renders are composited on and that replaces the
            training colour outside a view's mask (with ``use_masks``). Default black (vanilla's
            default).
        use_masks: train against the background outside the views' object masks, where they
            have one. Default True.
        mask_edge_band: pixels outside a view's mask within this many pixels of it (the mask
            dilated by a (2b+1)^2 square) are left out of the colour loss; >= 0; 0 (default,
            vanilla) keeps every pixel. A binary mask says nothing of how much of a pixel on its
            edge the object covers, and the rasterizer's low-pass filter spreads an exactly
            placed surface ~1 px beyond its silhouette, so training against a background there
            pulls the surface inwards (docs/evaluation.md "The mask's edge"). Only with
            ``use_masks``.
        num_init_points: initial Gaussians sampled on the visual hull of the masks (when no
            points are given to the :class:`Trainer`); >= 1. Default 10000.
        init_resolution: voxels per side of the visual-hull grid; >= 1. Default 64.
        initial_opacity: opacity of the initial Gaussians; in (0, 1). Default and vanilla 0.1.
        eps2d: the rasterizer's screen-space low-pass dilation, in pixels^2 (``rasterize``),
            given to the model (:class:`GaussianModel` keeps it with its parameters); >= 0.
            Default and vanilla 0.3; :meth:`cpu` sets 0.1.
        order: the rasterizer's compositing order within a tile (``rasterize``), given to the
            model like ``eps2d``: "center" (default and vanilla, as the upstream trainers: by
            each Gaussian's mean depth) or "ray" (by the depth at which the tile centre's ray
            meets it; it shrinks the inward bias, docs/evaluation.md "Depth bias"). A
            ray-ordered model's meshes, evaluation and pictures are rendered with one-pixel
            tiles (``GaussianModel.render_output``).
        tile_size: the rasterizer's tile edge in pixels during training, given to the model;
            >= 1. Default and vanilla 16. With ``order="ray"`` smaller tiles follow each pixel's
            ray more closely and cost more time (a CPU-preset training at 128 px: about 1.5x
            at 4 px).
        lrs: the learning rates (:class:`LearningRates`, vanilla's).
        density: vanilla density control (:class:`DensityConfig`).
        device: torch device of the training, e.g. ``"cpu"`` or ``"cuda:0"``. Default ``"cpu"``.
        backend: the rasterizer's compositing path: ``"torch"`` (exact reference, any device),
            ``"numba"`` (compiled CPU kernel) or ``"auto"`` (default: numba on CPU).
        progress: show a progress bar. Default True.
        threads: the process's CPU threading policy (:class:`polargs_plugin.threads.ThreadPolicy`:
            one thread count for torch and numba, numba's threading layer, OpenMP's wait policy),
            applied when a :class:`Trainer` is built (docs/speed.md).
        log_every: every how many iterations :meth:`Trainer.train` reads the progress figures
            (mean loss over those iterations, PSNR of that iteration's view); in between no
            figure leaves the device; >= 1. Default 10.
    """

    RETIRED: ClassVar[dict[str, str]] = {
        "ssim_weight": "the colour loss's SSIM share is PolarConfig's losses.ssim_weight (in a settings file: "
                       "\"polar\": {\"losses\": {\"ssim_weight\": ...}}); without the hooks it is vanilla 3DGS's 0.2",
    }

    iterations: int = field(default=30_000, metadata=at_least(1))
    schedule_scale: float = field(default=1.0, metadata=above(0))
    sh_degree: int = field(default=3, metadata=within(0, 3))
    sh_increase_every: int = field(default=1000, metadata=at_least(1))
    seed: int = 0
    background: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=within(0, 1))
    use_masks: bool = True
    mask_edge_band: int = field(default=0, metadata=at_least(0))
    num_init_points: int = field(default=10_000, metadata=at_least(1))
    init_resolution: int = field(default=64, metadata=at_least(1))
    initial_opacity: float = field(default=0.1, metadata=within(0, 1, low_open=True, high_open=True))
    eps2d: float = field(default=DEFAULT_EPS2D, metadata=at_least(0))
    order: CompositeOrder = "center"
    tile_size: int = field(default=DEFAULT_TILE_SIZE, metadata=at_least(1))
    lrs: LearningRates = field(default_factory=LearningRates)
    density: DensityConfig = field(default_factory=DensityConfig)
    device: str = field(default="cpu", metadata=satisfies(_is_torch_device, "a torch device such as 'cpu' or 'cuda:0'"))
    backend: Backend = "auto"
    progress: bool = True
    threads: ThreadPolicy = field(default_factory=ThreadPolicy)
    log_every: int = field(default=10, metadata=at_least(1))

    @classmethod
    def paper(cls, **overrides: Any) -> "TrainConfig":
        """Vanilla 3DGS schedule (30k iterations, SH degree 3)."""
        return dataclasses.replace(cls(), **overrides)

    @classmethod
    def cpu(cls, factor: float = CPU_FACTOR, **overrides: Any) -> "TrainConfig":
        """Every schedule multiplied by ``factor`` for a CPU run at 128x128: SH degree 1, 2000
        initial points, at most 6000 Gaussians from vanilla density control (Dense's appends come
        on top, see :class:`DensityConfig`), the screen-size prune at 20 / 128 of the image width
        (vanilla's 20 px at 128 px; larger images keep that share), no opacity reset, a screen dilation ``eps2d`` of
        0.1 px^2 instead of 0.3 and a ``mask_edge_band`` of 1 pixel (a pixel at 128 px is a large
        share of the object: vanilla's dilation widened silhouettes by ~1.4 px, and training
        against the background just outside the mask offset the spill by recessing the surface;
        docs/evaluation.md "Depth bias" and "The mask's edge").

        The default ``polargs_plugin.config.CPU_FACTOR`` = 1/6 is the CPU preset: 5000 iterations, refinement every
        17 from 83 to 2500, SH degree +1 every 167, position learning-rate decay over 5000; with
        ``PolarConfig.cpu_demo()`` (the PolarGS schedules at 1/2: Dense 500-3500 every 50, L_dn
        from 3500; ``polargs_plugin.config.polar_schedule_factor``). docs/speed.md "CPU preset"
        gives the reasons and the wall times."""
        preset = dict(
            iterations=round(30_000 * factor),
            schedule_scale=factor,
            sh_degree=1,
            num_init_points=2000,
            density=DensityConfig(max_gaussians=6000, opacity_reset=False, prune_screen_fraction=CPU_PRUNE_SCREEN_FRACTION),
            eps2d=CPU_EPS2D,
            mask_edge_band=1,
        )
        return cls(**{**preset, **overrides})  # checked once, with the overrides in


class Trainer:
    """Vanilla 3DGS training of the reference :class:`GaussianModel` with optional PolarGS hooks.

    Args:
        views: training views (``view.image`` = s0 / 2 is the colour target; mono images are
            repeated to RGB).
        config: settings (default :class:`TrainConfig`).
        hooks: an object with ``preprocess / loss / densify_due / densify / state_dict / load_state_dict``
            (e.g. ``PolarHooks``), or None for plain 3DGS.
        init_points: optional ((N, 3) points, (N, 3) colours in [0, 1]), e.g. SfM points.
            Default: points on the visual hull of the masks (:func:`init_points_from_masks`).

    Note: constructing a trainer seeds the global torch, numpy and python generators and applies
    ``config.threads`` (process-wide thread counts, numba's threading layer; ``self.threads``
    says what took effect).
    """

    def __init__(
        self,
        views: list[View],
        config: TrainConfig | None = None,
        hooks: TrainingHooks | None = None,
        init_points: tuple[Tensor, Tensor] | None = None,
    ):
        if not views:
            raise ValueError("Trainer: no training views")
        self.config = config or TrainConfig()
        cfg = self.config
        cfg.validate("config")  # attributes may have been reassigned since it was built
        self.threads = cfg.threads.apply()  # process-wide thread counts / layer (polargs_plugin.threads)
        _seed_everything(cfg.seed)
        self.device = torch.device(cfg.device)
        for view in views:
            validate_view(view, "Trainer")
        self.views = [v.to(self.device) for v in views]
        self.hooks = hooks
        self.extent = scene_extent(self.views)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        for view in self.views:
            _check_channels(view)
        factor = cfg.schedule_scale
        self.sh_interval = max(1, round(cfg.sh_increase_every * factor))
        lrs = dataclasses.replace(cfg.lrs, means_max_steps=max(1, round(cfg.lrs.means_max_steps * factor)))
        if init_points is None:
            init_points = init_points_from_masks(self.views, cfg.num_init_points, cfg.init_resolution)
        points, colors = init_points
        self.model = GaussianModel.from_points(
            points.to(self.device),
            colors.to(self.device),
            sh_degree=cfg.sh_degree,
            extent=self.extent,
            initial_opacity=cfg.initial_opacity,
            lrs=lrs,
            eps2d=cfg.eps2d,
            order=cfg.order,
            tile_size=cfg.tile_size,
        )
        self.density = DensityControl(cfg.density.scaled(factor), self.extent, max(v.width for v in self.views))
        self.iteration = 0
        self._sampler = torch.Generator().manual_seed(cfg.seed)
        self._order: list[int] = []
        self._prepared = False
        self.polar_maps: Any = None
        self.last_logs: Mapping[str, float] = {}

    # --------------------------------------------------------------------- pieces
    def target(self, view: View) -> Tensor:
        """(3, H, W) colour target of ``view``: s0 / 2 clamped to [0, 1], mono repeated to RGB, the
        background outside the mask (``use_masks``). Built from the view's stored images when asked
        (a step keeps only its own view's target)."""
        image = view.image.float().clamp(0, 1)
        if image.shape[0] == 1:
            image = image.expand(3, -1, -1)
        if self.config.use_masks and view.mask is not None:
            m = view.mask.to(image).reshape(1, view.height, view.width)
            image = image * m + self.background.reshape(3, 1, 1) * (1 - m)
        return image.contiguous()

    def edge_band(self, view: View) -> Tensor | None:
        """(1, H, W) bool: the pixels the colour loss leaves out (``TrainConfig.mask_edge_band``), or None."""
        width = self.config.mask_edge_band
        if width == 0 or not self.config.use_masks or view.mask is None:
            return None
        mask = view.mask.reshape(1, 1, view.height, view.width).float()
        grown = torch.nn.functional.max_pool2d(mask, 2 * width + 1, stride=1, padding=width)
        return ((grown > 0) & (mask == 0)).reshape(1, view.height, view.width)

    def render(self, view: View, state: GaussianState | None = None) -> RenderOut:
        """Render ``view`` with the trainer's background; colour clamped to [0, 1] (as vanilla).
        ``state``: the model's current :meth:`GaussianModel.state`, if already computed. The
        plane depth (L_dn's) only with hooks: a Base run has no use for it."""
        out = self.model.render(view, background=self.background, state=state, backend=self.config.backend,
                                with_plane_depth=self.hooks is not None)
        return dataclasses.replace(out, color=out.color.clamp(0, 1))

    def _prepare(self) -> None:
        if not self._prepared:
            if self.hooks is not None:
                self.polar_maps = self.hooks.preprocess(self.views)
            self._prepared = True

    def _next_view(self) -> int:
        if not self._order:
            self._order = torch.randperm(len(self.views), generator=self._sampler).tolist()
        return self._order.pop()

    def base_loss(self, image: Tensor, target: Tensor) -> Tensor:
        """``(1 - w) L1 + w (1 - SSIM)`` over the whole image (vanilla 3DGS), as
        :func:`polargs_plugin.losses.photometric_loss`, with ``w`` the hooks' ``losses.ssim_weight``
        (:func:`ssim_weight_of`), so PolarHooks' replacement cancels it exactly."""
        return photometric_loss(image, target, ssim_weight=ssim_weight_of(self.hooks))

    # --------------------------------------------------------------------- training
    def step(self) -> "StepLogs":
        """Run one iteration; returns its :class:`StepLogs`: ``{"loss", "psnr", "num"}`` plus the
        hooks' logs and the refinement counts.

        The figures are read lazily: the loss, the PSNR and the hooks' values stay tensors until a
        key is read (no host synchronisation, no extra image pass in a step nobody looks at).
        """
        self._prepare()
        model = self.model
        it = self.iteration + 1
        model.update_learning_rate(it)
        if it % self.sh_interval == 0:
            model.active_sh_degree = min(model.active_sh_degree + 1, model.max_sh_degree)
        index = self._next_view()
        # the band and the target are built when used, not kept: a step's work is far larger
        view = self.views[index]
        band = self.edge_band(view)
        target = self.target(view)

        # The hooks get the activations the render used (one set of activation nodes to differentiate).
        state = model.state() if self.hooks is not None else None
        render = self.render(view, state)
        if band is not None:  # the target in the band: no loss, no gradient there (hooks' colour terms included)
            render = dataclasses.replace(render, color=torch.where(band, target, render.color))
        loss = self.base_loss(render.color, target)
        values: dict[str, Any] = {}
        if self.hooks is not None:
            extra, hook_logs = self.hooks.loss(it, view, render, state)
            loss = loss + extra
            # detached, so that the logs do not keep the step's autograd graph alive
            values.update({k: v.detach() if isinstance(v, Tensor) else v for k, v in (hook_logs or {}).items()})
        if not bool(torch.isfinite(loss)):  # one scalar: the only host sync a step needs
            raise TrainingDiverged(f"iteration {it}: the loss is {float(loss)} (view '{view.name}'); nothing was updated")
        loss.backward()
        self.density.update(render, view.width, view.height, it)
        model.optimizer.step()
        model.optimizer.zero_grad(set_to_none=True)
        _check_finite_parameters(model, f"iteration {it}: after the optimizer step")

        with torch.no_grad():
            refined = self.density.step(model, it)
            if self.hooks is not None and self.hooks.densify_due(it):
                new = self.hooks.densify(it, view, self.render, model.state(), render=render.detached())
                if new is not None and len(new) > 0:
                    model.append(new)
                    self.density.pad(len(new))
                    values["appended"] = float(len(new))
        self.iteration = it
        values.update(num=float(model.num), **{k: float(v) for k, v in refined.items() if v})
        logs = StepLogs(values, loss=loss.detach(), color=render.color.detach(), target=target)
        self.last_logs = logs
        return logs

    def time_step(self, view: View, repeats: int = 2) -> float:
        """Seconds of the cheapest of ``repeats`` renders of ``view`` with the colour loss and its
        backward, on the current model, which is left as it was (the gradients are dropped; no
        optimizer step, no density statistics, no random numbers drawn). The first repeat also
        pays for compiling and warming what the step uses."""
        best = math.inf
        for _ in range(max(1, repeats)):
            start = time.perf_counter()
            render = self.render(view)
            self.base_loss(render.color, self.target(view)).backward()
            best = min(best, time.perf_counter() - start)
            self.model.optimizer.zero_grad(set_to_none=True)
        return best

    def train(self, until: int | None = None, checkpoint: str | Path | None = None, checkpoint_every: int = 0) -> dict[str, Any]:
        """Train up to iteration ``until`` (default ``config.iterations``).

        Args:
            until: last iteration to run (a run can be stopped early and resumed later).
            checkpoint: where to save a checkpoint at the end (and every ``checkpoint_every``).
            checkpoint_every: iterations between intermediate checkpoints (0 = only at the end).

        Returns:
            final figures: ``iterations``, ``num_gaussians``, ``psnr`` (mean over all training
            views, against the masked targets), ``loss`` (mean over the last ``log_every``
            iterations, at most; None if none ran), ``seconds``, ``extent`` and the last hook logs.
        """
        end = self.config.iterations if until is None else int(until)
        self._prepare()
        start_time = time.perf_counter()
        window: list[Tensor] = []  # loss tensors since the figures were last read (no sync per step)
        mean_loss = psnr = None
        bar = tqdm(
            total=end,
            initial=self.iteration,
            desc="train",
            unit="it",
            disable=not self.config.progress,
            dynamic_ncols=True,
            smoothing=_RATE_SMOOTHING,
        )
        with bar:
            while self.iteration < end:
                logs = self.step()
                window.append(logs.loss)
                bar.update(1)
                if self.iteration % self.config.log_every == 0 or self.iteration == end:
                    mean_loss = float(torch.stack(window).mean())
                    psnr = logs["psnr"]
                    window.clear()
                    bar.set_postfix(loss=f"{mean_loss:.4f}", psnr_view=f"{psnr:.2f}", n=self.model.num)
                if checkpoint is not None and checkpoint_every > 0 and self.iteration % checkpoint_every == 0:
                    self.save_checkpoint(checkpoint)
            seconds = time.perf_counter() - start_time
            # the bar ends on the figure the summary reports: PSNR over all views, not the last view's
            final_psnr = self.evaluate()
            bar.set_postfix(loss=f"{mean_loss:.4f}" if mean_loss is not None else "-", psnr=f"{final_psnr:.2f}",
                            n=self.model.num)
        if checkpoint is not None:
            self.save_checkpoint(checkpoint)
        return {
            "iterations": self.iteration,
            "num_gaussians": self.model.num,
            "psnr": final_psnr,
            "loss": mean_loss,
            "seconds": seconds,
            "extent": self.extent,
            "hook_logs": {k: float(v) for k, v in self.last_logs.items() if k not in ("loss", "psnr", "num")},
        }

    @torch.no_grad()
    def evaluate(self) -> float:
        """Mean PSNR (dB) of the rendered training views against their (masked) targets."""
        values = [_psnr(float(((self.render(v).color - self.target(v)) ** 2).mean())) for v in self.views]
        return float(np.mean(values))

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path: str | Path) -> Path:
        """Write everything needed to resume (atomic: the file is complete or absent)."""
        path = Path(path)
        data = {
            "format": CHECKPOINT_FORMAT,
            "iteration": self.iteration,
            "config": self.config.to_dict(),
            "view_names": [v.name for v in self.views],
            "model": self.model.checkpoint(),
            "density": self.density.state_dict(),
            "hooks": None if self.hooks is None else self.hooks.state_dict(),
            "rng": {
                "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
                "numpy": _numpy_state_to_dict(np.random.get_state()),
                "python": random.getstate(),
                "sampler": self._sampler.get_state(),
                "order": list(self._order),
            },
        }
        return atomic_torch_save(data, path)

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore a checkpoint written by :meth:`save_checkpoint` into this trainer.

        The trainer must have been built on the same views (names are checked); the
        configuration passed at construction is kept (so ``iterations`` may be raised).
        Only load checkpoints from trusted sources (``torch.load`` with ``weights_only=True``).
        """
        path = Path(path)
        data = read_checkpoint(path, self.device)
        names = [v.name for v in self.views]
        if data["view_names"] != names:
            raise PolarInputError(path, "checkpoint was trained on different views than the ones given")
        if (self.hooks is None) != (data["hooks"] is None):
            raise PolarInputError(
                path, "checkpoint was trained " + ("without" if data["hooks"] is None else "with") + " hooks"
            )
        self._prepare()
        model = GaussianModel.from_checkpoint(data["model"], lrs=self.model.lrs, device=self.device)
        try:
            _check_finite_parameters(model, "checkpoint")
        except TrainingDiverged as err:
            raise PolarInputError(path, str(err)) from None
        self.model = model
        self.density.load_state_dict(data["density"])
        if self.hooks is not None:
            self.hooks.load_state_dict(data["hooks"])
        self.iteration = int(data["iteration"])
        rng = data["rng"]
        torch.set_rng_state(rng["torch"].cpu())
        if rng["cuda"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])
        np.random.set_state(_numpy_state_from_dict(rng["numpy"]))
        random.setstate(_to_tuple(rng["python"]))
        self._sampler.set_state(rng["sampler"].cpu())
        self._order = [int(i) for i in rng["order"]]


def read_checkpoint(path: str | Path, map_location: torch.device | str = "cpu") -> dict[str, Any]:
    """The contents of a checkpoint written by :meth:`Trainer.save_checkpoint`.

    Only plain tensors and containers are unpickled (``torch.load(weights_only=True)``).

    Raises:
        PolarInputError: naming the file: missing, unreadable, or not a checkpoint of this package.
    """
    path = Path(path)
    if not path.is_file():
        raise PolarInputError(path, "checkpoint file not found")
    if path.stat().st_size == 0:
        raise PolarInputError(path, "not a checkpoint of this package (the file is empty)")
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # truncated, not a torch file, or disallowed types
        raise PolarInputError(path, f"not a checkpoint of this package ({_load_failure(err)})") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise PolarInputError(path, f"not a checkpoint of this package (no \"format\": \"{CHECKPOINT_FORMAT}\" entry)")
    return data


def _load_failure(err: Exception) -> str:
    """Why torch could not read a file, in a few words. torch's own text for a weights-only
    refusal advises loading the file with ``weights_only=False``, which runs whatever code an
    untrusted file holds: it is never repeated."""
    if isinstance(err, pickle.UnpicklingError) or "weights_only" in str(err):
        return "torch cannot read it as plain tensors and containers"
    return f"torch cannot read it: {torch_error_line(err)}"


class StepLogs(Mapping):
    """One iteration's figures, read lazily: a read-only mapping of float values.

    ``loss`` (the total loss, hooks' terms included), ``psnr`` (dB, of the rendered colour against
    the view's target), ``num`` (Gaussians after the step), the hooks' logs (``l_*`` ...),
    ``appended`` and the refinement counts when nonzero. The tensors are kept as they are and turned
    into floats (a host synchronisation on CUDA; the PSNR's image pass) only when a key is read,
    once. ``logs.loss`` is the loss tensor itself (detached).
    """

    __slots__ = ("_values", "loss", "_color", "_target", "_cache")

    def __init__(self, values: dict[str, Any], loss: Tensor, color: Tensor, target: Tensor):
        self._values = values
        self.loss = loss
        self._color = color
        self._target = target
        self._cache: dict[str, float] = {}

    def _keys(self) -> list[str]:
        return [k for k in self._values if k not in ("loss", "psnr")] + ["loss", "psnr"]

    def __getitem__(self, key: str) -> float:
        if key in self._cache:
            return self._cache[key]
        if key == "loss":
            value = float(self.loss)
        elif key == "psnr":
            with torch.no_grad():
                value = _psnr(float(((self._color - self._target) ** 2).mean()))
        else:
            value = float(self._values[key])
        self._cache[key] = value
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def __contains__(self, key: object) -> bool:
        return key in ("loss", "psnr") or key in self._values

    def __repr__(self) -> str:
        return f"StepLogs({dict(self)})"


def _check_finite_parameters(model: GaussianModel, where: str) -> None:
    # A sum is non-finite if any element is (or on overflow, which the exact count below then
    # clears): one small reduction per parameter and one host sync, instead of six masks.
    sums = torch.stack([getattr(model, name).detach().sum() for name in PARAM_NAMES])
    if bool(torch.isfinite(sums).all()):
        return
    bad = {name: int((~torch.isfinite(getattr(model, name))).sum()) for name in PARAM_NAMES}
    named = [f"'{name}' has {count} of {getattr(model, name).numel()}" for name, count in bad.items() if count]
    if named:
        raise TrainingDiverged(f"{where}: non-finite parameters: {', '.join(named)}")


def _check_channels(view: View) -> None:
    if view.channels not in (1, 3):
        raise PolarInputError(view.source or view.name, f"expected 1 or 3 colour channels, got {view.channels}")


def ssim_weight_of(hooks: TrainingHooks | None) -> float:
    """The SSIM share of the trainer's colour loss: the PolarHooks' ``losses.ssim_weight`` (the
    loss their reflective replacement cancels), vanilla 3DGS's without them."""
    from polargs_plugin.hooks import PolarHooks

    return hooks.config.losses.ssim_weight if isinstance(hooks, PolarHooks) else VANILLA_SSIM_WEIGHT


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def _seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


def _numpy_state_to_dict(state: tuple) -> dict:
    kind, keys, pos, has_gauss, cached = state
    return {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss), "cached": float(cached)}


def _numpy_state_from_dict(d: dict) -> tuple:
    return (d["kind"], d["keys"].cpu().numpy().astype(np.uint32), d["pos"], d["has_gauss"], d["cached"])


def _to_tuple(value: Any) -> Any:
    """torch.load may return lists where tuples were saved; python's random wants tuples."""
    return tuple(_to_tuple(v) for v in value) if isinstance(value, (list, tuple)) else value
