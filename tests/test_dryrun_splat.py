"""The stand-ins' rasterizer (polargs_plugin.dryrun.splat): the compiled numba compositing path
against the torch path (the oracle) on every output and every gradient, and finite differences
of the numba path's depth distortion."""

from __future__ import annotations

import math

import pytest
import torch

from polargs_plugin.dryrun.splat import SplatOut, camera_from_upstream, splat

W, H, N = 24, 18, 40
FIELDS = ("features", "alpha", "normal", "depth", "inverse_depth", "median_depth", "distortion")


def _scene(seed: int, channels: int):
    """N overlapping float64 Gaussians 2.5-3.5 in front of an upstream-style camera (a few
    pixels wide, opacities 0.2-0.95: many pixels pass T = 0.5 and some reach T < 1e-4)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(N, 3, generator=g, dtype=torch.float64) * torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64)
    means = means + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(N, 4, generator=g, dtype=torch.float64), dim=-1)
    scales = torch.rand(N, 3, generator=g, dtype=torch.float64) * 0.12 + 0.03
    opac = torch.rand(N, generator=g, dtype=torch.float64) * 0.75 + 0.2
    features = torch.rand(N, channels, generator=g, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    K, w2c = camera_from_upstream(view, math.tan(0.4), math.tan(0.4) * H / W, W, H)
    return [means, quats, scales, opac, features], K.double(), w2c.double()


def _render(params, K, w2c, backend: str, abs_columns: int, **options):
    """Leaves, the screen tensors and the output of one :func:`splat` call on ``backend``."""
    leaves = [p.clone().requires_grad_(True) for p in params]
    screen = torch.zeros(N, 3, dtype=torch.float64, requires_grad=True)
    screen_abs = torch.zeros(N, abs_columns, dtype=torch.float64, requires_grad=True)
    out = splat(*leaves[:4], leaves[4], K, w2c, W, H, screen=screen, screen_abs=screen_abs, tile_size=8,
                backend=backend, **options)
    return leaves, screen, screen_abs, out


def _loss(out: SplatOut, seed: int) -> torch.Tensor:
    """A fixed random weighting of every image output (every gradient path is exercised)."""
    g = torch.Generator().manual_seed(seed)
    return sum((getattr(out, f) * torch.rand(getattr(out, f).shape, generator=g, dtype=torch.float64)).sum()
               for f in FIELDS)


@pytest.mark.parametrize(("channels", "abs_columns", "options"), [
    (3, 1, {"compensate": True, "normalize_distortion": True}),  # GOF's setting
    (8, 2, {}),  # PGSR's colour + all-map, its per-axis absolute gradient
    (1, 1, {"eps2d": 0.1}),
])
def test_numba_path_matches_the_torch_path(channels: int, abs_columns: int, options: dict) -> None:
    params, K, w2c = _scene(3, channels)
    runs = {}
    for backend in ("torch", "numba"):
        leaves, screen, screen_abs, out = _render(params, K, w2c, backend, abs_columns, **options)
        _loss(out, 7).backward()
        runs[backend] = (out, [p.grad for p in leaves] + [screen.grad, screen_abs.grad])
    (ref, ref_grads), (got, got_grads) = runs["torch"], runs["numba"]
    for field in FIELDS:
        assert getattr(ref, field).abs().max() > 0, field
        torch.testing.assert_close(getattr(got, field), getattr(ref, field), atol=1e-11, rtol=1e-9, msg=field)
    assert ref.observe.sum() > 0 and torch.equal(got.observe, ref.observe)
    assert torch.equal(got.radii, ref.radii)
    names = ("means", "quats", "scales", "opacities", "features", "screen", "screen_abs")
    for name, g_ref, g_got in zip(names, ref_grads, got_grads):
        assert g_ref.abs().max() > 0, name
        torch.testing.assert_close(g_got, g_ref, atol=1e-9, rtol=1e-7, msg=name)


def test_median_depth_is_the_last_gaussian_blended_above_half() -> None:
    """Two fronto-parallel layers of opacity 0.2 (T: 1, 0.8, 0.64): the median depth is the far
    layer's, whose T before it is 0.8 > 0.5, on both paths (the reference rasterizer's rule, T
    crossing 0.5, gives 0 here); both layers count as observed at every pixel."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[2.0, 2.0, 1e-4]] * 2, dtype=torch.float64)
    opac = torch.full((2,), 0.2, dtype=torch.float64)
    K, w2c = camera_from_upstream(torch.eye(4, dtype=torch.float64), 0.1, 0.1 * H / W, W, H)
    for backend in ("torch", "numba"):
        out = splat(means, quats, scales, opac, torch.ones(2, 1, dtype=torch.float64), K.double(), w2c.double(), W, H,
                    backend=backend)
        centre = out.median_depth[0, H // 2, W // 2]
        assert float(centre) == pytest.approx(3.0, abs=1e-3), backend
        assert out.observe.tolist() == [W * H, W * H], backend


def test_numba_distortion_gradient_matches_finite_differences() -> None:
    params, K, w2c = _scene(5, 1)
    params[2] = params[2] * 1.5

    def distortion(means, scales, opac):
        out = splat(means, params[1], scales, opac, params[4], K, w2c, W, H, tile_size=8, backend="numba",
                    normalize_distortion=True)
        return out.distortion.reshape(-1)

    inputs = [params[0].clone().requires_grad_(True), params[2].clone().requires_grad_(True),
              params[3].clone().requires_grad_(True)]
    assert distortion(*inputs).abs().sum() > 0
    assert torch.autograd.gradcheck(distortion, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_bad_inputs_are_refused_in_one_line() -> None:
    params, K, w2c = _scene(3, 3)
    with pytest.raises(ValueError, match="backend must be"):
        splat(*params, K, w2c, W, H, backend="cuda")
    with pytest.raises(ValueError, match=r"features must be \(N, C\)"):
        splat(*params[:4], params[4][:5], K, w2c, W, H)
    with pytest.raises(ValueError, match=r"screen_abs must be \(N, 1\) or \(N, 2\)"):
        splat(*params, K, w2c, W, H, screen_abs=torch.zeros(N, 3, dtype=torch.float64), backend="numba")
