"""PolarDensifier: the Dense module on a training schedule (what PolarHooks.densify delegates to).

On each scheduled iteration, for the current training view:

1. choose ``num_sources`` source views by triangulation angle (view_selection.py);
2. render the reference and the sources with ``render_fn``;
3. run polar-enhanced PatchMatch initialised from the rendered depth and normal, with the view's
   AoLP / DoLP (patchmatch.py);
4. keep pixels whose photometric cost is below ``filters.max_photometric_cost`` and that are
   multi-view geometrically and polarimetrically consistent (filters.py). A source's depth is,
   per pixel, its last PatchMatch depth from this densifier where that passed the filters
   (cached), else its current rendered depth where the render is opaque, else its last
   unfiltered PatchMatch depth. Unconfirmed PatchMatch depths are thus evidence only inside
   render holes (so fills of holes shared by every render can be confirmed once neighbouring
   views have been processed); elsewhere they can be far off early in training (textureless
   surfaces, a rough model), and checking against them rejects good pixels;
5. store the kept normals as the L_n target ``N_opt`` of the view (:meth:`normal_target`);
6. seed new Gaussians where the render has a hole or a wrong surface (seeding.py), at most
   ``max_new_per_call`` a call and, with ``budget_fraction``, at most that fraction of the model's
   size at the first call over the whole run.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch
from torch import Tensor

from polargs_plugin.config import PolarConfig
from polargs_plugin.io import atomic_torch_save
from polargs_plugin.densify.filters import consistency_filter
from polargs_plugin.densify.patchmatch import patchmatch
from polargs_plugin.densify.seeding import seed_gaussians, seed_mask, seed_relative_depth
from polargs_plugin.densify.view_selection import scene_center, select_sources
from polargs_plugin.types import GaussianState, NewGaussians, PolarMaps, RenderOut, View

__all__ = ["PolarDensifier", "ViewStates", "source_depth", "STATE_DTYPE"]

#: Every visited view's last PatchMatch depth and normal are kept (the sources' evidence, the L_n
#: targets) in this dtype: relative 4.9e-4, far below PatchMatch's own error, at half the memory.
STATE_DTYPE = torch.float16

#: One view's kept PatchMatch result: depth (1, H, W) and normal (3, H, W) in STATE_DTYPE, and
#: where they passed the filters, valid (1, H, W) bool.
ViewState = tuple[Tensor, Tensor, Tensor]


class ViewStates:
    """The kept PatchMatch result of every visited view, in memory or in a temporary folder.

    With a ``parent`` folder (the maps cache of a run), each view's state lives in a file of a
    temporary folder created there and removed when the store is garbage-collected or the
    process exits; a view's state is read when it is used (the L_n target of the current view,
    the sources of a Dense call), so the memory does not grow with the number of views visited.

    Args:
        parent: where the temporary folder goes; None keeps the states in memory.
    """

    def __init__(self, parent: str | Path | None = None):
        self._memory: dict[str, ViewState] = {}
        self._folder = None if parent is None else tempfile.TemporaryDirectory(prefix=".dense-state-", dir=parent, ignore_cleanup_errors=True)
        self._names: set[str] = set()

    def _path(self, name: str) -> Path:
        return Path(self._folder.name) / f"{len(name)}-{name.encode().hex()}.pt"  # any view name, one file

    def put(self, name: str, depth: Tensor, normal: Tensor, valid: Tensor) -> None:
        state = (depth.detach().to(STATE_DTYPE), normal.detach().to(STATE_DTYPE), valid.detach().bool())
        if self._folder is None:
            self._memory[name] = state
        else:
            atomic_torch_save([t.cpu() for t in state], self._path(name))
        self._names.add(name)

    def get(self, name: str, device: torch.device | str | None = None) -> ViewState | None:
        """The view's state (None before its first Dense call), on ``device`` (default: as stored)."""
        if name not in self._names:
            return None
        if self._folder is None:
            state = self._memory[name]
        else:
            state = tuple(torch.load(self._path(name), map_location="cpu", weights_only=True))
        return state if device is None else tuple(t.to(device) for t in state)

    def names(self) -> list[str]:
        return sorted(self._names)


def source_depth(
    rendered: Tensor, alpha: Tensor, alpha_threshold: float,
    patchmatch_depth: Tensor | None = None, kept: Tensor | None = None,
) -> Tensor:
    """A source view's depth as evidence for the consistency filter.

    Per pixel: the PatchMatch depth where it passed the filters, else the rendered depth where
    the render is opaque, else the unconfirmed PatchMatch depth (render holes), else 0.

    Args:
        rendered, alpha: (1, H, W) current rendered depth and opacity of the source.
        alpha_threshold: the render counts where ``alpha > alpha_threshold``.
        patchmatch_depth: (1, H, W) the source's last PatchMatch depth (0 = none), or None.
        kept: (1, H, W) bool, where that depth passed the filters (needed with it).

    Returns:
        (1, H, W) depth (0 = no evidence).
    """
    depth = torch.where(alpha > alpha_threshold, rendered, torch.zeros_like(rendered))
    if patchmatch_depth is None:
        return depth
    return torch.where(kept | (depth <= 0), patchmatch_depth, depth)


class PolarDensifier:
    """Scheduled polar-enhanced PatchMatch densification.

    Args:
        config: PolarConfig (uses ``config.densify`` and its patchmatch / filters sections).
        views: all training views (their cameras drive source selection).
        maps: PolarMaps per view name (AoLP / DoLP); views without maps run without the AoLP term.
            A store with a ``folder`` (a :class:`~polargs_plugin.correction.store.MapsStore` on a
            cache folder) also hosts the per-view Dense state in a temporary folder there
            (:class:`ViewStates`).
    """

    def __init__(self, config: PolarConfig, views: list[View], maps: dict[str, PolarMaps]):
        if not views:
            raise ValueError("PolarDensifier needs at least one view")
        self.config = config
        self.views = list(views)
        self.maps = maps
        self._index = {v.name: i for i, v in enumerate(self.views)}
        self._w2c = torch.stack([v.world_to_camera.to(torch.float64).cpu() for v in self.views])
        self._center = scene_center(self._w2c) if len(self.views) > 1 else None
        self._states = ViewStates(getattr(maps, "folder", None))
        self._generator = torch.Generator().manual_seed(config.densify.patchmatch.seed)
        self.calls = 0
        # Gaussians appended so far, and the most all calls may append (None: no budget; set at
        # the first call from the model's size then)
        self.appended = 0
        self.budget: int | None = None
        # running pixel counts of each stage (photometric, kept = N_opt, seed), for diagnostics
        self.stats = {"estimated": 0, "photometric": 0, "kept": 0, "seeds": 0, "added": 0}

    def should_run(self, iteration: int) -> bool:
        """Whether ``iteration`` is on the schedule (start <= it <= end, it % interval == 0)."""
        d = self.config.densify
        return d.enabled and d.start_iter <= iteration <= d.end_iter and iteration % d.interval == 0

    def __call__(
        self,
        iteration: int,
        view: View,
        render_fn,
        gaussians: GaussianState | None = None,
        render: RenderOut | None = None,
    ) -> NewGaussians | None:
        """Densify from ``view`` if ``iteration`` is scheduled.

        Args:
            iteration: training iteration.
            view: the current training view (must be one of ``views`` by name).
            render_fn: ``render_fn(view) -> RenderOut`` with the current Gaussians.
            gaussians: the current Gaussians (unused by the algorithm; part of the hook API).
            render: the caller's render of ``view`` (``render_fn(view)`` when None).

        Returns:
            NewGaussians to append (world frame), or None when nothing is to be added.
        """
        if not self.should_run(iteration):
            return None
        if view.name not in self._index:
            raise KeyError(f"view '{view.name}' is not one of the densifier's views")
        if self.config.densify.budget_fraction is not None and self.budget is None:
            if gaussians is None:
                raise ValueError("PolarDensifier: densify.budget_fraction needs the current Gaussians")
            self.budget = int(self.config.densify.budget_fraction * gaussians.means.shape[0])
        with torch.no_grad():
            return self._densify(view, render_fn, render)

    def _sources(self, ref: int) -> list[int]:
        if self._center is None:
            return []
        pm = self.config.densify.patchmatch
        chosen = select_sources(self._w2c[ref], self._w2c, pm.num_sources, self._center, exclude=ref)
        if chosen:  # the NCC stacks sources, so they must share one size
            size = (self.views[chosen[0]].height, self.views[chosen[0]].width)
            chosen = [j for j in chosen if (self.views[j].height, self.views[j].width) == size]
        return chosen

    def _densify(self, view: View, render_fn, render: RenderOut | None) -> NewGaussians | None:
        cfg = self.config.densify
        ref = self._index[view.name]
        src = self._sources(ref)
        if not src:
            return None
        if render is None:
            render = render_fn(view)
        dev = render.depth.device
        src_views = [self.views[j] for j in src]
        ref_polar = self._polar(view.name, dev)  # decoded once: the filter below reads it again
        mask = view.mask.to(dev) if (cfg.use_view_mask and view.mask is not None) else None
        init_valid = render.alpha > cfg.alpha_threshold
        if not (init_valid & (render.depth > 0)).any():
            return None
        gen = self._device_generator(dev)
        result = patchmatch(
            view.image.to(dev), view.K, view.world_to_camera,
            # grey already (all PatchMatch reads of them): a fourth of the colour images' memory
            torch.stack([v.image.to(dev).mean(-3, keepdim=True) for v in src_views]),
            torch.stack([v.K for v in src_views]), torch.stack([v.world_to_camera for v in src_views]),
            render.depth, render.normal,
            aolp=ref_polar[0] if ref_polar is not None else None,
            dolp=ref_polar[1] if ref_polar is not None else None,
            mask=mask, init_valid=init_valid, config=cfg.patchmatch, generator=gen,
        )
        photometric_ok = (result.photometric_cost <= cfg.filters.max_photometric_cost) & (result.depth > 0)
        depth = torch.where(photometric_ok, result.depth, torch.zeros_like(result.depth))

        # the sources are rendered after PatchMatch, which does not read them, and only their
        # depth evidence and normals are kept: at real sizes a Dense call's peak memory
        src_depths, src_normals = [], []
        for v in src_views:
            r = render_fn(v)
            kept = self._states.get(v.name, dev)
            src_depths.append(source_depth(r.depth, r.alpha, cfg.alpha_threshold,
                                           None if kept is None else kept[0].to(torch.float32),
                                           None if kept is None else kept[2]))
            src_normals.append(r.normal)
            del r, kept
        all_polar = [ref_polar] + [self._polar(v.name, dev) for v in src_views]
        polar = all(m is not None for m in all_polar)
        keep = consistency_filter(
            [depth] + src_depths, [result.normal] + src_normals, [view] + src_views,
            aolps=[m[0] for m in all_polar] if polar else None,
            dolps=[m[1] for m in all_polar] if polar else None,
            config=cfg.filters, reference=0,
        )
        del ref_polar, all_polar, src_depths, src_normals
        self._states.put(view.name, depth, result.normal, keep)
        self.calls += 1

        seeds = seed_mask(keep, result.depth, render.depth, render.alpha,
                          alpha_threshold=cfg.alpha_threshold,
                          relative_depth=seed_relative_depth(cfg.seed_depth_footprints, view.K),
                          normal=result.normal, K=view.K.to(dev), max_plane_deviation=cfg.seed_max_plane_deviation,
                          behind=cfg.seed_behind_surface)
        max_new = cfg.max_new_per_call if self.budget is None else min(cfg.max_new_per_call, self.budget - self.appended)
        new = seed_gaussians(
            result.depth, result.normal, view.image.to(dev), view.K, view.world_to_camera, seeds,
            stride=cfg.stride, max_new=max(0, max_new), initial_opacity=cfg.initial_opacity,
            thin_ratio=cfg.thin_scale_ratio, generator=self._generator,
        )
        self.appended += len(new)
        for key, count in (("estimated", mask.sum() if mask is not None else depth.numel()),
                           ("photometric", photometric_ok.sum()), ("kept", keep.sum()),
                           ("seeds", seeds.sum()), ("added", len(new))):
            self.stats[key] += int(count)
        return new if len(new) > 0 else None

    def _polar(self, name: str, device: torch.device) -> tuple[Tensor, Tensor] | None:
        """The view's (AoLP, DoLP) maps on ``device``, or None (no maps); the rest of its maps
        is not kept."""
        maps = self.maps.get(name)
        return None if maps is None else (maps.aolp.to(device), maps.dolp.to(device))

    def _device_generator(self, device: torch.device) -> torch.Generator:
        """A generator on ``device`` seeded from the CPU stream (so runs are reproducible)."""
        seed = int(torch.randint(0, 2**62, (1,), generator=self._generator))
        gen = torch.Generator(device=device)
        gen.manual_seed(seed)
        return gen

    def normal_target(self, view_name: str) -> tuple[Tensor, Tensor] | None:
        """The latest PatchMatch normals ``N_opt`` of a view and where they are valid.

        Returns:
            (normal (3, H, W) camera frame, float32; valid (1, H, W) bool), or None before the
            first run.
        """
        index = self._index.get(view_name)
        state = None if index is None else self._states.get(view_name, self.views[index].device)
        return None if state is None else (state[1].to(torch.float32), state[2])

    def state_dict(self) -> dict:
        return {
            "calls": self.calls,
            "appended": self.appended,
            "budget": self.budget,
            "generator": self._generator.get_state(),
            "depths": {k: self._states.get(k, "cpu")[0] for k in self._states.names()},
            "targets": {k: {"normal": n, "valid": m}
                        for k, (_, n, m) in ((k, self._states.get(k, "cpu")) for k in self._states.names())},
        }

    def load_state_dict(self, state: dict) -> None:
        self.calls = int(state["calls"])
        # checkpoints written before the budget existed hold neither: nothing counted, no budget set
        self.appended = int(state.get("appended", 0))
        self.budget = state.get("budget")
        self._generator.set_state(state["generator"])
        for name, depth in state["depths"].items():
            target = state["targets"][name]
            self._states.put(name, depth, target["normal"], target["valid"])
