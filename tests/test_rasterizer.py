"""Reference rasterizer against an independent dense float64 renderer written here from the
stated compositing rule (scipy rotations, numpy inverse and eigen-decomposition, every pixel
walking every Gaussian); its scenes are shared with the gradient tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from polargs_plugin.backends.reference.rasterizer import rasterize

BACKENDS = ["torch", "numba"]
ALPHA_MIN, ALPHA_MAX, T_MIN, EPS2D, CLAMP_SIGMAS = 1 / 255, 0.99, 1e-4, 0.3, 5.0


def _camera(width: int, height: int, focal: float, dtype=torch.float64):
    K = torch.tensor([[focal, 0, width / 2], [0, focal * 1.1, height / 2], [0, 0, 1]], dtype=dtype)
    return K


def _look_transform(seed: int) -> torch.Tensor:
    """A world-to-camera transform with a non-trivial rotation and translation."""
    rot = Rotation.from_rotvec(np.random.default_rng(seed).normal(size=3) * 0.3).as_matrix()
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = [0.1, -0.2, 0.3]
    return torch.tensor(w2c)


def _random_scene(n: int, width: int, height: int, seed: int, dtype=torch.float64):
    """Gaussians in front of the camera (placed in camera space, mapped to world)."""
    gen = torch.Generator().manual_seed(seed)
    K = _camera(width, height, focal=1.2 * width)
    w2c = _look_transform(seed)
    z = 2.0 + 2.0 * torch.rand(n, generator=gen, dtype=torch.float64)
    size = torch.tensor([width, height], dtype=torch.float64)
    uv = (1.2 * torch.rand(n, 2, generator=gen, dtype=torch.float64) - 0.1) * size  # some lie off-image
    cam = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], dim=-1)
    means = (cam - w2c[:3, 3]) @ w2c[:3, :3]  # R^T (x - t)
    scales = (0.02 + 0.12 * torch.rand(n, 3, generator=gen, dtype=torch.float64)) * z[:, None] / 4
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    opacities = 0.2 + 0.79 * torch.rand(n, generator=gen, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    tensors = [means, quats, scales, opacities, colors]
    return [t.to(dtype) for t in tensors], K, w2c


def dense_reference(means, quats, scales, opacities, colors, K, w2c, width, height, near=0.01, far=100.0,
                    order="center"):
    """Independent float64 renderer: every pixel walks every Gaussian, sorted by mean z
    (``order="center"``) or, per pixel (``order="ray"``, ties in mean-z order), by the depth of
    its ray's maximum density point of the Gaussian thickened by the dilation, covariance
    + EPS2D (z / f)^2 I with f the mean focal length."""
    means, quats, scales = (np.asarray(x, dtype=np.float64) for x in (means, quats, scales))
    opacities, colors = np.asarray(opacities, np.float64), np.asarray(colors, np.float64)
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    ys, xs = np.mgrid[0:height, 0:width]
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], -1)
    rays = np.concatenate([pix, np.ones((pix.shape[0], 1))], -1) @ np.linalg.inv(K).T
    n_pix = pix.shape[0]
    # every Gaussian's alpha, depth, normal and plane distance at every pixel, in mean-z order
    alphas, depths, keys, normals, dists, cols = [], [], [], [], [], []
    for i in np.argsort(means @ R.T[:, 2] + t[2]):
        mu = R @ means[i] + t
        if not near <= mu[2] <= far:
            continue
        rot = Rotation.from_quat(np.roll(quats[i], -1)).as_matrix()  # scipy is xyzw
        cov = R @ rot @ np.diag(scales[i] ** 2) @ rot.T @ R.T
        fx, fy = K[0, 0], K[1, 1]
        x, y, z = mu
        jac = np.array([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
        cov2 = jac @ cov @ jac.T + EPS2D * np.eye(2)
        mean2 = (K @ (mu / z))[:2]
        d = pix - mean2
        power = 0.5 * np.einsum("pi,ij,pj->p", d, np.linalg.inv(cov2), d)
        alphas.append(np.minimum(ALPHA_MAX, opacities[i] * np.exp(-power)))
        prec = np.linalg.inv(cov)
        depth = (rays @ prec @ mu) / np.einsum("pi,ij,pj->p", rays, prec, rays)
        spread = CLAMP_SIGMAS * math.sqrt(cov[2, 2])
        depths.append(np.clip(depth, z - spread, z + spread))
        thick = cov + EPS2D * (z / (0.5 * (fx + fy))) ** 2 * np.eye(3)
        thick_prec = np.linalg.inv(thick)
        key = (rays @ thick_prec @ mu) / np.einsum("pi,ij,pj->p", rays, thick_prec, rays)
        keys.append(np.clip(key, z - CLAMP_SIGMAS * math.sqrt(thick[2, 2]), z + CLAMP_SIGMAS * math.sqrt(thick[2, 2])))
        evals, evecs = np.linalg.eigh(cov)
        normals.append(evecs[:, 0] * (-1.0 if evecs[:, 0] @ mu > 0 else 1.0))
        dists.append(-(normals[-1] @ mu))  # the splat's plane n . x = -d, d = -n . mu
        cols.append(colors[i])
    alphas, depths = np.array(alphas).reshape(-1, n_pix), np.array(depths).reshape(-1, n_pix)
    normals, dists, cols = np.array(normals).reshape(-1, 3), np.array(dists), np.array(cols).reshape(-1, 3)
    keys = np.array(keys).reshape(-1, n_pix)
    ranks = np.argsort(keys, axis=0, kind="stable") if order == "ray" else np.arange(len(cols))[:, None].repeat(n_pix, 1)
    trans = np.ones(n_pix)
    done = np.zeros(n_pix, bool)
    out = {k: np.zeros((n_pix, c)) for k, c in (("color", 3), ("dsum", 1), ("normal", 3), ("median", 1), ("dist", 1))}
    every = np.arange(n_pix)
    for rank in ranks:  # the rank-th Gaussian of each pixel
        alpha, depth = alphas[rank, every], depths[rank, every]
        use = ~done & (alpha >= ALPHA_MIN)
        stop = use & (trans * (1 - alpha) < T_MIN)
        done |= stop
        use &= ~stop
        w = np.where(use, alpha * trans, 0.0)
        out["color"] += w[:, None] * cols[rank]
        out["normal"] += w[:, None] * normals[rank]
        out["dsum"][:, 0] += w * depth
        out["dist"][:, 0] += w * dists[rank]
        new_t = np.where(use, trans * (1 - alpha), trans)
        crossing = use & (trans >= 0.5) & (new_t < 0.5)
        out["median"][crossing, 0] = depth[crossing]
        trans = new_t
    alpha = 1 - trans
    # The blended plane n . x = -d meets the pixel's ray z * (rx, ry, 1) at z = d / -(n . r).
    cosine = -np.einsum("pi,pi->p", out["normal"], rays)
    plane = np.where(cosine > 1e-6, out["dist"][:, 0] / np.maximum(cosine, 1e-6), 0.0)
    shape = lambda a: torch.tensor(a.T.reshape(-1, height, width))  # noqa: E731
    return {
        "color": shape(out["color"]),
        "normal": shape(out["normal"]),
        "alpha": shape(alpha[:, None]),
        "depth": shape(np.where(alpha > 0, out["dsum"][:, 0] / np.maximum(alpha, 1e-300), 0.0)[:, None]),
        "median_depth": shape(out["median"]),
        "plane_depth": shape(plane[:, None]),
        "terminated": shape(done[:, None].astype(np.float64)) > 0,
    }


def _edge_on_gaussian(w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World mean and wxyz quaternion of a flat Gaussian seen almost edge-on, in front of the
    occluders: its plane depth leaves the +-5 sigma_z clamp interval over part of its footprint."""
    mean_cam = np.array([-0.1, 0.05, 1.2])
    view = mean_cam / np.linalg.norm(mean_cam)
    normal = np.cross(view, [1.0, 0.0, 0.0]) + 0.05 * view
    normal /= np.linalg.norm(normal)
    tangent = np.cross(normal, [0.0, 0.0, 1.0])
    tangent /= np.linalg.norm(tangent)
    frame_cam = np.stack([tangent, np.cross(normal, tangent), normal], axis=1)
    rot_w2c, t_w2c = w2c[:3, :3].numpy(), w2c[:3, 3].numpy()
    quat = np.roll(Rotation.from_matrix(rot_w2c.T @ frame_cam).as_quat(), 1)
    return torch.tensor(rot_w2c.T @ (mean_cam - t_w2c)), torch.tensor(quat)


def _scene_with_occluders(seed: int, width: int, height: int, dtype=torch.float64):
    """Random Gaussians, a stack of large opaque ones (so T < 1e-4 termination happens) and an
    edge-on splat in front of them (so the per-pixel depth clamp is active)."""
    (means, quats, scales, opac, colors), K, w2c = _random_scene(30, width, height, seed, dtype)
    cam_pts = torch.tensor([[0.05 * k, 0.02 * k, 1.5 + 0.1 * k] for k in range(5)], dtype=torch.float64)
    edge_mean, edge_quat = _edge_on_gaussian(w2c)
    extra_means = torch.cat([(cam_pts - w2c[:3, 3]) @ w2c[:3, :3], edge_mean[None]])
    stack_quats = torch.randn(5, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    extra_scales = torch.tensor([[0.3, 0.25, 0.05]] * 5 + [[0.2, 0.12, 0.002]], dtype=torch.float64)
    means = torch.cat([means, extra_means.to(dtype)])
    quats = torch.cat([quats, stack_quats.to(dtype), edge_quat[None].to(dtype)])
    scales = torch.cat([scales, extra_scales.to(dtype)])
    opac = torch.cat([opac, torch.tensor([0.97, 0.995, 0.9, 0.96, 0.98, 0.8], dtype=dtype)])
    colors = torch.cat([colors, torch.linspace(0, 1, 18, dtype=dtype).reshape(6, 3)])
    return [means, quats, scales, opac, colors], K, w2c


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("order", ["center", "ray"])
def test_matches_dense_reference(backend: str, seed: int, order: str) -> None:
    """Both orders against the dense renderer; "ray" with one-pixel tiles is exact per pixel."""
    width, height = 22, 17
    params, K, w2c = _scene_with_occluders(seed, width, height)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = rasterize(*params, K, w2c, width, height, tile_size=8 if order == "center" else 1, backend=backend,
                    background=bg, order=order)
    ref = dense_reference(*params, K, w2c, width, height, order=order)
    assert ref["terminated"].any()  # the occluder stack exercises the T < 1e-4 rule
    for name in ("normal", "alpha", "depth", "median_depth", "plane_depth"):
        torch.testing.assert_close(getattr(out, name), ref[name], atol=1e-5, rtol=0, msg=name)
    torch.testing.assert_close(out.color, ref["color"] + (1 - ref["alpha"]) * bg[:, None, None], atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_close_to_float64_reference(backend: str) -> None:
    width, height = 20, 16
    params, K, w2c = _scene_with_occluders(2, width, height, dtype=torch.float32)
    out = rasterize(*params, K, w2c, width, height, tile_size=8, backend=backend)
    ref = dense_reference(*(p.double() for p in params), K, w2c, width, height)
    for name in ("color", "normal", "alpha", "depth", "plane_depth"):
        torch.testing.assert_close(getattr(out, name).double(), ref[name], atol=2e-4, rtol=0, msg=name)


def test_means2d_and_radii() -> None:
    width, height = 24, 18
    (means, quats, scales, opac, colors), K, w2c = _random_scene(40, width, height, seed=3)
    out = rasterize(means, quats, scales, opac, colors, K, w2c, width, height, backend="torch")
    cam = means @ w2c[:3, :3].T + w2c[:3, 3]
    expected = (cam / cam[:, 2:]) @ K.T
    torch.testing.assert_close(out.means2d, expected[:, :2])
    # A Gaussian that reaches alpha >= 1/255 at some pixel centre must have radius > 0.
    for i in range(means.shape[0]):
        single = dense_reference(means[i : i + 1], quats[i : i + 1], scales[i : i + 1], opac[i : i + 1],
                                 colors[i : i + 1], K, w2c, width, height)
        assert (single["alpha"].max() > 0) <= (out.radii[i] > 0)
    assert out.radii.dtype == torch.int64


def _row_case(rng: np.random.Generator, c0: float) -> tuple:
    """A row of a random Gaussian: sigma(dx) = c0 dx^2 / 2 + k1 dx + k0, box [ulo, uhi]."""
    k1, k0 = rng.normal() * 2.0, abs(rng.normal()) * 0.3
    mx, opacity = rng.uniform(-4.0, 24.0), rng.uniform(0.05, 1.0)
    ulo = int(rng.integers(0, 8))
    return c0, k1, k0, mx, opacity, ulo, ulo + int(rng.integers(0, 16))


@pytest.mark.slow
def test_row_falloffs_are_exp_on_exactly_the_contributing_span() -> None:
    """The numba compositing's exp(-sigma) along a row (one exponential at the row's peak, then a
    multiplication a pixel) against numpy's exponential at every pixel: the span is exactly the
    pixels with opacity exp(-sigma) >= 1/255, the values agree to 1e-13, also where the peak lies
    outside the box and, for a row with c0 <= 0 (never binned) or a NaN centre, over the whole box."""
    from polargs_plugin.backends.reference.composite_numba import _row_falloffs

    rng = np.random.default_rng(0)
    spans = clipped = 0
    for case in range(400):
        c0 = rng.uniform(0.05, 12.0) if case % 10 else -rng.uniform(0.0, 1.0)
        c0, k1, k0, mx, opacity, ulo, uhi = _row_case(rng, c0)
        dx = np.arange(ulo, uhi + 1) + 0.5 - mx
        exact = np.exp(-((0.5 * c0 * dx + k1) * dx + k0))
        falloff = np.full(16, np.nan)
        first, last = _row_falloffs(falloff, c0, k1, k0, mx, opacity, ulo, uhi)
        if c0 <= 0:
            assert (first, last) == (ulo, uhi)
        else:
            assert not np.any(np.abs(opacity * exact - ALPHA_MIN) < 1e-12)  # no knife edge in these cases
            inside = np.flatnonzero(opacity * exact >= ALPHA_MIN) + ulo
            expected = (inside[0], inside[-1]) if inside.size else None
            assert (first, last) == expected or (expected is None and first > last)
            spans += inside.size > 0
            clipped += inside.size > 0 and not ulo <= mx - k1 / c0 <= uhi + 1
        got = falloff[first - ulo : last - ulo + 1]
        np.testing.assert_allclose(got, exact[first - ulo : last - ulo + 1], rtol=1e-13, atol=0)
    assert spans > 100 and clipped > 10, (spans, clipped)  # spans, and spans the box cuts short
    falloff = np.zeros(16)
    assert _row_falloffs(falloff, 1.0, 0.5, 0.1, math.nan, 0.5, 2, 9) == (2, 9)  # NaN: every pixel, no crash
    assert np.isnan(falloff[:8]).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_without_plane_depth_the_other_outputs_are_the_same(backend: str) -> None:
    """``with_plane_depth=False`` (a trainer without L_dn) drops only the plane depth."""
    width, height = 22, 17
    params, K, w2c = _scene_with_occluders(0, width, height)
    full = rasterize(*params, K, w2c, width, height, tile_size=8, backend=backend)
    bare = rasterize(*params, K, w2c, width, height, tile_size=8, backend=backend, with_plane_depth=False)
    assert full.plane_depth is not None and bare.plane_depth is None
    for name in ("color", "depth", "median_depth", "normal", "alpha", "means2d", "radii"):
        assert torch.equal(getattr(full, name), getattr(bare, name)), name


@pytest.mark.parametrize("backend", BACKENDS)
def test_ray_order_shows_the_splat_each_ray_meets_first(backend: str) -> None:
    """Two large opaque flat splats crossing at 60 degrees in front of the camera: each pixel
    must show the colour of the plane its ray meets first (analytic ray-plane intersection).
    "ray" with one-pixel tiles gets every pixel right away from the crossing line's blur; mean
    depth ("center") shows the splat with the nearer centre over the whole overlap."""
    width = height = 32
    K = torch.tensor([[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    # plane A: through (0, 0, 2), tilted +30 deg about y; plane B: through (0.1, 0, 2.2), tilted -30 deg
    angles, centres = (math.radians(30), math.radians(-30)), ([0.0, 0.0, 2.0], [0.1, 0.0, 2.2])
    quats = torch.tensor([[math.cos(a / 2), 0.0, math.sin(a / 2), 0.0] for a in angles], dtype=torch.float64)
    means = torch.tensor(centres, dtype=torch.float64)
    scales = torch.tensor([[2.0, 2.0, 1e-4]] * 2, dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    opacities = torch.tensor([0.99, 0.99], dtype=torch.float64)
    u = (torch.arange(width, dtype=torch.float64) + 0.5 - 16) / 32  # ray x / z (rows are alike)
    hits = []
    for a, c in zip(angles, centres):
        n = torch.tensor([math.sin(a), 0.0, math.cos(a)], dtype=torch.float64)  # the splat's local z in camera frame
        hits.append((n @ torch.tensor(c, dtype=torch.float64)) / (n[0] * u + n[2]))  # camera z where the ray meets it
    a_first = hits[0] < hits[1]
    away = (hits[0] - hits[1]).abs() > 0.02  # a few pixels from the crossing line
    shown = {}
    for order, tile in (("ray", 1), ("center", 16)):
        out = rasterize(means, quats, scales, opacities, colors, K, w2c, width, height, tile_size=tile,
                        backend=backend, order=order, with_plane_depth=False)
        shown[order] = out.color[0, 16] > out.color[1, 16]  # red (A) over green (B), middle row
    assert a_first[away].any() and (~a_first[away]).any()  # both planes are in front somewhere
    assert torch.equal(shown["ray"][away], a_first[away])
    assert bool(shown["center"].all())  # A's centre is nearer: A everywhere, wrong where B is in front


@pytest.mark.parametrize("backend", BACKENDS)
def test_ray_order_sorts_an_edge_on_splat_the_ray_passes_by_at_its_centre_depth(backend: str) -> None:
    """A face-on opaque red splat at z = 3 and, behind it (centre z = 3.3), a blue flat splat
    seen edge-on, long along the view direction, whose plane x = 0.003 the rays of the middle
    columns pass 0.01-0.02 beside (100-200 thicknesses): the blue splat's alpha there comes from
    the screen dilation alone. Those rays cross its plane far in front (its depth clamps at
    5 sigma_z before its centre, z = 1.8), where sorting it would draw it over the red one; the
    splat thickened by the dilation (0.018 at z = 3.3) is densest along them near its centre,
    behind the red splat, which must stay in front."""
    width = height = 32
    K = torch.tensor([[100.0, 0, 16], [0, 100.0, 16], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 3.0], [0.003, 0.0, 3.3]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[1.0, 1.0, 1e-4], [1e-4, 0.3, 0.3]], dtype=torch.float64)  # blue: normal along x
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    opacities = torch.tensor([0.99, 0.99], dtype=torch.float64)
    out = rasterize(means, quats, scales, opacities, colors, K, w2c, width, height, tile_size=1,
                    backend=backend, order="ray", with_plane_depth=False)
    alone = rasterize(means[1:], quats[1:], scales[1:], opacities[1:], colors[1:], K, w2c, width, height,
                      tile_size=1, backend=backend, order="ray", with_plane_depth=False)
    columns = slice(15, 17)  # pixel centres 15.5 and 16.5; the blue line projects to x = 16.09
    rows = slice(12, 20)
    assert bool((alone.alpha[0, rows, columns] > 0.4).all())  # the blue splat does cover these pixels
    assert bool((alone.median_depth[0, rows, columns] < 2.0).all())  # at its clamped plane crossing
    assert bool((out.color[0, rows, columns] > 0.98).all()) and bool((out.color[2, rows, columns] < 0.02).all())
    torch.testing.assert_close(out.median_depth[0, rows, columns], torch.full((8, 2), 3.0, dtype=torch.float64), atol=1e-9, rtol=0)


def _bins_and_ray_keys(n: int, seed: int, dtype: torch.dtype, tile_size: int, copies: int = 0):
    """The mean-depth tile lists of a random 40x32 scene of ``n`` Gaussians (the first ``copies``
    repeated, for ties in the keys) and their ray-order keys, in ``dtype``."""
    from polargs_plugin.backends.reference.binning import bin_gaussians
    from polargs_plugin.backends.reference.projection import dilated_ray_depth_data, project_gaussians

    width, height = 40, 32
    (means, quats, scales, opacities, _), K, w2c = _random_scene(n, width, height, seed=seed, dtype=dtype)
    means, quats, scales, opacities = (torch.cat([x, x[:copies]]) for x in (means, quats, scales, opacities))
    K, w2c = K.to(dtype), w2c.to(dtype)
    proj = project_gaussians(means, quats, scales, opacities, K, w2c, width, height)
    bins = bin_gaussians(proj.means2d, proj.extents, proj.depths, width, height, tile_size)
    return bins, dilated_ray_depth_data(means, quats, scales, K, w2c)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tile_size", [1, 4, 16])
def test_ray_order_lists_are_the_same_from_the_compiled_sort(tile_size: int, dtype: torch.dtype) -> None:
    """The compiled per-tile sort gives each tile the same list as the torch sort (same keys in
    the same dtype, both stable), on a scene of many overlapping Gaussians with ties in the keys
    (copies)."""
    from polargs_plugin.backends.reference.composite_numba import ray_ordered_numba
    from polargs_plugin.backends.reference.rasterizer import ray_ordered

    bins, keys = _bins_and_ray_keys(300, seed=5, dtype=dtype, tile_size=tile_size, copies=20)
    reference = ray_ordered(bins, keys).gauss_ids
    compiled = ray_ordered_numba(bins, keys).gauss_ids
    assert not torch.equal(reference, bins.gauss_ids)  # the ray order differs from the mean-depth order
    assert torch.equal(compiled, reference)


def test_parse_order_and_tile_names_the_argument_in_its_errors() -> None:
    from polargs_plugin.backends.reference.rasterizer import parse_order_and_tile

    assert parse_order_and_tile("center:16", "--orders") == ("center", 16)
    for spec, message in (("nearest:1", "the order in --render must be one of"), ("ray", "--render wants ORDER:TILE"),
                          ("ray:x", "--render wants ORDER:TILE"), ("ray:0", "the tile size in --render must be >= 1")):
        with pytest.raises(ValueError, match=message):
            parse_order_and_tile(spec, "--render")


def test_ray_order_keys_in_chunks_give_the_same_lists(monkeypatch) -> None:
    """The torch path computes the ray-order keys chunk by chunk; chunks of 7 pairs give the
    lists of one chunk."""
    import polargs_plugin.backends.reference.rasterizer as rasterizer_module

    bins, keys = _bins_and_ray_keys(200, seed=6, dtype=torch.float32, tile_size=4)
    whole = rasterizer_module.ray_ordered(bins, keys).gauss_ids
    monkeypatch.setattr(rasterizer_module, "RAY_KEY_CHUNK", 7)
    assert bins.gauss_ids.shape[0] > 7 * 10
    assert torch.equal(rasterizer_module.ray_ordered(bins, keys).gauss_ids, whole)
    assert not torch.equal(whole, bins.gauss_ids)
