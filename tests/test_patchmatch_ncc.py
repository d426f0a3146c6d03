"""Bilateral NCC: backends agree, true planes score best, NCC invariances, COLMAP weights."""

import math

import pytest
import torch

from polargs_plugin.densify.homography import pixel_rays, relative_pose
from polargs_plugin.geometry import ray_plane_distance
from polargs_plugin.densify.ncc import (
    MAX_COST,
    bilateral_ncc_cost,
    numba_available,
    reference_windows,
    window_offsets,
)
from test_patchmatch_scenes import make_scene


def _setup(size=40):
    views, renders = make_scene("plane", size=size, num_sources=2)
    ref = views[0]
    R, t = relative_pose(ref.world_to_camera, torch.stack([v.world_to_camera for v in views[1:]]))
    Ks = torch.stack([v.K for v in views[1:]])
    A = (Ks @ R @ torch.linalg.inv(ref.K)).float()
    b = (Ks @ t.unsqueeze(-1)).squeeze(-1).float()
    offsets = window_offsets(5, 2)
    gray = renders[0][0].mean(0)
    win = reference_windows(gray, offsets, -1.0, 0.2)
    sources = torch.stack([r[0].mean(0) for r in renders[1:]])
    return views, renders, A, b, offsets, win, sources


def _hypotheses(ref, depth, normal, idx):
    """(1/d, m_xy) of hypotheses depth (P, M), normal (P, M, 3) at flat pixels idx."""
    rays = pixel_rays(ref.K, ref.height, ref.width).float().reshape(3, -1).T[idx]
    d_plane = ray_plane_distance(depth, normal, rays[:, None])
    m = -torch.einsum("ij,pmi->pmj", torch.linalg.inv(ref.K).float(), normal) / d_plane[..., None]
    return 1.0 / depth, m[..., :2].contiguous()


def _pixels(ref, idx):
    u = idx % ref.width
    v = idx // ref.width
    return torch.stack([u, v], -1).float() + 0.5


def test_window_offsets_follow_colmap_radius_and_step():
    off = window_offsets(5, 2)
    assert off.shape == (36, 2)
    assert set(off[:, 0].tolist()) == {-5.0, -3.0, -1.0, 1.0, 3.0, 5.0}


def test_reference_weights_match_the_bilateral_formula():
    gray = torch.rand(12, 12)
    offsets = window_offsets(3, 1)
    win = reference_windows(gray, offsets, 2.0, 0.3)
    v, u = 6, 5
    i = v * 12 + u
    raw = []
    for ox, oy in offsets.tolist():
        val = gray[v + int(oy), u + int(ox)]
        raw.append(math.exp(-(ox**2 + oy**2) / 8.0 - (val - gray[v, u]) ** 2 / (2 * 0.09)))
    raw = torch.tensor(raw)
    assert torch.allclose(win.weights[i], raw / raw.sum(), atol=1e-6)
    mean = (raw / raw.sum() * win.values[i]).sum()
    assert torch.isclose(win.mean[i], mean, atol=1e-6)


@pytest.mark.skipif(not numba_available(), reason="numba missing")
def test_numba_reference_statistics_match_including_borders():
    import numpy as np

    from polargs_plugin.densify.numba_kernels import reference_kernel

    gray = torch.rand(9, 13, generator=torch.Generator().manual_seed(0))
    win = reference_windows(gray, window_offsets(3, 2), 2.0, 0.3)
    w, wc, var = np.empty((117, 16), np.float32), np.empty((117, 16), np.float32), np.empty(117, np.float32)
    reference_kernel(gray.numpy(), 3, 2, 2.0, 0.3, w, wc, var)
    assert torch.allclose(torch.from_numpy(w), win.weights, atol=1e-6)
    assert torch.allclose(torch.from_numpy(var), win.var, atol=1e-6)
    assert torch.allclose(torch.from_numpy(wc), win.weights * (win.values - win.mean[:, None]), atol=1e-6)


def test_true_plane_has_near_zero_cost_and_wins_a_depth_sweep():
    views, renders, A, b, offsets, win, sources = _setup()
    ref = views[0]
    depth_gt, normal_gt = renders[0][1][0], renders[0][2]
    idx = torch.arange(ref.height * ref.width).reshape(ref.height, ref.width)[8:-8:3, 8:-8:3].reshape(-1)
    scales = torch.tensor([0.9, 0.95, 0.98, 1.0, 1.02, 1.05, 1.1])
    d = depth_gt.reshape(-1)[idx][:, None] * scales
    n = normal_gt.reshape(3, -1)[:, idx].T[:, None].expand(-1, len(scales), 3).contiguous()
    inv_d, m_xy = _hypotheses(ref, d, n, idx)
    cost = bilateral_ncc_cost(sources, A, b, _pixels(ref, idx), inv_d, m_xy, offsets, win.values[idx],
                              win.weights[idx], win.mean[idx], win.var[idx], backend="torch")
    # bilinear resampling of a few-pixel-wavelength texture keeps the true cost slightly above 0
    assert (cost[:, 3] < 0.15).float().mean() > 0.9
    assert (cost.mean(-1).argmin(-1) == 3).float().mean() > 0.95


@pytest.mark.skipif(not numba_available(), reason="numba missing")
def test_numba_and_torch_backends_agree_including_borders_and_behind():
    views, renders, A, b, offsets, win, sources = _setup()
    ref = views[0]
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(ref.height * ref.width, (200,), generator=g)
    d = (renders[0][1].reshape(-1)[idx][:, None] * (0.5 + 1.5 * torch.rand(200, 6, generator=g)))
    d[:5, 0] = -1.0  # plane behind the reference: projects behind the sources
    n = torch.nn.functional.normalize(torch.randn(200, 6, 3, generator=g) + torch.tensor([0, 0, -2.0]), dim=-1)
    inv_d, m_xy = _hypotheses(ref, d, n, idx)
    args = (sources, A, b, _pixels(ref, idx), inv_d, m_xy, offsets, win.values[idx], win.weights[idx],
            win.mean[idx], win.var[idx])
    c_torch = bilateral_ncc_cost(*args, backend="torch", chunk_elements=5000)
    c_numba = bilateral_ncc_cost(*args, backend="numba")
    assert (c_torch == MAX_COST).any() and (c_torch < 0.5).any()
    assert torch.allclose(c_torch, c_numba, atol=2e-4)
    with pytest.raises(ValueError, match="window_offsets"):  # the numba kernel walks the regular grid
        bilateral_ncc_cost(*args[:6], offsets.flip(0), *args[7:], backend="numba")


def test_cost_is_invariant_to_source_and_reference_gain():
    views, renders, A, b, offsets, win, sources = _setup()
    ref = views[0]
    idx = torch.arange(ref.height * ref.width)[::37]
    d = renders[0][1].reshape(-1)[idx][:, None] * torch.tensor([1.0, 1.03])
    n = renders[0][2].reshape(3, -1)[:, idx].T[:, None].expand(-1, 2, 3).contiguous()
    inv_d, m_xy = _hypotheses(ref, d, n, idx)
    rest = (offsets, win.values[idx], win.weights[idx], win.mean[idx], win.var[idx])
    base = bilateral_ncc_cost(sources, A, b, _pixels(ref, idx), inv_d, m_xy, *rest, backend="torch")
    # a gain keeps the zero padding zero, so NCC is exactly invariant (also outside the sources)
    scaled = bilateral_ncc_cost(0.6 * sources, A, b, _pixels(ref, idx), inv_d, m_xy, *rest, backend="torch")
    assert ((base > 0.02) & (base < MAX_COST)).any()
    assert torch.allclose(scaled, base, atol=1e-4)
