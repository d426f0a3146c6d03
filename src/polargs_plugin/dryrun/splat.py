"""The rasterizer under every stand-in: the reference backend's projection and compositing rule,
with the per-pixel and per-Gaussian extras the upstream CUDA rasterizers return.

The upstream rasterizers of the graphdeco family all walk each pixel's Gaussians front to back
with the same rule as :mod:`polargs_plugin.backends.reference.composite_torch` (alpha clamped at
0.99, skipped under 1/255, stop once T < 1e-4). :func:`splat` composites with that rule, besides
any per-Gaussian feature columns, what the forks add: the alpha, the camera-frame normal, the
per-pixel depth, the inverse depth, the per-pixel depth of the last Gaussian blended while T > 0.5
("median" depth), the depth distortion of 2DGS/GOF, the count of pixels where a Gaussian was
blended while T > 0.5 (PGSR's ``out_observe``), and the upstream screen radius.

Two paths, chosen by ``backend`` (default "auto": numba on CPU): the compiled projection and
compositing of the reference backend
(:func:`~polargs_plugin.backends.reference.composite_numba.composite_features_numba`, tile-threaded,
hand-written backward; a step costs 1.1-1.3 times the reference rasterizer's, bench/standins.py), and a
torch path that runs the rule on the contributing (pixel, Gaussian) pairs and index-adds them
(any device; the tests' oracle for the compiled one). Both give the same outputs and gradients to
float rounding.

The screen-space means. Upstream trainers pass a zero tensor ``means2D`` (N, 3) whose gradient
the CUDA backward fills with dL/d(projected mean) in NDC units, i.e. pixels times (W/2, H/2);
densification reads it. Here that tensor is added to the projected means with those factors,
so its ``.grad`` is the same quantity (its value, zero, changes nothing). The absolute gradient of
AbsGS (GOF's ``means2D[:, 2]``, PGSR's ``means2D_abs``), the sum over pixels of each pixel's
|dL/d mean|, is summed per Gaussian by the compiled backward; on the torch path it comes from a
zero per-pair offset whose backward scatters |grad| into that tensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from polargs_plugin.backends.reference.binning import TileBins, bin_gaussians
from polargs_plugin.backends.reference.composite_torch import (
    contributing_pairs,
    exclusive_transmittance,
    gaussian_alpha,
    pixel_depth,
)
from polargs_plugin.backends.reference.projection import Projection, project_gaussians
from polargs_plugin.backends.reference.rasterizer import Backend, resolve_backend

__all__ = [
    "NEAR_PLANE", "FAR_PLANE", "SplatOut", "Projected", "project_splats", "composite_splats", "splat",
    "camera_from_upstream", "compensation", "upstream_radii",
]

NEAR_PLANE = 0.2
"""Camera z below which the upstream rasterizers cull a Gaussian (``in_frustum``: z <= 0.2)."""

FAR_PLANE = 100.0
"""Far plane of the NDC depth mapping of the distortion term (2DGS and GOF)."""


@dataclass
class SplatOut:
    """What :func:`splat` composites for one image (channel-first, H x W).

    Attributes:
        features: (C, H, W) sum of weight * feature columns (no background).
        alpha: (1, H, W) sum of weights (1 - final transmittance).
        normal: (3, H, W) sum of weight * camera-frame shortest axis facing the camera.
        depth: (1, H, W) sum of weight * per-pixel depth (camera z on the pixel's ray).
        inverse_depth: (1, H, W) sum of weight / (camera z of the mean), graphdeco 2024's output.
        median_depth: (1, H, W) per-pixel depth of the last Gaussian blended while T > 0.5
            (0 where no Gaussian was blended).
        distortion: (1, H, W) depth distortion sum_ij w_i w_j (m_i - m_j)^2 over NDC-mapped depths
            m (2DGS's form; divided by alpha^2 when ``normalize_distortion``, GOF's form).
        observe: (N,) int, pixels where the Gaussian was blended while T > 0.5.
        radii: (N,) int, upstream screen radius ceil(3 sigma_max) of the dilated screen
            covariance, 0 when culled (z <= near) or off-screen.
    """

    features: Tensor
    alpha: Tensor
    normal: Tensor
    depth: Tensor
    inverse_depth: Tensor
    median_depth: Tensor
    distortion: Tensor
    observe: Tensor
    radii: Tensor


def camera_from_upstream(viewmatrix: Tensor, tanfovx: float, tanfovy: float, width: int, height: int) -> tuple[Tensor, Tensor]:
    """(K, world_to_camera) of an upstream raster setting: ``viewmatrix`` is the transposed
    world-to-camera (row-vector convention), the frustum is symmetric with fx = W / (2 tan(fovx/2)),
    and the principal point W/2, H/2 in +0.5-centred pixels is the rasterizers' ndc2Pix
    ((v + 1) S - 1) / 2 in integer-centred ones. The projection matrix is not read: every
    upstream trainer builds it from the same FoVs."""
    w2c = viewmatrix.detach().transpose(0, 1).float()
    fx = width / (2.0 * tanfovx)
    fy = height / (2.0 * tanfovy)
    K = torch.tensor([[fx, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]], dtype=w2c.dtype)
    return K.to(w2c.device), w2c


def _dilated_covariance(conics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(a, b, c) of the dilated screen covariance [[a, b], [b, c]] from its inverse (the conic)."""
    det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
    return conics[:, 2] / det, -conics[:, 1] / det, conics[:, 0] / det


def compensation(conics: Tensor, eps2d: float) -> Tensor:
    """Opacity factor sqrt(det(cov) / det(cov + eps2d I)) of the Mip-Splatting 2D filter (GOF's
    ``kernel_size``, graphdeco 2024's ``antialiasing``), 0 for degenerate footprints."""
    a, b, c = _dilated_covariance(conics)
    det_dilated = (a * c - b * b).clamp_min(1e-6)
    det_raw = (a - eps2d) * (c - eps2d) - b * b
    ratio = det_raw.clamp_min(0.0) / det_dilated
    return torch.where(det_raw > 1e-6, torch.sqrt(ratio + 1e-6), torch.zeros_like(ratio))


@torch.no_grad()
def upstream_radii(proj: Projection, in_range: Tensor, width: int, height: int) -> Tensor:
    """(N,) int radius ceil(3 sqrt(lambda_max)) of each dilated screen covariance, as the upstream
    ``preprocessCUDA`` computes it, 0 when culled or when the square it spans misses the image."""
    a, b, c = _dilated_covariance(proj.conics)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp_min(mid * mid - (a * c - b * b), 0.1))
    radius = torch.ceil(3.0 * torch.sqrt(lam.clamp_min(0.0)))
    u, v = proj.means2d[:, 0], proj.means2d[:, 1]
    on_screen = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    keep = in_range & on_screen & torch.isfinite(radius)
    return torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)


class _AbsoluteGradient(torch.autograd.Function):
    """A zero (P, 2) per-pair offset of the projected means; its backward scatters each pair's
    |dL/d mean| (times the NDC factors) into ``target`` (N, 1): |x| + |y|, or (N, 2): per axis."""

    @staticmethod
    def forward(ctx, target: Tensor, gauss: Tensor, factors: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(gauss, factors)
        ctx.shape = target.shape
        return torch.zeros(gauss.shape[0], 2, dtype=target.dtype, device=target.device)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        gauss, factors = ctx.saved_tensors
        per_pair = grad.abs() * factors
        if ctx.shape[1] == 1:
            per_pair = per_pair.sum(dim=1, keepdim=True)
        out = torch.zeros(ctx.shape, dtype=grad.dtype, device=grad.device)
        return out.index_add(0, gauss, per_pair[:, : ctx.shape[1]]), None, None


def _segmented_exclusive_sum(values: Tensor, pix: Tensor) -> Tensor:
    """Sum of ``values`` over the earlier pairs of each pixel's group (float64)."""
    values = values.double()
    excl = torch.cumsum(values, 0) - values
    first = torch.ones_like(pix, dtype=torch.bool)
    first[1:] = pix[1:] != pix[:-1]
    segment = torch.cumsum(first.long(), 0) - 1
    return excl - excl[first][segment]


def _median_depth(depth: Tensor, trans: Tensor, pix: Tensor, num_pix: int) -> Tensor:
    """(num_pix,) depth of the last pair of each pixel blended while T > 0.5, else 0."""
    order = torch.arange(pix.shape[0], device=pix.device)
    before_half = trans > 0.5
    last = torch.full((num_pix,), -1, dtype=torch.long, device=pix.device)
    last = last.scatter_reduce(0, pix[before_half], order[before_half], reduce="amax")
    found = last >= 0
    out = torch.zeros(num_pix, dtype=depth.dtype, device=depth.device)
    return out.masked_scatter(found, depth[last[found]])


def _distortion(depth: Tensor, weight: Tensor, trans: Tensor, pix: Tensor, num_pix: int) -> Tensor:
    """(num_pix,) 2DGS's distortion sum_i w_i (m_i^2 A_i + M2_i - 2 m_i M1_i): m the NDC-mapped depth,
    A_i = 1 - T_i, M1, M2 the weighted sums of m and m^2 over the pixel's earlier Gaussians."""
    m = FAR_PLANE / (FAR_PLANE - NEAR_PLANE) * (1.0 - NEAR_PLANE / depth.clamp_min(NEAR_PLANE))
    w = weight.double()
    m1 = _segmented_exclusive_sum(w * m, pix)
    m2 = _segmented_exclusive_sum(w * m * m, pix)
    per_pair = (m * m * (1.0 - trans) + m2 - 2.0 * m * m1) * w
    out = torch.zeros(num_pix, dtype=torch.float64, device=pix.device).index_add(0, pix, per_pair)
    return out.to(depth.dtype)


@dataclass
class Projected:
    """N Gaussians projected into one camera, ready for :func:`composite_splats`.

    Attributes:
        proj: the reference backend's projection, its ``means2d`` (N, 2) in pixels already
            carrying the trainer's screen-space tensor (its gradient flows through it).
        opacities: (N,) opacities, times the Mip-Splatting factor when compensated.
        in_range: (N,) bool, camera z at or beyond the near plane (and before the far plane).
        factors: (2,) NDC factors (W/2, H/2) of this image.
    """

    proj: Projection
    opacities: Tensor
    in_range: Tensor
    factors: Tensor


def project_splats(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    K: Tensor,
    world_to_camera: Tensor,
    width: int,
    height: int,
    *,
    screen: Tensor | None = None,
    eps2d: float = 0.3,
    compensate: bool = False,
    near: float = NEAR_PLANE,
    far: float = 1e10,
    backend: Backend = "auto",
) -> Projected:
    """The projection half of :func:`splat` (its arguments; ``near`` / ``far`` the culling planes).
    On the numba path the projection is the compiled kernel of
    :func:`~polargs_plugin.backends.reference.projection_numba.project_numba` (same outputs to
    float rounding), unless K or ``world_to_camera`` require a gradient, which only the torch
    projection gives."""
    w2c = world_to_camera.to(means)
    K = K.to(means)
    compiled = resolve_backend(backend, means.device) == "numba" and not (K.requires_grad or w2c.requires_grad)
    if compiled:
        from polargs_plugin.backends.reference.projection_numba import project_numba

        proj = project_numba(means, quats, scales, opacities, None, K, w2c, width, height, near, far, eps2d)[0]
    else:
        proj = project_gaussians(means, quats, scales, opacities, K, w2c, width, height, near, far, eps2d)
    z = means @ w2c[2, :3] + w2c[2, 3]
    in_range = (z >= near) & (z < far)
    factors = torch.tensor([width / 2.0, height / 2.0], dtype=means.dtype, device=means.device)
    means2d = proj.means2d if screen is None else proj.means2d + screen[:, :2] * factors
    proj = proj._replace(means2d=means2d)
    opac = opacities * compensation(proj.conics, eps2d) if compensate else opacities
    return Projected(proj=proj, opacities=opac, in_range=in_range, factors=factors)


def composite_splats(
    projected: Projected,
    features: Tensor,
    width: int,
    height: int,
    *,
    screen_abs: Tensor | None = None,
    normalize_distortion: bool = False,
    tile_size: int = 16,
    backend: Backend = "auto",
) -> SplatOut:
    """The compositing half of :func:`splat`: ``features`` (N, C) and the extras, front to back,
    on the compositing path ``backend`` selects (:func:`~polargs_plugin.backends.reference.rasterizer.resolve_backend`:
    "auto" is the compiled kernel on CPU)."""
    proj = projected.proj
    if features.dim() != 2 or features.shape[0] != proj.means2d.shape[0]:
        raise ValueError(f"features must be (N, C) with N={proj.means2d.shape[0]}, got {tuple(features.shape)}")
    path = resolve_backend(backend, proj.means2d.device)
    bins = bin_gaussians(proj.means2d.detach(), proj.extents, proj.depths.detach(), width, height, tile_size)
    if path == "numba":
        sums = _composite_numba(projected, features, bins, width, height, screen_abs)
    else:
        sums = _composite_torch(projected, features, bins, width, height, screen_abs)
    image, alpha, normal, depth, inverse_depth, median_depth, distortion, observe = sums
    if normalize_distortion:
        distortion = distortion / (alpha * alpha + 1e-7)
    return SplatOut(
        features=image, alpha=alpha, normal=normal, depth=depth, inverse_depth=inverse_depth,
        median_depth=median_depth, distortion=distortion, observe=observe,
        radii=upstream_radii(proj, projected.in_range, width, height),
    )


def _composite_numba(projected: Projected, features: Tensor, bins: TileBins, width: int, height: int,
                     screen_abs: Tensor | None) -> tuple[Tensor, ...]:
    """The sums of :class:`SplatOut` (before the distortion's normalisation) from the compiled kernel."""
    from polargs_plugin.backends.reference.composite_numba import (
        composite_features_numba,
    )

    proj = projected.proj
    out = composite_features_numba(
        proj, projected.opacities, [features, proj.normals, 1.0 / proj.depths[:, None]], bins, width, height,
        median="last_above", distortion_planes=(NEAR_PLANE, FAR_PLANE), screen_abs=screen_abs,
        abs_factors=(width / 2.0, height / 2.0),
    )
    image, normal, inverse_depth = out.features
    return image, out.alpha, normal, out.depth, inverse_depth, out.median_depth, out.distortion, out.observe


def _composite_torch(projected: Projected, features: Tensor, bins: TileBins, width: int, height: int,
                     screen_abs: Tensor | None) -> tuple[Tensor, ...]:
    """The sums of :class:`SplatOut` (before the distortion's normalisation) from the torch path:
    the contributing (pixel, Gaussian) pairs, index-added into the pixels."""
    proj, opac, factors = projected.proj, projected.opacities, projected.factors
    means2d = proj.means2d
    num_gaussians, dtype, device = means2d.shape[0], means2d.dtype, means2d.device
    pix, g = contributing_pairs(proj, opac.detach(), bins, width, height)

    num_pix = width * height
    px = (pix % width).to(dtype) + 0.5
    py = torch.div(pix, width, rounding_mode="floor").to(dtype) + 0.5
    pair_means = means2d[g]
    if screen_abs is not None:
        pair_means = pair_means + _AbsoluteGradient.apply(screen_abs, g, factors)
    alpha = gaussian_alpha(pair_means, proj.conics[g], opac[g], px, py)
    trans = exclusive_transmittance(alpha, pix)
    weight = (alpha * trans).to(dtype)
    depth = pixel_depth(proj.ray_coeffs[g], proj.ray_offsets[g], proj.depth_bounds[g], px, py)

    columns = [features[g], torch.ones_like(depth)[:, None], proj.normals[g], depth[:, None], 1.0 / proj.depths[g][:, None]]
    values = torch.cat(columns, dim=-1)
    sums = torch.zeros(num_pix, values.shape[1], dtype=dtype, device=device).index_add(0, pix, weight[:, None] * values)
    image = sums.T.reshape(values.shape[1], height, width)
    c = features.shape[1]
    distortion = _distortion(depth, weight, trans, pix, num_pix).reshape(1, height, width)
    with torch.no_grad():
        observe = torch.bincount(g[trans > 0.5], minlength=num_gaussians).to(torch.int32)
    median_depth = _median_depth(depth, trans, pix, num_pix).reshape(1, height, width)
    return (image[:c], image[c : c + 1], image[c + 1 : c + 4], image[c + 4 : c + 5], image[c + 5 : c + 6],
            median_depth, distortion, observe)


def splat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    K: Tensor,
    world_to_camera: Tensor,
    width: int,
    height: int,
    *,
    screen: Tensor | None = None,
    screen_abs: Tensor | None = None,
    eps2d: float = 0.3,
    compensate: bool = False,
    normalize_distortion: bool = False,
    tile_size: int = 16,
    backend: Backend = "auto",
) -> SplatOut:
    """Composite N Gaussians into one image with the upstream extras (module docstring):
    :func:`project_splats`, then :func:`composite_splats`.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations (normalised by the projection).
        scales: (N, 3) scales, already multiplied by any ``scale_modifier``.
        opacities: (N,) opacities.
        features: (N, C) per-Gaussian columns to composite (colours, PGSR's all-map ...).
        K: (3, 3) intrinsics of the camera (:func:`camera_from_upstream`).
        world_to_camera: (4, 4) its world-to-camera transform.
        width: image width in pixels.
        height: image height in pixels.
        screen: the trainer's zero screen-space tensor (N, >=2); its ``.grad[:, :2]`` becomes
            dL/d(projected mean) in NDC units.
        screen_abs: (N, 1) or (N, 2) view of a zero tensor that receives the absolute gradient.
        eps2d: dilation of the screen covariance (0.3, GOF's ``kernel_size``).
        compensate: scale opacities by the Mip-Splatting factor of that dilation.
        normalize_distortion: divide the distortion by alpha^2 + 1e-7 (GOF).
        tile_size: binning tile edge.
        backend: "numba" (the compiled CPU projection and compositing, hand-written backward),
            "torch" (torch projection, the contributing pairs in torch, any device) or "auto"
            (numba on CPU when it imports, else torch); same rule and outputs to float rounding.
    """
    projected = project_splats(means, quats, scales, opacities, K, world_to_camera, width, height, screen=screen,
                               eps2d=eps2d, compensate=compensate, backend=backend)
    return composite_splats(projected, features, width, height, screen_abs=screen_abs,
                            normalize_distortion=normalize_distortion, tile_size=tile_size, backend=backend)
