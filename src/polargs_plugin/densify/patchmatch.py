"""Polar-enhanced PatchMatch MVS for one reference view (PolarGS Dense).

Per-pixel state: camera-z depth, unit camera-frame normal (a 3D plane), photometric cost.

1. **Initial hypotheses** ``{(d, n), (d_prt, n), (d, n_aolp_i), (d_prt, n_aolp_i)}``, i = 1..4:
   ``d, n`` the rendered depth and normal, ``d_prt = d (1 + U(-delta, delta))``, ``n_aolp_i``
   the normal with the rendered zenith and azimuth ``phi_i`` in
   ``{phi - pi/2, phi, phi + pi/2, phi + pi}`` (AoLP ``phi``). Pixels without a rendered depth
   (holes) start from a random depth in the rendered range and a fronto-parallel normal.
2. **Iterations**: red-black checkerboard (pixel colour ``(u + v) mod 2``); each half-step updates
   one colour from the other. Candidates per pixel: for each of the four directions, the
   neighbour plane with the lowest current cost among ``propagation_distances`` (all odd, so
   always of the other colour), re-intersected with the pixel's ray; and three random
   refinements ``(d', n), (d, n'), (d', n')`` with a relative depth range and normal angle that
   halve every iteration. A pixel keeps the cheapest of its current plane and its candidates.
3. **Cost** ``S = S_c + lambda1 S_a + lambda2 S_nd``:

   - ``S_c``: bilateral NCC (ncc.py) against each source, averaged over the ``top_k_sources``
     best sources.
   - ``S_a = min_i omega exp(wrap(phi_i - azimuth(n))^2 / tau)`` as the paper's cost is usually written (docs/patchmatch.md), with
     ``omega = dolp_weight(rho, sigma)`` and the difference wrapped to (-pi, pi]. It is a
     *penalty* that grows with the angular distance from the nearest of the four AoLP azimuths:
     ``omega`` at agreement, ``omega e^(pi^2 / 16 tau)`` at the worst case (pi/4 from every
     candidate, the min bounds it). The constant floor ``omega`` does not change the argmin.
   - ``S_nd = 1 - n_dg . n`` with ``n_dg`` the normal of the surface through the current depth
     hypotheses of the four direct neighbours (central differences, facing the camera);
     0 where a neighbour is missing.

**Backends** (``PatchMatchConfig.ncc_backend``): ``"torch"`` is the reference (full-map candidate
tensors, vectorised ``grid_sample`` costs; CPU and CUDA); ``"numba"`` runs each half-step as one
fused parallel CPU kernel (numba_kernels.py) that builds, scores and selects the candidates per
pixel without full-map intermediates; ``"auto"`` picks numba on CPU. Both consume the same random
draws in the same order, so they give the same costs for the same hypotheses (to ~1e-5).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from polargs_plugin.config import PatchMatchConfig
from polargs_plugin.densify.homography import pixel_rays, relative_pose
from polargs_plugin.densify.ncc import (
    MAX_COST,
    MIN_VARIANCE,
    RefWindows,
    bilateral_ncc_cost,
    numba_available,
    reference_windows,
    window_offsets,
)
from polargs_plugin.geometry import ray_plane_depth, ray_plane_distance
from polargs_plugin.optics.azimuth import (
    azimuth_candidates,
    dolp_weight,
    normal_azimuth,
    normals_from_azimuth,
    zenith_from_normals,
)
from polargs_plugin.threads import numba_scheduling

__all__ = ["PatchMatchResult", "patchmatch", "azimuth_cost", "depth_gradient_normal"]


@dataclass
class PatchMatchResult:
    """PatchMatch output for the reference view (0 depth / normal outside the mask).

    Attributes:
        depth: (1, H, W) camera-z depth.
        normal: (3, H, W) unit camera-frame normal facing the camera.
        cost: (1, H, W) total cost S_c + lambda1 S_a + lambda2 S_nd (inf outside the mask).
        photometric_cost: (1, H, W) S_c in [0, 2] (2 outside the mask).
        evaluations: number of (pixel, hypothesis, source view) NCC evaluations: admissible
            hypotheses at pixels whose reference window has texture (elsewhere S_c = 2 unsampled).
    """

    depth: Tensor
    normal: Tensor
    cost: Tensor
    photometric_cost: Tensor
    evaluations: int


def _gray(image: Tensor) -> Tensor:
    return image.mean(-3)


def _shift(x: Tensor, dx: int, dy: int, fill: float) -> Tensor:
    """``out[..., y, x] = x[..., y + dy, x + dx]`` with ``fill`` outside the image."""
    h, w = x.shape[-2:]
    out = torch.full_like(x, fill)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[..., yd, xd] = x[..., ys, xs]
    return out


def depth_gradient_normal(depth: Tensor, rays: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Normal of the surface through the four direct neighbours' depths (central differences).

    Args:
        depth: (H, W) camera-z depth; rays: (3, H, W) ``K^-1 p~``; valid: (H, W) bool.

    Returns:
        normal: (3, H, W) unit, facing the camera; ok: (H, W) bool, all four neighbours valid.
    """
    points = depth * rays
    vf = valid.float()
    ok = torch.ones_like(valid)
    diffs = []
    for (ax, ay), (bx, by) in (((1, 0), (-1, 0)), ((0, 1), (0, -1))):
        diffs.append(_shift(points, ax, ay, 0.0) - _shift(points, bx, by, 0.0))
        ok = ok & (_shift(vf, ax, ay, 0.0) > 0) & (_shift(vf, bx, by, 0.0) > 0)
    # x right, y down, z forward: (dX/dv) x (dX/du) points towards the camera
    normal = F.normalize(torch.cross(diffs[1], diffs[0], dim=0), dim=0)
    return normal, ok


def azimuth_cost(
    normals: Tensor,
    aolp: Tensor,
    dolp: Tensor | None,
    *,
    tau: float,
    sigma: float,
    K: Tensor | None = None,
    model: str = "orthographic",
) -> Tensor:
    """``S_a = min_i omega exp(wrap(phi_i - azimuth(n))^2 / tau)`` (see module docstring).

    Args:
        normals: (M, 3, H, W) camera-frame normal hypotheses.
        aolp: (1, H, W) observed AoLP in [0, pi); dolp: (1, H, W) or None (omega = 1).
        tau, sigma: paper constants; K, model: the azimuth model (optics.azimuth).

    Returns:
        (M, H, W) penalty, >= omega.
    """
    alpha = normal_azimuth(normals, K=K, model=model)  # (M, 1, H, W)
    phis = azimuth_candidates(aolp)  # (4, H, W)
    diff = phis.unsqueeze(0) - alpha
    wrapped = torch.atan2(torch.sin(diff), torch.cos(diff))
    nearest = (wrapped**2).min(1).values
    omega = dolp_weight(dolp, sigma=sigma)[0] if dolp is not None else torch.ones_like(aolp[0])
    return omega * torch.exp(nearest / tau)


class _Problem:
    """Everything fixed during one PatchMatch run (cameras, reference windows, priors)."""

    def __init__(self, ref_image, ref_K, ref_w2c, src_images, src_K, src_w2c, aolp, dolp, cfg):
        dev = ref_image.device
        self.cfg = cfg
        self.h, self.w = ref_image.shape[-2:]
        K64 = ref_K.to(dev, torch.float64)
        self.K = K64.float()
        self.K_inv = torch.linalg.inv(K64).float()
        self.rays = pixel_rays(K64, self.h, self.w).float()  # (3, H, W)
        rot, trans = relative_pose(ref_w2c.to(dev, torch.float64), src_w2c.to(dev, torch.float64))
        Ks = src_K.to(dev, torch.float64)
        self.A = (Ks @ rot @ torch.linalg.inv(K64)).float()
        self.b = (Ks @ trans.unsqueeze(-1)).squeeze(-1).float()
        self.sources = _gray(src_images.float()).contiguous()
        self.offsets = window_offsets(cfg.window_radius, cfg.window_step, device=dev)
        self.gray = _gray(ref_image.float()).contiguous()
        v, u = torch.meshgrid(
            torch.arange(self.h, device=dev), torch.arange(self.w, device=dev), indexing="ij"
        )
        self.pixels = torch.stack([u, v], -1).reshape(-1, 2).float() + 0.5
        self.colour = ((u + v) % 2).reshape(-1)
        self.aolp, self.dolp = aolp, dolp
        self.top_k = max(1, min(cfg.top_k_sources, self.sources.shape[0]))

    @cached_property
    def ref(self) -> RefWindows:
        """Reference windows and statistics (the torch search's; the numba one has its own)."""
        return reference_windows(self.gray, self.offsets, self.cfg.sigma_spatial, self.cfg.sigma_color)

    def photometric(self, idx: Tensor, depth: Tensor, normal: Tensor) -> Tensor:
        """(P, M) S_c for hypotheses ``depth`` (P, M), ``normal`` (P, M, 3) at flat ``idx``."""
        rays = self.rays.reshape(3, -1).T[idx]  # (P, 3)
        d_plane = ray_plane_distance(depth, normal, rays[:, None, :])
        m = -torch.einsum("ij,pmi->pmj", self.K_inv, normal) / d_plane[..., None]
        cost = bilateral_ncc_cost(
            self.sources, self.A, self.b, self.pixels[idx], 1.0 / depth, m[..., :2].contiguous(),
            self.offsets, self.ref.values[idx], self.ref.weights[idx], self.ref.mean[idx],
            self.ref.var[idx], backend="torch",
            chunk_elements=self.cfg.chunk_elements,
        )
        return torch.topk(cost, self.top_k, dim=-1, largest=False).values.mean(-1)

    def prior(self, normals: Tensor, depth: Tensor, valid: Tensor) -> Tensor:
        """(M, H, W) lambda1 S_a + lambda2 S_nd of normal maps (M, 3, H, W) given current depth."""
        cfg = self.cfg
        out = normals.new_zeros((normals.shape[0], self.h, self.w))
        if cfg.lambda_aolp > 0 and self.aolp is not None:
            out = out + cfg.lambda_aolp * azimuth_cost(
                normals, self.aolp, self.dolp, tau=cfg.tau, sigma=cfg.sigma_dolp, K=self.K,
                model=cfg.azimuth_model,
            )
        if cfg.lambda_normal_depth > 0:
            n_dg, ok = depth_gradient_normal(depth, self.rays, valid)
            s_nd = (1.0 - (n_dg.unsqueeze(0) * normals).sum(1)) * ok
            out = out + cfg.lambda_normal_depth * s_nd
        return out

    def admissible(self, depth: Tensor, normal: Tensor, lo: float, hi: float) -> Tensor:
        """Hypotheses (M, H, W) / (M, 3, H, W) with depth in range and the plane facing the ray."""
        facing = (normal * self.rays.unsqueeze(0)).sum(1) < -1e-3
        return torch.isfinite(depth) & (depth >= lo) & (depth <= hi) & facing


_State = tuple[Tensor, Tensor, Tensor, Tensor]
"""The search state, updated in place: depth (H, W), normal (3, H, W), photometric cost (H, W),
total cost (H, W)."""


def _rand(shape, like: Tensor, gen) -> Tensor:
    return torch.rand(shape, device=like.device, generator=gen, dtype=like.dtype)


def patchmatch(
    ref_image: Tensor,
    ref_K: Tensor,
    ref_world_to_camera: Tensor,
    src_images: Tensor,
    src_K: Tensor,
    src_world_to_camera: Tensor,
    init_depth: Tensor,
    init_normal: Tensor,
    *,
    aolp: Tensor | None = None,
    dolp: Tensor | None = None,
    mask: Tensor | None = None,
    init_valid: Tensor | None = None,
    config: PatchMatchConfig | None = None,
    generator: torch.Generator | None = None,
) -> PatchMatchResult:
    """Polar-enhanced PatchMatch of one reference view against ``S`` source views.

    Args:
        ref_image: (C, H, W) reference colour (converted to grey internally).
        ref_K: (3, 3) intrinsics; ref_world_to_camera: (4, 4).
        src_images: (S, C, Hs, Ws) source colours, or their grey (C = 1): PatchMatch reads only the
            mean over C; src_K: (S, 3, 3); src_world_to_camera: (S, 4, 4).
        init_depth: (1, H, W) rendered camera-z depth (0 or non-finite = hole).
        init_normal: (3, H, W) rendered camera-frame normal.
        aolp: optional (1, H, W) observed AoLP in [0, pi) (adds the AoLP hypotheses and S_a).
        dolp: optional (1, H, W) DoLP for the weight omega.
        mask: optional (1, H, W) bool, pixels to estimate (default all).
        init_valid: optional (1, H, W) bool, where ``init_depth`` is trusted (default depth > 0).
        config: PatchMatchConfig (defaults if None).
        generator: torch random generator on the images' device (seeded from config if None).

    Returns:
        PatchMatchResult with (1, H, W) depth, (3, H, W) normal, costs and the evaluation count.
    """
    cfg = config or PatchMatchConfig()
    _check_search(src_images, cfg)
    dev = ref_image.device
    backend = _resolve_backend(cfg.ncc_backend, dev)
    if generator is None:
        generator = torch.Generator(device=dev)
        generator.manual_seed(cfg.seed)
    with torch.no_grad(), _search_threads(backend == "numba"):
        prob = _Problem(ref_image, ref_K, ref_world_to_camera, src_images, src_K,
                        src_world_to_camera, aolp, dolp, cfg)
        h, w = prob.h, prob.w
        active = mask[0].bool() if mask is not None else torch.ones(h, w, dtype=torch.bool, device=dev)
        d0, n0, lo, hi = _initial_plane(prob, init_depth, init_normal, init_valid, generator)
        groups = _initial_hypotheses(prob, d0, n0, aolp, generator)

        depth, normal = d0.clone(), n0.clone()
        photo = torch.full((h, w), MAX_COST, device=dev)
        total = torch.full((h, w), math.inf, device=dev)
        state = (depth, normal, photo, total)
        search = (_NumbaSearch if backend == "numba" else _TorchSearch)(prob, active, lo, hi)
        search.initial(state, groups)
        _iterate(search, state, cfg, generator)
        return _result(state, active, search.evaluations)


def _check_search(src_images: Tensor, cfg: PatchMatchConfig) -> None:
    """ValueError unless there is a source view and the propagation distances are odd."""
    if src_images.shape[0] == 0:
        raise ValueError("patchmatch needs at least one source view")
    if not cfg.propagation_distances or any(k < 1 or k % 2 == 0 for k in cfg.propagation_distances):
        # An even distance reads a pixel of the colour being updated: a data race between the
        # numba threads (results would depend on thread timing) and a different rule on torch.
        raise ValueError(f"propagation_distances must be odd and >= 1 (checkerboard), got {cfg.propagation_distances}")


def _initial_plane(
    prob: _Problem, init_depth: Tensor, init_normal: Tensor, init_valid: Tensor | None, generator
) -> tuple[Tensor, Tensor, float, float]:
    """(depth (H, W), normal (3, H, W), lo, hi): the rendered plane where it is trusted and faces
    the camera; elsewhere a random depth within the rendered range and a fronto-parallel normal.
    [lo, hi] = [0.5 x, 2 x] the rendered depth range bounds the search."""
    h, w = prob.h, prob.w
    d0 = init_depth[0].float()
    valid0 = torch.isfinite(d0) & (d0 > 0)
    if init_valid is not None:
        valid0 = valid0 & init_valid[0].bool()
    n0 = F.normalize(torch.nan_to_num(init_normal.float()), dim=0)
    fronto = -F.normalize(prob.rays, dim=0)
    n0 = torch.where(valid0 & ((n0 * prob.rays).sum(0) < -1e-3), n0, fronto)
    if valid0.any():
        lo_v, hi_v = d0[valid0].min().item(), d0[valid0].max().item()
    else:
        raise ValueError("patchmatch needs a rendered depth on at least one pixel")
    d0 = torch.where(valid0, d0, lo_v + (hi_v - lo_v) * _rand((h, w), d0, generator))
    return d0, n0, 0.5 * lo_v, 2.0 * hi_v


def _initial_hypotheses(
    prob: _Problem, d0: Tensor, n0: Tensor, aolp: Tensor | None, generator
) -> Iterator[tuple[Tensor, Tensor]]:
    """The initial hypotheses in groups of two, (2, H, W) depths and (2, 3, H, W) normals: the
    initial plane and a perturbed depth with the initial normal, then with each of the four AoLP
    normals when ``aolp`` is given (in that order, which breaks ties between equal costs).

    The groups are made one at a time, so that the search holds two hypotheses a pixel rather
    than ten (at 1224x1024 the ten take 200 MB). The perturbation is drawn here, before the search
    draws anything."""
    cfg = prob.cfg
    d_prt = d0 * (1 + cfg.depth_perturbation * (2 * _rand((prob.h, prob.w), d0, generator) - 1))
    depths = torch.stack([d0, d_prt])

    def groups() -> Iterator[tuple[Tensor, Tensor]]:
        yield depths, n0.expand(2, -1, -1, -1)
        if aolp is None:
            return
        zen = zenith_from_normals(n0, K=prob.K, model=cfg.azimuth_model)
        azimuths = azimuth_candidates(aolp.float())
        for i in range(azimuths.shape[-3]):
            normal = normals_from_azimuth(azimuths[..., i : i + 1, :, :], zen, K=prob.K, model=cfg.azimuth_model)
            yield depths, normal.expand(2, -1, -1, -1)

    return groups()


def _iterate(search: _TorchSearch | _NumbaSearch, state: _State, cfg: PatchMatchConfig, generator) -> None:
    """The red-black sweeps: per iteration, both checkerboard colours with a refinement range
    halved each iteration."""
    depth, device = state[0], state[2].device
    _, h, w = state[1].shape
    for it in range(cfg.iterations):
        rel = cfg.refine_depth_range * 0.5**it
        ang = math.radians(cfg.refine_normal_deg) * 0.5**it
        for colour in (0, 1):
            # the same draws in the same order for both backends
            uni = _rand((2, h, w), depth, generator)
            noise = torch.randn((2, 3, h, w), device=device, generator=generator)
            search.half_step(state, colour, rel, ang, uni, noise)


def _result(state: _State, active: Tensor, evaluations: int) -> PatchMatchResult:
    """The search state as a :class:`PatchMatchResult`, pixels outside ``active`` reset."""
    depth, normal, photo, total = state
    depth = torch.where(active, depth, torch.zeros_like(depth))
    normal = torch.where(active, normal, torch.zeros_like(normal))
    photo = torch.where(active, photo, torch.full_like(photo, MAX_COST))
    total = torch.where(active, total, torch.full_like(total, math.inf))
    return PatchMatchResult(depth[None], normal, total[None], photo[None], evaluations)


@contextmanager
def _search_threads(numba_search: bool):
    """For the numba search: its kernels on the thread policy's count (:func:`numba_scheduling`,
    taken while torch still has its own count) and torch single-threaded, since its work there is
    a few small map operations whose intra-op workers would only spin against numba's threads
    (measured: ~25 % more CPU time). Nothing changes for the torch search."""
    if not numba_search:
        yield
        return
    before = torch.get_num_threads()
    with numba_scheduling():
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(before)


def _resolve_backend(name: str, device: torch.device) -> str:
    if name == "auto":
        return "numba" if device.type == "cpu" and numba_available() else "torch"
    if name == "numba":
        if device.type != "cpu":
            raise ValueError("the numba PatchMatch backend runs on CPU tensors only")
        if not numba_available():
            raise ValueError("ncc_backend='numba' but numba is not installed")
        return name
    if name != "torch":
        raise ValueError(f"unknown NCC backend '{name}' (torch, numba, auto)")
    return name


class _TorchSearch:
    """Reference search: full-map candidate tensors, vectorised costs (CPU and CUDA)."""

    def __init__(self, prob: _Problem, active: Tensor, lo: float, hi: float):
        self.prob, self.active, self.lo, self.hi = prob, active, lo, hi
        self.evaluations = 0

    def initial(self, state, groups: Iterable[tuple[Tensor, Tensor]]) -> None:
        # all hypotheses in one evaluation: S_nd sees the initial depths for every one of them
        cand_d, cand_n = (torch.cat(parts) for parts in zip(*groups))
        self._update(state, self.active.reshape(-1), cand_d, cand_n, fresh=True)

    def half_step(self, state, colour: int, rel: float, ang: float, uni: Tensor, noise: Tensor) -> None:
        depth, normal = state[0], state[1]
        h, w = depth.shape
        sel = self.active.reshape(-1) & (self.prob.colour == colour)
        cand_d, cand_n = _propagation_candidates(self.prob, state, self.active, self.prob.cfg)
        d_ref = depth * (1 + rel * (2 * uni - 1))
        n_ref = F.normalize(normal.expand(2, 3, h, w) + noise * ang, dim=-3)
        cand_d = torch.cat([cand_d, d_ref[:1], depth[None], d_ref[1:]])
        cand_n = torch.cat([cand_n, normal[None], n_ref[:1], n_ref[1:]])
        self._update(state, sel, cand_d, cand_n, fresh=False)

    def _update(self, state, sel, cand_d, cand_n, fresh):
        """Evaluate candidates at the flat pixels ``sel`` and keep the cheapest plane in ``state``."""
        prob, active = self.prob, self.active
        depth, normal, photo, total = state
        idx = sel.nonzero().squeeze(-1)
        if idx.numel() == 0:
            return
        num_m = cand_d.shape[0]
        ok = prob.admissible(cand_d, cand_n, self.lo, self.hi).reshape(num_m, -1)[:, idx].T  # (P, M)
        textured = prob.ref.var[idx] >= MIN_VARIANCE
        self.evaluations += int((ok & textured[:, None]).sum()) * prob.sources.shape[0]
        d_flat = cand_d.reshape(num_m, -1)[:, idx].T
        n_flat = cand_n.reshape(num_m, 3, -1)[:, :, idx].permute(2, 0, 1)  # (P, M, 3)
        safe_d = torch.where(ok, d_flat, torch.ones_like(d_flat))
        safe_n = torch.where(ok[..., None], n_flat, -prob.rays.reshape(3, -1).T[idx][:, None, :])
        c_photo = prob.photometric(idx, safe_d, safe_n)
        prior = prob.prior(cand_n, depth, active).reshape(num_m, -1)[:, idx].T
        c_total = torch.where(ok, c_photo + prior, torch.full_like(c_photo, math.inf))
        if not fresh:
            cur_prior = prob.prior(normal[None], depth, active).reshape(-1)[idx]
            cur = photo.reshape(-1)[idx] + cur_prior
            c_total = torch.cat([cur[:, None], c_total], 1)
            c_photo = torch.cat([photo.reshape(-1)[idx][:, None], c_photo], 1)
            d_flat = torch.cat([depth.reshape(-1)[idx][:, None], d_flat], 1)
            n_flat = torch.cat([normal.reshape(3, -1)[:, idx].T[:, None], n_flat], 1)
        best = c_total.argmin(1)
        rows = torch.arange(idx.numel(), device=idx.device)
        keep = torch.isfinite(c_total[rows, best])
        idx, best, rows = idx[keep], best[keep], rows[keep]
        depth.view(-1)[idx] = d_flat[rows, best]
        normal.view(3, -1)[:, idx] = n_flat[rows, best].T
        photo.view(-1)[idx] = c_photo[rows, best]
        total.view(-1)[idx] = c_total[rows, best]


def _f32(t: Tensor):
    return t.detach().to(torch.float32).contiguous().numpy()


def _f64(t: Tensor):
    return t.detach().to(torch.float64).contiguous().numpy()


class _NumbaSearch:
    """Fast CPU search: one fused numba kernel per half-step (numba_kernels.py), same numbers.

    The state tensors are updated in place through numpy views of their memory.
    """

    def __init__(self, prob: _Problem, active: Tensor, lo: float, hi: float):
        from polargs_plugin.densify import numba_kernels

        cfg = prob.cfg
        if cfg.azimuth_model not in ("orthographic", "perspective"):
            raise ValueError(f"unknown azimuth model '{cfg.azimuth_model}' (orthographic, perspective)")
        self.kernels = numba_kernels
        self.evaluations = 0
        sigma_s = cfg.sigma_spatial if cfg.sigma_spatial > 0 else float(cfg.window_radius)
        use_aolp = cfg.lambda_aolp > 0 and prob.aolp is not None
        if use_aolp:
            phi = prob.aolp[0]
            omega = (dolp_weight(prob.dolp, sigma=cfg.sigma_dolp)[0] if prob.dolp is not None
                     else torch.ones_like(phi))
        else:
            phi = omega = torch.zeros(prob.h, prob.w)
        self.common = dict(
            src=_f32(F.pad(prob.sources, (2, 2, 2, 2))), A=_f64(prob.A), b=_f64(prob.b),
            kinv=_f64(prob.K_inv), rays=_f32(prob.rays), radius=cfg.window_radius, step=cfg.window_step,
            top_k=prob.top_k, gray=_f32(prob.gray), sigma_spatial=sigma_s, sigma_color=cfg.sigma_color,
            phi=_f32(phi), omega=_f32(omega),
            params=np.array([cfg.lambda_aolp if use_aolp else 0.0, cfg.tau, max(cfg.lambda_normal_depth, 0.0),
                             float(cfg.azimuth_model == "perspective"), lo, hi]),
            active=active.contiguous().numpy(),
        )
        flat = active.reshape(-1)
        self.idx = [(flat & (prob.colour == c)).nonzero().squeeze(-1).numpy() for c in (0, 1)]
        self.all = flat.nonzero().squeeze(-1).numpy()
        self.dists = np.asarray(cfg.propagation_distances, dtype=np.int64)

    def initial(self, state, groups: Iterable[tuple[Tensor, Tensor]]) -> None:
        arrays = [t.numpy() for t in state]
        outs = [a.copy() for a in arrays]  # neighbours' S_nd must see the old depths
        # group after group, each kept where it beats the best so far: the same planes as scoring
        # all hypotheses at once, with two of them a pixel in memory
        best_total = np.full(arrays[0].shape, np.inf)
        for cand_d, cand_n in groups:
            self.evaluations += int(self.kernels.init_kernel(
                self.all, _f32(cand_d), _f32(cand_n), **self.common, depth=arrays[0], out_depth=outs[0],
                out_normal=outs[1], out_photo=outs[2], out_total=outs[3], best_total=best_total,
            ))
        for t, o in zip(state, outs):
            t.copy_(torch.from_numpy(o))

    def half_step(self, state, colour: int, rel: float, ang: float, uni: Tensor, noise: Tensor) -> None:
        depth, normal, photo, total = (t.numpy() for t in state)
        self.evaluations += int(self.kernels.half_step_kernel(
            self.idx[colour], **self.common, dists=self.dists, rel=float(rel), ang=float(ang),
            uni=_f32(uni), noise=_f32(noise), depth=depth, normal=normal, photo=photo, total=total,
        ))


def _propagation_candidates(prob: _Problem, state, active: Tensor, cfg: PatchMatchConfig):
    """Per direction, the cheapest neighbour plane among the distances, re-intersected (4 planes)."""
    depth, normal, _, total = state
    h, w = prob.h, prob.w
    rays_hw = prob.rays.permute(1, 2, 0)
    d_plane = ray_plane_distance(depth, normal.permute(1, 2, 0), rays_hw)
    cost = torch.where(active, total, torch.full_like(total, math.inf))
    r = max(cfg.propagation_distances)
    # one padded copy; every neighbour offset is then a view (no per-offset allocation)
    cost_p = F.pad(cost[None, None], (r,) * 4, value=math.inf)[0, 0]
    plane_p = F.pad(torch.cat([normal, d_plane[None]])[None], (r,) * 4)[0]
    depths, normals = [], []
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        win = [(r + k * dy, r + k * dx) for k in cfg.propagation_distances]
        costs = torch.stack([cost_p[y : y + h, x : x + w] for y, x in win])
        best, pick = costs.min(0, keepdim=True)
        planes = torch.stack([plane_p[:, y : y + h, x : x + w] for y, x in win])  # (K, 4, H, W)
        plane = planes.gather(0, pick[:, None].expand(1, 4, -1, -1))[0]
        d_p = ray_plane_depth(plane[3], plane[:3].permute(1, 2, 0), rays_hw)
        depths.append(torch.where(torch.isfinite(best[0]), d_p, torch.full_like(d_p, math.nan)))
        normals.append(plane[:3])
    return torch.stack(depths), torch.stack(normals)
