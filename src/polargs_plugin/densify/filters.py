"""Multi-view geometric and polarimetric consistency of depth/normal maps (PolarGS Dense filter).

Geometric test (COLMAP / ACMM style forward-backward check) of a reference pixel ``p`` with
depth ``d`` against a source view ``j``: back-project ``p``, project into ``j`` (``p_j``), read
``j``'s depth there (bilinear, only between pixels that all have a depth), back-project that
point and project it into the reference (``p'`` with depth ``d'``). The pixel is consistent with ``j`` when
``|p' - p| <= max_reprojection_px`` and ``|d' - d| / d <= max_relative_depth``; it passes when
at least ``min_consistent_views`` sources agree.

Polarimetric residual (our definition; the paper names it without a formula): rotate the
reference normal into each consistent source camera, predict its diffuse AoLP there
(optics.azimuth.aolp_from_normals) and compare with the AoLP observed at ``p_j``:
``r_j = |sin 2 (phi_pred - phi_obs)|`` in [0, 1], zero for agreement modulo pi/2 (so diffuse and
specular explanations both pass: the pi/2 ambiguity). Each residual is scaled by the confidence
``w_j = clip(rho_j / polar_dolp_reference, 0, 1)`` because AoLP is noise where DoLP is low, and
averaged over the ``k`` consistent sources: ``R = sum_j w_j r_j / k``. The pixel fails when
``R > max_polar_residual`` (0.3, about 8.7 degrees at full confidence). Dividing by ``k`` rather
than ``sum_j w_j`` matters: the latter renormalises the weights, so a pixel seen only at low DoLP
(e.g. a diffuse surface facing the camera, AoLP noise of tens of degrees) would be judged on that
noise at full strength; here such a pixel can only be rejected in proportion to its signal, and
one with no polarization signal is not judged at all.

Incidence test (``max_incidence_deg``): a view that sees a surface edge-on (or from behind) gives
no evidence about it: PatchMatch's window is stretched several pixels along the surface, and a
rendered depth that agrees with a wrong estimate there agrees by accident. With the test, a
source counts as consistent only when it sees the reference pixel's point, with its normal, from
the front at an incidence angle below the threshold, and the reference pixel itself is kept only
when the reference sees it so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from polargs_plugin.config import FilterConfig
from polargs_plugin.densify.homography import pixel_grid, pixel_rays
from polargs_plugin.optics.azimuth import aolp_from_normals
from polargs_plugin.types import View

__all__ = ["reprojection_check", "polar_residual", "incidence_cosine", "consistency_filter"]


def _sample(image: Tensor, pix: Tensor, mode: str = "nearest") -> Tensor:
    """Sample (C, Hs, Ws) at pixel coordinates pix (2, H, W) (centres at +0.5), 0 outside."""
    h, w = image.shape[-2:]
    grid = torch.stack([pix[0] * (2.0 / w) - 1.0, pix[1] * (2.0 / h) - 1.0], -1)[None]
    return F.grid_sample(image[None], grid, mode=mode, padding_mode="zeros", align_corners=False)[0]


def _sample_depth(depth: Tensor, pix: Tensor) -> Tensor:
    """Bilinear depth where all four taps have a depth (0 elsewhere): no mixing with holes."""
    both = _sample(torch.cat([depth, (depth > 0).float()]), pix, mode="bilinear")
    return torch.where(both[1:] > 1 - 1e-4, both[:1], torch.zeros_like(both[:1]))


def _project(points: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """(3, H, W) camera points -> (2, H, W) pixel coordinates and (H, W) z."""
    proj = torch.einsum("ij,jhw->ihw", K, points)
    z = proj[2]
    return proj[:2] / z.clamp_min(1e-12), points[2]


def reprojection_check(
    depth: Tensor, K: Tensor, world_to_camera: Tensor,
    src_depth: Tensor, src_K: Tensor, src_world_to_camera: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Forward-backward reprojection of a reference depth map through one source depth map.

    Args:
        depth: (1, H, W) reference camera-z depth (<= 0: none); K (3, 3); world_to_camera (4, 4).
        src_depth: (1, Hs, Ws) source depth; src_K (3, 3); src_world_to_camera (4, 4).

    Returns:
        reproj_px: (1, H, W) pixel distance |p' - p|; rel_depth: (1, H, W) |d' - d| / d;
        valid: (1, H, W) bool, both depths exist and the point projects in front into the source;
        src_pixels: (2, H, W) source pixel coordinates of each reference pixel.
    """
    dt = torch.float32
    K, w2c = K.to(depth.device, dt), world_to_camera.to(depth.device, dt)
    sK, s_w2c = src_K.to(depth.device, dt), src_world_to_camera.to(depth.device, dt)
    h, w = depth.shape[-2:]
    rays = pixel_rays(K, h, w)
    x_ref = depth[0].float() * rays
    rel_R = s_w2c[:3, :3] @ w2c[:3, :3].T
    rel_t = s_w2c[:3, 3] - rel_R @ w2c[:3, 3]
    x_src = torch.einsum("ij,jhw->ihw", rel_R, x_ref) + rel_t[:, None, None]
    pix_src, z_src = _project(x_src, sK)
    d_src = _sample_depth(src_depth.float(), pix_src)[0]
    hs, ws = src_depth.shape[-2:]
    inside = (pix_src[0] >= 0) & (pix_src[0] < ws) & (pix_src[1] >= 0) & (pix_src[1] < hs)
    valid = (depth[0] > 0) & (z_src > 0) & inside & (d_src > 0)
    ray_src = torch.einsum("ij,jhw->ihw", torch.linalg.inv(sK), torch.cat([pix_src, torch.ones_like(d_src)[None]]))
    back_src = d_src * ray_src
    back_ref = torch.einsum("ji,jhw->ihw", rel_R, back_src - rel_t[:, None, None])
    pix_back, z_back = _project(back_ref, K)
    grid = pixel_grid(h, w, device=depth.device)[:2]
    reproj = torch.linalg.vector_norm(pix_back - grid, dim=0)
    rel = (z_back - depth[0]).abs() / depth[0].clamp_min(1e-12)
    inf = torch.full_like(reproj, float("inf"))
    return (torch.where(valid, reproj, inf)[None], torch.where(valid, rel, inf)[None], valid[None], pix_src)


def polar_residual(
    normal: Tensor, world_to_camera: Tensor, src_world_to_camera: Tensor, src_K: Tensor,
    src_pixels: Tensor, src_aolp: Tensor, src_dolp: Tensor | None, *,
    dolp_reference: float = 0.1, model: str = "orthographic",
) -> tuple[Tensor, Tensor]:
    """Per-pixel AoLP residual of the reference normals seen from one source view.

    Args:
        normal: (3, H, W) reference camera-frame normals.
        world_to_camera, src_world_to_camera: (4, 4) cameras; src_K: (3, 3).
        src_pixels: (2, H, W) where each reference pixel lands in the source
            (:func:`reprojection_check`).
        src_aolp: (1, Hs, Ws) observed AoLP in [0, pi); src_dolp: (1, Hs, Ws) or None (weight 1).
        dolp_reference: DoLP at which the weight saturates to 1.
        model: azimuth model; "perspective" evaluates the ray at the reference pixel grid
            (an approximation; the orthographic model is exact for this definition).

    Returns:
        residual: (1, H, W) ``|sin 2 (phi_pred - phi_obs)|``; weight: (1, H, W) in [0, 1].
    """
    dev = normal.device
    rel_R = (src_world_to_camera[:3, :3] @ world_to_camera[:3, :3].T).to(dev, torch.float32)
    n_src = torch.einsum("ij,jhw->ihw", rel_R, normal.float())
    predicted = aolp_from_normals(n_src, "diffuse", K=src_K.to(dev, torch.float32), model=model)
    observed = _sample(src_aolp.float(), src_pixels)
    residual = torch.sin(2 * (predicted - observed)).abs()
    if src_dolp is None:
        weight = torch.ones_like(residual)
    else:
        weight = (_sample(src_dolp.float(), src_pixels) / dolp_reference).clamp(0, 1)
    return residual, weight


def incidence_cosine(depth: Tensor, normal: Tensor, K: Tensor, world_to_camera: Tensor,
                     target_world_to_camera: Tensor) -> Tensor:
    """(1, H, W) cosine of the incidence angle at which a target camera sees each pixel's surface.

    The pixel's point (``depth`` along its ray) and its camera-frame ``normal`` (facing the
    reference camera) are moved into the target camera; the cosine is that of the angle between
    the normal and the direction from the point to the target camera, negative when the target
    sees the surface from behind. The reference camera itself as target gives the pixel's own
    incidence. Pixels without a depth get -1.
    """
    dev, dt = depth.device, torch.float32
    K, w2c, t_w2c = K.to(dev, dt), world_to_camera.to(dev, dt), target_world_to_camera.to(dev, dt)
    h, w = depth.shape[-2:]
    point = depth[0].float() * pixel_rays(K, h, w)
    rel_R = t_w2c[:3, :3] @ w2c[:3, :3].T
    rel_t = t_w2c[:3, 3] - rel_R @ w2c[:3, 3]
    point = torch.einsum("ij,jhw->ihw", rel_R, point) + rel_t[:, None, None]
    turned = torch.einsum("ij,jhw->ihw", rel_R, F.normalize(normal.float(), dim=0))
    cosine = -(turned * point).sum(0) / torch.linalg.vector_norm(point, dim=0).clamp_min(1e-12)
    return torch.where(depth[0] > 0, cosine, torch.full_like(cosine, -1.0))[None]


def consistency_filter(
    depths: Sequence[Tensor],
    normals: Sequence[Tensor] | None,
    views: Sequence[View],
    *,
    aolps: Sequence[Tensor] | None = None,
    dolps: Sequence[Tensor] | None = None,
    config: FilterConfig | None = None,
    reference: int | None = None,
    sources: Sequence[int] | None = None,
) -> Tensor:
    """Keep pixels that are multi-view geometrically and polarimetrically consistent.

    Usable on any depth/normal maps (e.g. another MVS's output), not only PatchMatch's.

    Args:
        depths: per view (1, H_v, W_v) camera-z depth (<= 0 = none).
        normals: per view (3, H_v, W_v) camera-frame normals, needed for the polarimetric test.
        views: the cameras (K, world_to_camera) of the same views.
        aolps, dolps: per view (1, H_v, W_v) observed AoLP / DoLP (polarimetric test skipped
            when ``aolps`` or ``normals`` is None or ``config.use_polar`` is False).
        config: thresholds (FilterConfig defaults if None).
        reference: index of the one view to filter; None filters every view.
        sources: indices to check against (default: every other view).

    Returns:
        (1, H, W) bool for ``reference``; with ``reference=None`` a stacked (V, 1, H, W) bool
        (all views must then share one size).
    """
    cfg = config or FilterConfig()
    if len(depths) != len(views):
        raise ValueError(f"{len(depths)} depth maps for {len(views)} views")
    refs = range(len(views)) if reference is None else [reference]
    masks = []
    for i in refs:
        others = [j for j in (sources if sources is not None else range(len(views))) if j != i]
        count = torch.zeros_like(depths[i], dtype=torch.int64)
        res_sum = torch.zeros_like(depths[i], dtype=torch.float32)
        polar = cfg.use_polar and aolps is not None and normals is not None
        steep = _steep_cosine(cfg, normals)
        for j in others:
            reproj, rel, valid, pix = reprojection_check(
                depths[i], views[i].K, views[i].world_to_camera,
                depths[j], views[j].K, views[j].world_to_camera,
            )
            ok = valid & (reproj <= cfg.max_reprojection_px) & (rel <= cfg.max_relative_depth)
            if steep is not None:
                ok = ok & (incidence_cosine(depths[i], normals[i], views[i].K, views[i].world_to_camera,
                                            views[j].world_to_camera) >= steep)
            count += ok
            if polar:
                r, w = polar_residual(
                    normals[i], views[i].world_to_camera, views[j].world_to_camera, views[j].K,
                    pix, aolps[j], dolps[j] if dolps is not None else None,
                    dolp_reference=cfg.polar_dolp_reference, model=cfg.azimuth_model,
                )
                res_sum += (w * r) * ok
        keep = (count >= cfg.min_consistent_views) & (depths[i] > 0)
        if steep is not None:
            keep = keep & (incidence_cosine(depths[i], normals[i], views[i].K, views[i].world_to_camera,
                                            views[i].world_to_camera) >= steep)
        if polar:
            keep = keep & (res_sum / count.clamp_min(1) <= cfg.max_polar_residual)
        masks.append(keep)
    return masks[0] if reference is not None else torch.stack(masks)


def _steep_cosine(cfg: FilterConfig, normals: Sequence[Tensor] | None) -> float | None:
    """cos(max_incidence_deg), or None without the incidence test; it needs the normals."""
    if cfg.max_incidence_deg is None:
        return None
    if normals is None:
        raise ValueError("consistency_filter: max_incidence_deg needs the normals")
    return math.cos(math.radians(cfg.max_incidence_deg))
