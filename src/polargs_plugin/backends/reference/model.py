"""A minimal 3D Gaussian Splatting model: vanilla 3DGS parameters and Adam groups.

Raw parameters: one Adam group each, named like the parameters, in the layout of
:data:`polargs_plugin.kit.RAW_NAMES` (``means``, ``sh_dc``, ``sh_rest``, ``opacity_logits``,
``log_scales``, ``quats``; shapes and activations in :mod:`polargs_plugin.kit.append`).

Learning rates are vanilla 3DGS; the position rate decays exponentially and is multiplied by
the scene extent. Row edits (:meth:`GaussianModel.extend`, :meth:`GaussianModel.keep`,
:meth:`GaussianModel.append`) keep the Adam moments aligned with the rows: new rows get zero
moments, kept rows keep theirs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from polargs_plugin.backends.reference.binning import DEFAULT_TILE_SIZE
from polargs_plugin.backends.reference.projection import DEFAULT_EPS2D
from polargs_plugin.backends.reference.rasterizer import CompositeOrder, check_order
from polargs_plugin.config import CheckedConfig, at_least, satisfies, within
from polargs_plugin.geometry import quat_to_rotmat, rgb_to_sh
from polargs_plugin.kit.append import RAW_NAMES, edit_rows, logit, pad_rows, raw_from_new
from polargs_plugin.types import GaussianState, NewGaussians, RenderOut, View

__all__ = [
    "PARAM_NAMES",
    "LearningRates",
    "GaussianModel",
    "exponential_lr",
    "scene_extent",
    "init_points_from_masks",
    "init_points_in_box",
]

PARAM_NAMES = RAW_NAMES


def _decays_with_means_init(final: float, config: "LearningRates") -> bool:
    return final >= 0 and (final > 0) == (config.means_init > 0)


@dataclass
class LearningRates(CheckedConfig):
    """Vanilla 3DGS learning rates (graphdeco 3DGS's ``arguments/__init__.py``), one Adam group
    per raw parameter; every default is vanilla's.

    The position rate goes from ``means_init`` to ``means_final`` (log-linear) over
    ``means_max_steps`` and is multiplied by the scene extent (:func:`exponential_lr`).

    Attributes:
        means_init: position rate at step 0, per unit of scene extent; >= 0. Default 1.6e-4.
        means_final: position rate at ``means_max_steps``; > 0 while ``means_init`` is > 0, 0
            together with it (positions frozen). Default 1.6e-6.
        means_delay_mult: with ``means_delay_steps`` > 0, the rate starts at this fraction and
            ramps up to the decay's over those steps (a sine ramp); in [0, 1]. Default 0.01.
        means_delay_steps: length of that ramp, in iterations; >= 0 (0: no ramp). Default 0.
        means_max_steps: iterations of the decay (scaled by ``TrainConfig.schedule_scale``);
            >= 1. Default 30000.
        sh_dc: rate of the SH degree-0 coefficients; >= 0. Default 2.5e-3.
        sh_rest: rate of the higher SH coefficients; >= 0. Default 2.5e-3 / 20.
        opacity_logits: rate of the opacity logits; >= 0. Default 0.025.
        log_scales: rate of the log scales; >= 0. Default 5e-3.
        quats: rate of the rotation quaternions; >= 0. Default 1e-3.
    """

    means_init: float = field(default=1.6e-4, metadata=at_least(0))
    means_final: float = field(
        default=1.6e-6, metadata=satisfies(_decays_with_means_init, "> 0 while means_init is > 0 (0 only together with it)")
    )
    means_delay_mult: float = field(default=0.01, metadata=within(0, 1))
    means_delay_steps: int = field(default=0, metadata=at_least(0))
    means_max_steps: int = field(default=30_000, metadata=at_least(1))
    sh_dc: float = field(default=2.5e-3, metadata=at_least(0))
    sh_rest: float = field(default=2.5e-3 / 20, metadata=at_least(0))
    opacity_logits: float = field(default=0.025, metadata=at_least(0))
    log_scales: float = field(default=5e-3, metadata=at_least(0))
    quats: float = field(default=1e-3, metadata=at_least(0))


def exponential_lr(
    step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0, delay_mult: float = 1.0
) -> float:
    """Log-linear interpolation from ``lr_init`` (step 0) to ``lr_final`` (``max_steps``).

    With ``delay_steps > 0`` the rate is further scaled by a sine ramp from ``delay_mult`` to 1.
    """
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    delay = 1.0
    if delay_steps > 0:
        ramp = min(max(step / delay_steps, 0.0), 1.0)
        delay = delay_mult + (1.0 - delay_mult) * math.sin(0.5 * math.pi * ramp)
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


def scene_extent(views: list[View]) -> float:
    """Vanilla 3DGS scene radius: 1.1 x the largest camera distance from the camera centroid.

    Falls back to 1.0 for a single camera (no spread to measure).
    """
    centres = torch.stack([v.camera_center.double() for v in views])
    radius = float((centres - centres.mean(0)).norm(dim=1).max()) * 1.1
    return radius if radius > 0 else 1.0


def _knn_scale(points: Tensor) -> Tensor:
    """(N, 3) -> (N,) sqrt of the mean squared distance to the 3 nearest neighbours (vanilla init)."""
    n = points.shape[0]
    if n < 2:
        return torch.full((n,), 0.01, dtype=points.dtype, device=points.device)
    k = min(3, n - 1)
    dist, _ = cKDTree(points.detach().cpu().double().numpy()).query(
        points.detach().cpu().double().numpy(), k=k + 1
    )
    mean_sq = (dist[:, 1:] ** 2).mean(axis=1).clip(min=1e-14)
    return torch.from_numpy(np.sqrt(mean_sq)).to(points)


class GaussianModel(nn.Module):
    """Gaussians with vanilla 3DGS raw parameters and one Adam optimizer (one group per name).

    Args:
        params: raw tensors keyed by :data:`PARAM_NAMES` (shapes in the module docstring).
        sh_degree: maximum SH degree; ``sh_rest`` must have ``(sh_degree + 1) ** 2 - 1`` rows.
        extent: scene extent multiplying the position learning rate.
        lrs: learning rates.
        eps2d: the screen-space dilation (pixels^2) every render of these Gaussians uses
            (``rasterize``): the parameters are fitted to it, so it belongs to the model and is
            saved with it.
        order: the compositing order every render uses (``rasterize``'s ``order``), kept and
            saved with the model for the same reason. Default "center" (vanilla).
        tile_size: the tile edge in pixels of :meth:`render` (with ``order="ray"`` it sets how
            closely the order follows each pixel's ray; :meth:`render_output` follows it exactly);
            >= 1. Default 16 (vanilla).
    """

    def __init__(
        self, params: dict[str, Tensor], sh_degree: int, extent: float = 1.0, lrs: LearningRates | None = None,
        eps2d: float = DEFAULT_EPS2D, order: CompositeOrder = "center", tile_size: int = DEFAULT_TILE_SIZE,
    ):
        super().__init__()
        missing = set(PARAM_NAMES) - set(params)
        if missing:
            raise ValueError(f"GaussianModel: missing parameters {sorted(missing)}")
        n = params["means"].shape[0]
        expected = {
            "means": (n, 3),
            "sh_dc": (n, 1, 3),
            "sh_rest": (n, (sh_degree + 1) ** 2 - 1, 3),
            "opacity_logits": (n,),
            "log_scales": (n, 3),
            "quats": (n, 4),
        }
        for name, shape in expected.items():
            if tuple(params[name].shape) != shape:
                raise ValueError(f"GaussianModel: {name} has shape {tuple(params[name].shape)}, expected {shape}")
            setattr(self, name, nn.Parameter(params[name].detach().clone().float().contiguous()))
        self.max_sh_degree = int(sh_degree)
        self.active_sh_degree = 0
        self.extent = float(extent)
        if not eps2d >= 0.0:
            raise ValueError(f"GaussianModel: eps2d must be >= 0 (pixels^2), got {eps2d}")
        self.eps2d = float(eps2d)
        check_order(order, "GaussianModel: order")
        if int(tile_size) != tile_size or tile_size < 1:
            raise ValueError(f"GaussianModel: tile_size must be a whole number of pixels >= 1, got {tile_size}")
        self.order: CompositeOrder = order
        self.tile_size = int(tile_size)
        self.lrs = lrs or LearningRates()
        self.optimizer = torch.optim.Adam(
            [
                {"params": [getattr(self, name)], "lr": self._base_lr(name), "name": name}
                for name in PARAM_NAMES
            ],
            lr=0.0,
            eps=1e-15,
            fused=True,  # one kernel for all groups (CPU and CUDA): ~2.5x cheaper than the per-tensor loop
        )

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_points(
        cls,
        points: Tensor,
        colors: Tensor,
        *,
        sh_degree: int = 0,
        extent: float = 1.0,
        initial_opacity: float = 0.1,
        lrs: LearningRates | None = None,
        eps2d: float = DEFAULT_EPS2D,
        order: CompositeOrder = "center",
        tile_size: int = DEFAULT_TILE_SIZE,
    ) -> "GaussianModel":
        """Vanilla 3DGS initialisation from a point cloud.

        Isotropic scales from the 3 nearest neighbours, identity rotations, opacity
        ``initial_opacity``, SH DC from ``colors`` and zero higher bands.

        Args:
            points: (N, 3) world positions.
            colors: (N, 3) RGB in [0, 1].
        """
        points = torch.as_tensor(points, dtype=torch.float32)
        colors = torch.as_tensor(colors, dtype=torch.float32, device=points.device)
        if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
            raise ValueError(
                f"from_points: points {tuple(points.shape)} and colors {tuple(colors.shape)} must both be (N, 3)"
            )
        n = points.shape[0]
        quats = torch.zeros(n, 4, device=points.device)
        quats[:, 0] = 1.0
        params = {
            "means": points,
            "sh_dc": rgb_to_sh(colors.clamp(0, 1)).unsqueeze(1),
            "sh_rest": torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3, device=points.device),
            "opacity_logits": logit(torch.full((n,), float(initial_opacity), device=points.device)),
            "log_scales": torch.log(_knn_scale(points)).unsqueeze(1).repeat(1, 3),
            "quats": quats,
        }
        return cls(params, sh_degree=sh_degree, extent=extent, lrs=lrs, eps2d=eps2d, order=order, tile_size=tile_size)

    # ------------------------------------------------------------------ activations
    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:
        """(N, 3) positive scales."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def rotations(self) -> Tensor:
        """(N, 4) unit wxyz quaternions."""
        return torch.nn.functional.normalize(self.quats, dim=-1)

    @property
    def sh(self) -> Tensor:
        """(N, K, 3) SH coefficients up to the active degree, K = (active_sh_degree + 1) ** 2."""
        k = (self.active_sh_degree + 1) ** 2
        return torch.cat([self.sh_dc, self.sh_rest[:, : k - 1]], dim=1)

    def state(self) -> GaussianState:
        """Activated, autograd-connected view of the Gaussians for the hooks."""
        return GaussianState(means=self.means, quats=self.rotations, scales=self.scales, opacities=self.opacities)

    def render(self, view: View, background: Tensor | None = None, state: GaussianState | None = None,
               **kwargs) -> RenderOut:
        """Render ``view`` with the reference rasterizer at the model's ``eps2d``, ``order`` and
        ``tile_size`` (extra ``kwargs`` go to ``rasterize``).

        ``state``: this model's :meth:`state`, when the caller already has it (the trainer passes
        the one it hands to the hooks, so the activations are computed and differentiated once)."""
        from polargs_plugin.backends.reference.rasterizer import rasterize

        device = self.means.device
        state = self.state() if state is None else state
        return rasterize(
            state.means,
            state.quats,
            state.scales,
            state.opacities,
            self.sh,
            view.K.to(device=device, dtype=torch.float32),
            view.world_to_camera.to(device=device, dtype=torch.float32),
            view.width,
            view.height,
            background=background,
            **{"eps2d": self.eps2d, "order": self.order, "tile_size": self.tile_size, **kwargs},
        )

    def render_output(self, view: View, background: Tensor | None = None, **kwargs) -> RenderOut:
        """:meth:`render` for what a trained model is used for (meshes, evaluation, the report's
        pictures): in ray order with one-pixel tiles, where the order is exact per pixel (training's
        ``tile_size`` approximates it tile by tile, for speed); in centre order as :meth:`render`,
        whose order does not depend on the tiles."""
        if self.order == "ray":
            kwargs = {"tile_size": 1, **kwargs}
        return self.render(view, background, **kwargs)

    # ------------------------------------------------------------- learning rates
    def _base_lr(self, name: str) -> float:
        if name == "means":
            return self.means_lr(0)
        return float(getattr(self.lrs, name))

    def means_lr(self, step: int) -> float:
        """Position learning rate at ``step`` (scene extent included)."""
        lr = self.lrs
        return self.extent * exponential_lr(
            step, lr.means_init, lr.means_final, lr.means_max_steps, lr.means_delay_steps, lr.means_delay_mult
        )

    def update_learning_rate(self, step: int) -> float:
        """Set the position group's rate for ``step``; returns it."""
        value = self.means_lr(step)
        self._group("means")["lr"] = value
        return value

    def _group(self, name: str) -> dict:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                return group
        raise KeyError(name)

    # -------------------------------------------------------------------- row edits
    def _params(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def _edit_rows(
        self,
        param_fn: Callable[[str, Tensor], Tensor],
        moment_fn: Callable[[str, Tensor], Tensor],
        names: tuple[str, ...] = PARAM_NAMES,
    ) -> None:
        """Replace each named parameter by ``param_fn(name, old)`` and each Adam moment by
        ``moment_fn(name, old_moment)``; the step counter is kept (:func:`polargs_plugin.kit.edit_rows`)."""
        for name, param in edit_rows(self._params(), self.optimizer, param_fn, moment_fn, names).items():
            setattr(self, name, param)

    def extend(self, rows: dict[str, Tensor]) -> None:
        """Append raw rows (keyed by :data:`PARAM_NAMES`) with zero Adam moments."""
        m = rows["means"].shape[0]
        self._edit_rows(
            lambda name, old: torch.cat([old, rows[name].to(old)], dim=0),
            lambda name, mom: pad_rows(mom, m),
        )

    def keep(self, mask: Tensor) -> None:
        """Keep the rows where the (N,) bool ``mask`` is true, with their Adam moments."""
        if mask.shape != (self.num,) or mask.dtype != torch.bool:
            raise ValueError(f"keep: mask must be bool ({self.num},), got {mask.dtype} {tuple(mask.shape)}")
        self._edit_rows(lambda name, old: old[mask], lambda name, mom: mom[mask])

    def append(self, new: NewGaussians) -> None:
        """Append activated Gaussians (e.g. from ``hooks.densify``); Adam moments zero-padded."""
        self.extend(raw_from_new(new, self.sh_rest.shape[1], like=self.means))

    def reset_opacity(self, max_opacity: float) -> None:
        """Clamp opacities to at most ``max_opacity`` and zero their Adam moments (vanilla reset)."""
        cap = logit(torch.tensor(max_opacity, device=self.means.device))
        self._edit_rows(
            lambda name, old: torch.minimum(old, cap),
            lambda name, mom: torch.zeros_like(mom),
            names=("opacity_logits",),
        )

    def rotation_matrices(self) -> Tensor:
        """(N, 3, 3) rotation matrices of the Gaussians (no grad)."""
        return quat_to_rotmat(self.quats.detach())

    # ------------------------------------------------------------------ persistence
    def checkpoint(self) -> dict:
        """Parameters, optimizer state and settings as plain tensors and numbers."""
        return {
            "params": {name: getattr(self, name).detach().clone() for name in PARAM_NAMES},
            "optimizer": self.optimizer.state_dict(),
            "max_sh_degree": self.max_sh_degree,
            "active_sh_degree": self.active_sh_degree,
            "extent": self.extent,
            "eps2d": self.eps2d,
            "order": self.order,
            "tile_size": self.tile_size,
        }

    @classmethod
    def from_checkpoint(cls, data: dict, lrs: LearningRates | None = None, device: str | torch.device = "cpu") -> "GaussianModel":
        """Inverse of :meth:`checkpoint` (the optimizer state, its moments and rates included)."""
        params = {name: t.to(device) for name, t in data["params"].items()}
        # Checkpoints older than the eps2d / order entries were trained at vanilla's settings.
        model = cls(params, sh_degree=int(data["max_sh_degree"]), extent=float(data["extent"]), lrs=lrs,
                    eps2d=float(data.get("eps2d", DEFAULT_EPS2D)), order=str(data.get("order", "center")),  # type: ignore[arg-type]
                    tile_size=int(data.get("tile_size", DEFAULT_TILE_SIZE)))
        model.optimizer.load_state_dict(data["optimizer"])
        model.active_sh_degree = int(data["active_sh_degree"])
        return model


def _project(points: Tensor, view: View) -> tuple[Tensor, Tensor]:
    """(P, 3) world points -> (P, 2) pixel coordinates (+0.5 centres) and (P,) camera z."""
    w2c = view.world_to_camera.to(points)
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uvw = cam @ view.K.to(points).T
    return uvw[:, :2] / uvw[:, 2:].clamp_min(1e-12), z


def _lookat_box(views: list[View]) -> tuple[Tensor, Tensor]:
    """Centre (3,) and half size (scalar) of a cube around the cameras' common look-at region.

    The centre is the least-squares point closest to every optical axis; the half size is the
    half-width seen by the widest camera at its distance to the centre.
    """
    origins = torch.stack([v.camera_center.double().cpu() for v in views])
    axes = torch.stack([v.R.double().cpu()[2] for v in views])  # camera +z in world
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - axes[:, :, None] * axes[:, None, :]
    if len(views) > 1 and torch.linalg.matrix_rank(proj.sum(0)) == 3:
        centre = torch.linalg.solve(proj.sum(0), (proj @ origins[:, :, None]).sum(0)).squeeze(1)
    else:
        centre = origins[0] + axes[0] * 1.0
    half = 0.0
    for v, o in zip(views, origins):
        dist = float((centre - o).norm())
        k = v.K.double().cpu()
        half = max(half, dist * 0.5 * max(v.width / float(k[0, 0]), v.height / float(k[1, 1])))
    return centre, torch.tensor(half, dtype=torch.float64)


def init_points_in_box(views: list[View], n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """``n`` uniform random points (float32 (n, 3)) and grey colours (n, 3) in the look-at cube."""
    centre, half = _lookat_box(views)
    u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    points = centre + (2 * u - 1) * half
    return points.float(), torch.full((n, 3), 0.5)


def _inside_masks(points: Tensor, views: list[View]) -> Tensor:
    """(P,) bool: the point projects in front of every view, inside its image and its mask."""
    inside = torch.ones(points.shape[0], dtype=torch.bool)
    for v in views:
        uv, z = _project(points, v)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        ok = (z > 0) & (col >= 0) & (col < v.width) & (row >= 0) & (row < v.height)
        hit = torch.zeros_like(ok)
        hit[ok] = v.mask[0].cpu()[row[ok], col[ok]].bool()
        inside &= hit
    return inside


#: bisection steps that move a hull sample onto the hull's boundary (to voxel / 2^steps)
HULL_BISECTION_STEPS = 16


def init_points_from_masks(
    views: list[View], n: int, resolution: int = 64, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Sample ``n`` points on the surface of the visual hull carved by the views' masks.

    A ``resolution``^3 voxel grid over the cameras' look-at cube is carved: a voxel survives if its
    centre lies in front of every camera, inside every image and inside every mask. Each sample
    takes a random boundary voxel (a surviving voxel with a carved neighbour among its 26) and one
    of its carved neighbours, both jittered by the same offset inside their voxels, and bisects
    the segment between them (:data:`HULL_BISECTION_STEPS` times, with the same point test) onto
    the hull's boundary. Points inside the boundary voxels would sit half a voxel inside the
    surface on average, and a photometric training of a weakly textured object keeps that offset.
    Their colour is the mean of the training colour ``s0 / 2`` at their projections.

    Args:
        views: views with ``mask`` set (views without a mask do not carve).
        n: number of points.
        resolution: voxels per side.
        generator: random generator for the sampling.

    Returns:
        points (n, 3) float32 and colors (n, 3) float32 in [0, 1]. Without any mask, or when the
        carving leaves nothing, falls back to :func:`init_points_in_box`.
    """
    masked = [v for v in views if v.mask is not None]
    if not masked:
        return init_points_in_box(views, n, generator)
    centre, half = _lookat_box(views)
    step = 2 * half / resolution
    axis = torch.arange(resolution, dtype=torch.float64) * step - half + step / 2
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3) + centre
    occ = _inside_masks(grid, masked).reshape(resolution, resolution, resolution)
    if not bool(occ.any()):
        return init_points_in_box(views, n, generator)
    # carved[i, j, k] for every voxel and its 26 neighbours (the grid's outside counts as carved)
    carved = torch.nn.functional.pad(~occ, (1, 1, 1, 1, 1, 1), value=True)
    offsets = torch.tensor([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                            if (i, j, k) != (0, 0, 0)])
    inner = occ.nonzero()  # (M, 3) voxel indices
    neighbours = inner[:, None, :] + offsets + 1  # (M, 26, 3) indices into the padded grid
    open_sides = carved[neighbours[..., 0], neighbours[..., 1], neighbours[..., 2]]  # (M, 26)
    boundary = open_sides.any(dim=1)
    inner, open_sides = inner[boundary], open_sides[boundary]
    pick = torch.randint(0, inner.shape[0], (n,), generator=generator)
    side = torch.multinomial(open_sides[pick].double(), 1, generator=generator)[:, 0]
    jitter = (torch.rand(n, 3, generator=generator, dtype=torch.float64) - 0.5) * step
    start = centre - half + step / 2 + inner[pick] * step  # the picked voxels' centres
    outward = offsets[side].double() * step
    a, b = start + jitter, start + jitter + outward
    # the jitter may cross the boundary: those samples start from the voxel centres themselves
    valid = _inside_masks(a, masked) & ~_inside_masks(b, masked)
    a = torch.where(valid[:, None], a, start)
    b = torch.where(valid[:, None], b, start + outward)
    for _ in range(HULL_BISECTION_STEPS):
        mid = 0.5 * (a + b)
        inside = _inside_masks(mid, masked)[:, None]
        a, b = torch.where(inside, mid, a), torch.where(inside, b, mid)
    points = a  # the inside end: in every mask, within voxel / 2^steps of the boundary
    color_sum = torch.zeros(n, 3, dtype=torch.float64)
    color_count = torch.zeros(n, 1, dtype=torch.float64)
    for v in views:
        uv, z = _project(points, v)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        ok = (z > 0) & (col >= 0) & (col < v.width) & (row >= 0) & (row < v.height)
        image = v.image.double().cpu()
        if image.shape[0] == 1:
            image = image.expand(3, -1, -1)
        color_sum[ok] += image[:, row[ok], col[ok]].T
        color_count[ok] += 1
    colors = (color_sum / color_count.clamp_min(1)).clamp(0, 1)
    colors[color_count[:, 0] == 0] = 0.5
    return points.float(), colors.float()
