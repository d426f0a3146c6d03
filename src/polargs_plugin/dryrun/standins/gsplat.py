"""CPU stand-ins for the parts of gsplat (nerfstudio-project/gsplat 1.5.x and main) that call its
CUDA kernels on the path of ``examples/simple_trainer.py``.

- :func:`rasterization`: ``gsplat.rasterization`` (``gsplat.rendering.rasterization``) on the
  reference backend (:mod:`polargs_plugin.dryrun.splat`), unpacked, pinhole cameras: colours
  ``[C, H, W, D]`` with the background, alphas ``[C, H, W, 1]`` and the ``meta`` dict the
  strategies and the trainer read (``means2d`` ``[C, N, 2]`` in pixels whose ``.grad`` is
  dL/d(projected mean), ``.absgrad`` with ``absgrad=True``; ``radii`` ``[C, N, 2]`` int32;
  ``depths``, ``conics``, ``opacities``, ``width``, ``height``, ``n_cameras``, ``tile_size``, ...).
  SH colours as gsplat evaluates them (``clamp_min(SH + 0.5, 0)`` towards each mean);
  ``render_mode`` RGB, D, ED, RGB+D, RGB+ED; ``rasterize_mode="antialiased"`` (the
  Mip-Splatting opacity factor).
- :func:`compute_relocation` and :func:`quat_scale_to_covar_preci`: what ``MCMCStrategy``'s ops
  call (the relocation formula of the MCMC paper, Eq. 9; the covariance from gsplat's own torch
  reference implementation).
- :func:`single_process_cli`: ``gsplat.distributed.cli`` on one device (``fn(0, 0, 1, args)``),
  without its assertion that CUDA is available.

Approximations (documented in docs/adapters/dryrun.md): the footprint, depth sorting and
compositing are the reference backend's (per-pixel, front-to-back, alpha clamped at 0.99),
not gsplat's tile kernels; the radii follow gsplat's formula (3.33 sigma per axis of the dilated
screen covariance) but which Gaussians reach a pixel is decided by the reference backend's
opacity-aware extents. Not supported (a clear error): ``packed=True``, ``sparse_grad``,
``distributed``, camera models other than pinhole, ``with_ut`` / ``with_eval3d``, lens
distortion coefficients, batch dimensions in front of N.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

from polargs_plugin.dryrun.splat import Projected, composite_splats, project_splats
from polargs_plugin.geometry import eval_sh

__all__ = ["rasterization", "gsplat_radii", "compute_relocation", "quat_scale_to_covar_preci", "single_process_cli"]

RADIUS_SIGMAS = 3.33
"""gsplat's screen radius in standard deviations of the dilated screen covariance, per axis."""

_NEUTRAL: Dict[str, Any] = {
    "sparse_grad": False, "distributed": False, "with_ut": False, "with_eval3d": False, "segmented": False,
    "radius_clip": 0.0, "covars": None, "radial_coeffs": None, "tangential_coeffs": None,
    "thin_prism_coeffs": None, "ftheta_coeffs": None, "rolling_shutter": None, "viewmats_rs": None,
    "channel_chunk": None, "batch_per_iter": None,
}
"""Arguments of gsplat's ``rasterization`` the stand-in accepts only at these values (or, for
``channel_chunk`` / ``batch_per_iter``, any value: they only split the work)."""

_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def _refuse_unsupported(packed: bool, camera_model: Any, options: Dict[str, Any]) -> None:
    if packed:
        raise NotImplementedError("the CPU stand-in of gsplat.rasterization renders unpacked: pass packed=False "
                                  "(simple_trainer.py: leave --packed off)")
    if str(getattr(camera_model, "value", camera_model)).split(".")[-1].lower() != "pinhole":
        raise NotImplementedError(f"the CPU stand-in of gsplat.rasterization has pinhole cameras only, not {camera_model}")
    for name, value in options.items():
        neutral = _NEUTRAL.get(name, None)
        if name in ("channel_chunk", "batch_per_iter") or value is None or value is False:
            continue
        if neutral is not None and value == neutral:
            continue
        raise NotImplementedError(f"the CPU stand-in of gsplat.rasterization does not support {name}={value!r}")


@torch.no_grad()
def gsplat_radii(projected: Projected, width: int, height: int) -> Tensor:
    """(N, 2) int32 radii as gsplat's projection computes them: ceil(3.33 sigma) of the dilated
    screen covariance along x and y, 0 when culled (outside the near/far range) or when the box
    they span misses the image."""
    conics = projected.proj.conics
    det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
    var_x, var_y = conics[:, 2] / det, conics[:, 0] / det
    radius = torch.stack([torch.ceil(RADIUS_SIGMAS * torch.sqrt(var_x)), torch.ceil(RADIUS_SIGMAS * torch.sqrt(var_y))], -1)
    u, v = projected.proj.means2d[:, 0], projected.proj.means2d[:, 1]
    inside = (u + radius[:, 0] > 0) & (u - radius[:, 0] < width) & (v + radius[:, 1] > 0) & (v - radius[:, 1] < height)
    keep = projected.in_range & inside & torch.isfinite(radius).all(-1) & (det > 0)
    return torch.where(keep[:, None], radius, torch.zeros_like(radius)).to(torch.int32)


def _camera_colors(colors: Tensor, camera: int, num_cameras: int, num_gaussians: int, sh_degree: Optional[int],
                   means: Tensor, viewmat: Tensor) -> Tensor:
    """(N, D) colours of one camera: post-activation values as given (``[N, D]`` or
    ``[C, N, D]``), or SH coefficients (``[N, K, 3]`` or ``[C, N, K, 3]``) evaluated as gsplat does."""
    per_camera = colors.dim() == (3 if sh_degree is None else 4)
    if per_camera and colors.shape[0] != num_cameras:
        raise ValueError(f"colors {tuple(colors.shape)} do not match {num_cameras} cameras")
    own = colors[camera] if per_camera else colors
    if own.shape[0] != num_gaussians:
        raise ValueError(f"colors {tuple(colors.shape)} do not match {num_gaussians} Gaussians")
    if sh_degree is None:
        return own
    bands = (int(sh_degree) + 1) ** 2
    if own.dim() != 3 or own.shape[-1] != 3 or own.shape[1] < bands:
        raise ValueError(f"SH colours must be [N, K >= {bands}, 3], got {tuple(own.shape)}")
    campos = torch.linalg.inv(viewmat)[:3, 3]
    return eval_sh(own[:, :bands].to(means), means - campos)


class _AbsGradSink:
    """Collects each camera's absolute screen gradient into ``means2d.absgrad`` ([C, N, 2], pixels)."""

    def __init__(self, means2d: Tensor) -> None:
        self.means2d = means2d
        self.absgrad = torch.zeros_like(means2d, requires_grad=False)

    def target(self, camera: int, factors: Tensor) -> Tensor:
        """A zero (N, 2) tensor for :func:`composite_splats`'s ``screen_abs`` of camera ``camera``;
        its gradient (NDC units) lands in ``means2d.absgrad[camera]`` in pixels."""
        sink = torch.zeros(self.means2d.shape[1:], dtype=self.means2d.dtype, device=self.means2d.device,
                           requires_grad=True)

        def collect(grad: Tensor) -> None:
            self.absgrad[camera] += grad / factors
            self.means2d.absgrad = self.absgrad

        sink.register_hook(collect)
        return sink


def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: Optional[int] = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    camera_model: Any = "pinhole",
    **options: Any,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """gsplat's ``rasterization`` on the CPU (module docstring): ``(render_colors [C, H, W, D],
    render_alphas [C, H, W, 1], meta)``.

    Raises:
        NotImplementedError: an option the stand-in does not render (module docstring).
        ValueError: shapes that do not match, an unknown ``render_mode``.
    """
    _refuse_unsupported(packed, camera_model, options)
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    tile_size = tile_size or 16  # gsplat main's default is None (its own choice); 16 is 1.5's
    if render_mode not in _RENDER_MODES:
        raise ValueError(f"render_mode must be one of {', '.join(_RENDER_MODES)}, got {render_mode!r}")
    if means.dim() != 2 or viewmats.dim() != 3 or Ks.dim() != 3:
        raise NotImplementedError("the CPU stand-in of gsplat.rasterization takes means [N, 3], viewmats [C, 4, 4], "
                                  "Ks [C, 3, 3] (no batch dimensions)")
    num_cameras, num_gaussians = viewmats.shape[0], means.shape[0]
    projected = [
        project_splats(means, quats, scales, opacities.reshape(-1), Ks[c], viewmats[c], width, height, eps2d=eps2d,
                       compensate=rasterize_mode == "antialiased", near=near_plane, far=far_plane)
        for c in range(num_cameras)
    ]
    # meta["means2d"] must lie upstream of every pixel for its .grad (the strategies read it)
    means2d = torch.stack([p.proj.means2d for p in projected])
    sink = _AbsGradSink(means2d) if absgrad else None
    images, alphas = [], []
    for c, p in enumerate(projected):
        p.proj = p.proj._replace(means2d=means2d[c])
        depth = p.proj.depths[:, None]
        rgb = _camera_colors(colors, c, num_cameras, num_gaussians, sh_degree, means, viewmats[c])
        features = {"RGB": rgb, "D": depth, "ED": depth}.get(render_mode, torch.cat([rgb, depth], -1) if "+" in render_mode else rgb)
        out = composite_splats(p, features, width, height, screen_abs=None if sink is None else sink.target(c, p.factors),
                               tile_size=tile_size)
        image = out.features
        if backgrounds is not None:
            background = backgrounds[c].to(image)
            if render_mode in ("D", "ED"):
                background = torch.zeros_like(background[:1])
            elif render_mode != "RGB":
                background = torch.cat([background, background.new_zeros(1)])
            image = image + (1.0 - out.alpha) * background.reshape(-1, 1, 1)
        if render_mode.endswith("ED"):
            image = torch.cat([image[:-1], image[-1:] / out.alpha.clamp_min(1e-10)])
        images.append(image.permute(1, 2, 0))
        alphas.append(out.alpha.permute(1, 2, 0))
    meta = {
        "camera_ids": None, "gaussian_ids": None, "batch_ids": None,
        "radii": torch.stack([gsplat_radii(p, width, height) for p in projected]),
        "means2d": means2d,
        "depths": torch.stack([p.proj.depths for p in projected]),
        "conics": torch.stack([p.proj.conics for p in projected]),
        "opacities": torch.stack([p.opacities for p in projected]),
        "width": width, "height": height, "tile_size": tile_size,
        "tile_width": math.ceil(width / float(tile_size)), "tile_height": math.ceil(height / float(tile_size)),
        "n_cameras": num_cameras, "n_batches": 1,
    }
    return torch.stack(images), torch.stack(alphas), meta


def quat_scale_to_covar_preci(quats: Tensor, scales: Tensor, compute_covar: bool = True, compute_preci: bool = True,
                              triu: bool = False) -> Tuple[Optional[Tensor], Optional[Tensor]]:
    """gsplat's ``quat_scale_to_covar_preci`` by gsplat's own torch reference implementation
    (``gsplat.cuda._torch_impl``) of the installed gsplat."""
    from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

    return _quat_scale_to_covar_preci(quats, scales, compute_covar, compute_preci, triu)


def compute_relocation(opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor,
                       min_opacity: Optional[float] = None) -> Tuple[Tensor, Tensor]:
    """gsplat's ``compute_relocation`` (MCMC paper, Eq. 9): a Gaussian sampled n times (``ratios``
    clamped to [1, n_max], truncated) becomes n Gaussians of opacity o' = 1 - (1 - o)^(1/n) (gsplat
    main: clamped to [``min_opacity``, 1 - 2^-23]) and scale o / (sum_{i=1..n} sum_{k<i} C(i-1, k)
    (-1)^k o'^(k+1) / sqrt(k+1)) times the old one."""
    n_max = binoms.shape[0]
    n = ratios.clamp(1, n_max).int().to(opacities.dtype)
    new_opacities = 1.0 - torch.pow(1.0 - opacities, 1.0 / n)
    if min_opacity is not None:
        new_opacities = new_opacities.clamp(min_opacity, 1.0 - torch.finfo(torch.float32).eps)
    denom = torch.zeros_like(opacities)
    for i in range(1, n_max + 1):
        for k in range(i):
            term = binoms[i - 1, k] * (-1.0) ** k / math.sqrt(k + 1) * new_opacities ** (k + 1)
            denom = denom + torch.where(n >= i, term, torch.zeros_like(term))
    return new_opacities, (opacities / denom)[:, None] * scales


def single_process_cli(fn: Callable[..., Any], args: Any, verbose: bool = False) -> Any:
    """``gsplat.distributed.cli`` on one device: ``fn(local_rank=0, world_rank=0, world_size=1, args)``."""
    return fn(0, 0, 1, args)
