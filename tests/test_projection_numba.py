"""The compiled projection (projection_numba) against the torch reference: values (float64 and
float32), hand-written gradients against finite differences (gradcheck) and against torch's
autograd, edge cases (field-of-view clamp, near/far culling, nearly flat and isotropic
Gaussians, opacity below 1/255, SH degrees 0-3), and the whole rasterizer with either projection."""

from __future__ import annotations

import pytest
import torch

from polargs_plugin.backends.reference.projection import Projection, project_gaussians
from polargs_plugin.geometry import eval_sh
from polargs_plugin.backends.reference.projection_numba import project_numba
from polargs_plugin.backends.reference.rasterizer import rasterize

from test_rasterizer import _random_scene, _scene_with_occluders

F64 = torch.float64
W, H = 20, 14


def _edge_scene(dtype=F64, sh_degree: int = -1, flat: float = 1e-3, seed: int = 0, ties: bool = True):
    """Random Gaussians plus the edge cases, in world coordinates of a rotated camera (``ties``:
    one isotropic Gaussian, whose normal jumps under finite differences of its scales)."""
    (means, quats, scales, opac, colors), K, w2c = _random_scene(8, W, H, seed)
    fx, cx = K[0, 0].item(), K[0, 2].item()
    z = 2.5
    lim = 1.3 * (W - cx) / fx  # FoV clamp of x/z
    cam = torch.tensor(
        [
            [3.0 * lim * z, 0.1, z],  # far outside the clamp: Jacobian clamped
            [0.97 * lim * z, -0.2, z],  # just inside the clamp
            [-2.0 * lim * z, 1.5 * lim * z, z],  # clamped on both axes
            [0.1, 0.1, 0.005],  # nearer than near: culled
            [0.1, 0.1, -1.0],  # behind the camera: culled
            [0.0, 0.0, 150.0],  # beyond far: culled
            [0.05, -0.05, 2.0],  # nearly flat
            [-0.05, 0.05, 2.2],  # isotropic (ties in the scales)
            [0.02, 0.03, 1.8],  # opacity below 1/255: no extent
        ],
        dtype=F64,
    )
    extra_means = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    gen = torch.Generator().manual_seed(seed + 100)
    extra_quats = torch.randn(cam.shape[0], 4, generator=gen, dtype=F64)
    extra_scales = torch.tensor(
        [[0.1, 0.05, 0.08], [0.06, 0.1, 0.07], [0.05, 0.052, 0.09], [0.1, 0.11, 0.12], [0.12, 0.1, 0.11],
         [0.3, 0.2, 0.1], [0.2, 0.15, 0.2 * flat], [0.08, 0.08, 0.08] if ties else [0.08, 0.081, 0.079],
         [0.1, 0.07, 0.05]],
        dtype=F64,
    )
    extra_opac = torch.tensor([0.5, 0.6, 0.7, 0.8, 0.8, 0.8, 0.9, 0.6, 0.003], dtype=F64)
    means = torch.cat([means, extra_means])
    quats = torch.cat([quats, extra_quats])
    scales = torch.cat([scales, extra_scales])
    opac = torch.cat([opac, extra_opac])
    n = means.shape[0]
    if sh_degree < 0:
        colors = torch.rand(n, 3, generator=gen, dtype=F64)
    else:
        colors = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=F64)
        colors[:3, 0] = -2.5  # clamped at 0 in some channels
    return [t.to(dtype) for t in (means, quats, scales, opac, colors)], K, w2c


def _torch_path(means, quats, scales, opac, colors, K, w2c):
    proj = project_gaussians(means, quats, scales, opac, K, w2c, W, H)
    if colors.dim() == 3:
        w = w2c.to(means)
        colors = eval_sh(colors, means - (-w[:3, :3].T @ w[:3, 3]))
    return proj, colors


def _fields(proj: Projection, colors: torch.Tensor) -> dict[str, torch.Tensor]:
    return {**proj._asdict(), "colors": colors}


@pytest.mark.parametrize("sh_degree", [-1, 0, 1, 2, 3])
def test_values_match_torch_float64(sh_degree: int) -> None:
    params, K, w2c = _edge_scene(sh_degree=sh_degree, flat=1e-7)
    ref = _fields(*_torch_path(*params, K, w2c))
    got = _fields(*project_numba(*params, K, w2c, W, H))
    assert (ref["extents"] == 0).all(dim=-1).sum() >= 4  # culled, and opacity < 1/255
    for name in ref:
        assert got[name].dtype == F64
        torch.testing.assert_close(got[name], ref[name], atol=1e-9, rtol=1e-9, msg=name)


@pytest.mark.parametrize("sh_degree", [-1, 1, 3])
def test_values_match_torch_float32(sh_degree: int) -> None:
    params, K, w2c = _edge_scene(dtype=torch.float32, sh_degree=sh_degree)
    K32, w2c32 = K.float(), w2c.float()
    ref = _fields(*_torch_path(*params, K32, w2c32))
    got = _fields(*project_numba(*params, K32, w2c32, W, H))
    for name in ref:
        assert got[name].dtype == torch.float32
        torch.testing.assert_close(got[name], ref[name], atol=2e-5, rtol=2e-4, msg=name)


def _differentiable_outputs(proj: Projection, colors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return (*proj[:7], colors)


@pytest.mark.parametrize("sh_degree", [-1, 0, *(pytest.param(d, marks=pytest.mark.slow) for d in (1, 2, 3))])
def test_gradcheck(sh_degree: int) -> None:
    params, K, w2c = _edge_scene(sh_degree=sh_degree, seed=1, ties=False)
    means, quats, scales, opac, colors = params

    def fn(m, q, s, c):
        return _differentiable_outputs(*project_numba(m, q, s, opac, c, K, w2c, W, H))

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, colors)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("sh_degree", [-1, 2, 3])
def test_gradients_match_torch_autograd(sh_degree: int) -> None:
    params, K, w2c = _edge_scene(sh_degree=sh_degree, seed=2, flat=1e-5)
    grads = {}
    for path in ("torch", "numba"):
        leaves = [t.clone().requires_grad_(True) for t in params]
        if path == "torch":
            outs = _differentiable_outputs(*_torch_path(*leaves, K, w2c))
        else:
            outs = _differentiable_outputs(*project_numba(*leaves, K, w2c, W, H))
        gen = torch.Generator().manual_seed(3)
        weights = [torch.randn(o.shape, generator=gen, dtype=F64) for o in outs]
        torch.autograd.backward(outs, weights)
        grads[path] = [t.grad for t in leaves]
    for name, g_ref, g in zip(("means", "quats", "scales", "opacities", "colors"), grads["torch"], grads["numba"]):
        if name == "opacities":  # only the (no-grad) extents read them
            assert g_ref is None and g is None
            continue
        assert g_ref.abs().max() > 0
        torch.testing.assert_close(g, g_ref, atol=1e-9, rtol=1e-7, msg=name)


def test_ties_and_facing_follow_shortest_axis_normals() -> None:
    """Ties in the scales pick the first axis (torch.argmin), for the normal and for s_min."""
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 7], [0, 0, 1]], dtype=F64)
    w2c = torch.eye(4, dtype=F64)
    means = torch.tensor([[0.1, 0.0, 2.0], [-0.1, 0.1, 2.5], [0.0, -0.1, 3.0]], dtype=F64, requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0], [0.9, 0.1, -0.3, 0.2], [0.0, 0.0, 1.0, 0.0]], dtype=F64)
    scales = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.05, 0.05], [0.3, 0.3, 0.1]], dtype=F64, requires_grad=True)
    opac = torch.full((3,), 0.7, dtype=F64)
    colors = torch.rand(3, 3, dtype=F64)
    ref, _ = _torch_path(means, quats, scales, opac, colors, K, w2c)
    got, _ = project_numba(means, quats, scales, opac, colors, K, w2c, W, H)
    torch.testing.assert_close(got.normals, ref.normals, atol=1e-12, rtol=0)
    g_ref = torch.autograd.grad(ref.ray_offsets.sum() + ref.ray_coeffs.sum(), scales)[0]
    g_got = torch.autograd.grad(got.ray_offsets.sum() + got.ray_coeffs.sum(), scales)[0]
    torch.testing.assert_close(g_got, g_ref, atol=1e-10, rtol=1e-9)


def _outputs(out) -> torch.Tensor:
    return torch.cat([out.color, out.depth, out.median_depth, out.normal, out.alpha]).reshape(-1)


@pytest.mark.parametrize("sh_degree", [-1, 1, 3])
def test_rasterize_projection_paths_agree(sh_degree: int) -> None:
    """rasterize(backend="numba") with the compiled projection equals the torch projection and
    the torch backend, in value and in every gradient (means2d included)."""
    width, height = 22, 17
    params, K, w2c = _scene_with_occluders(1, width, height)
    if sh_degree >= 0:
        gen = torch.Generator().manual_seed(8)
        params[4] = 0.3 * torch.randn(params[0].shape[0], (sh_degree + 1) ** 2, 3, generator=gen, dtype=F64)
    weights = torch.rand(9, height, width, dtype=F64, generator=torch.Generator().manual_seed(6))
    results = {}
    for name, kwargs in {
        "torch": {"backend": "torch"},
        "numba_tproj": {"backend": "numba", "projection": "torch"},
        "numba": {"backend": "numba", "projection": "numba"},
        "auto": {"backend": "auto"},
    }.items():
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, K, w2c, width, height, tile_size=8, **kwargs)
        (_outputs(out).reshape(9, height, width) * weights).sum().backward()
        results[name] = [_outputs(out).detach(), out.radii] + [p.grad for p in leaves] + [out.means2d.grad]
    for name in ("numba_tproj", "numba", "auto"):
        for ref, got in zip(results["torch"], results[name]):
            torch.testing.assert_close(got, ref, atol=1e-9, rtol=1e-7, msg=name)


def test_rasterize_camera_gradient_falls_back_to_torch_projection() -> None:
    width, height = 12, 10
    (means, quats, scales, opac, colors), K, w2c = _random_scene(6, width, height, seed=5)
    w2c = w2c.clone().requires_grad_(True)
    out = rasterize(means, quats, scales, opac, colors, K, w2c, width, height, backend="numba")
    out.color.sum().backward()
    assert w2c.grad is not None and w2c.grad.abs().max() > 0
    with pytest.raises(ValueError, match="K / world_to_camera"):
        rasterize(means, quats, scales, opac, colors, K, w2c, width, height, backend="numba", projection="numba")
    with pytest.raises(ValueError, match="projection"):
        rasterize(means, quats, scales, opac, colors, K, w2c.detach(), width, height, backend="torch",
                  projection="numba")


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compositing_unchanged_by_footprint_boxes(dtype: torch.dtype) -> None:
    """Long thin splats (ill-conditioned conics in float32): the numba compositor's per-Gaussian
    pixel boxes skip only pixels the exact alpha >= 1/255 test would skip, so it equals the
    torch compositor on the same projection (a wrongly skipped pair would cost ~1/255)."""
    width, height = 40, 32
    (means, quats, scales, opac, colors), K, w2c = _random_scene(60, width, height, seed=11)
    scales = scales * torch.tensor([6.0, 0.3, 0.05], dtype=F64)
    params = [t.to(dtype) for t in (means, quats, scales, opac, colors)]
    K, w2c = K.to(dtype), w2c.to(dtype)
    ref = rasterize(*params, K, w2c, width, height, backend="torch")
    got = rasterize(*params, K, w2c, width, height, backend="numba", projection="torch")
    atol = 2e-5 if dtype == torch.float32 else 1e-9
    for name in ("color", "depth", "normal", "alpha", "median_depth"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), atol=atol, rtol=0, msg=name)


@pytest.mark.parametrize("tile_size", [4, 16])
def test_cpu_tile_lists_equal_sorted_pairs(tile_size: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """bin_gaussians on CPU fills the tile lists by counting; the lists equal the torch sort's."""
    from polargs_plugin.backends.reference import binning
    from polargs_plugin.backends.reference.binning import bin_gaussians

    width, height = 37, 29  # not a multiple of the tile size
    (means, quats, scales, opac, colors), K, w2c = _random_scene(300, width, height, seed=12)
    proj = project_gaussians(means, quats, scales, opac, K, w2c, width, height)
    args = (proj.means2d.detach(), proj.extents, proj.depths.detach(), width, height, tile_size)
    counting, calls = binning.counted_tile_lists, []
    monkeypatch.setattr(binning, "counted_tile_lists", lambda *a: calls.append(a) or counting(*a))
    counted = bin_gaussians(*args)
    assert len(calls) == 1  # the CPU path counts
    monkeypatch.setattr(binning, "counted_tile_lists", binning.sorted_tile_lists)  # the sort path
    ref = bin_gaussians(*args)
    assert counted.gauss_ids.shape[0] > 300 and not counted.visible.all() and counted.visible.any()
    for got, want in zip(counted, ref):
        if isinstance(want, torch.Tensor):
            assert got.dtype == want.dtype
            assert torch.equal(got, want)
        else:
            assert got == want
