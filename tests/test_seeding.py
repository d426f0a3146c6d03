"""Seeded Gaussians lie on the analytic surface with the normal as their shortest axis."""

import math

import pytest
import torch

from polargs_plugin.densify.seeding import frames_from_normals, plane_deviation, seed_gaussians, seed_mask
from test_patchmatch_scenes import make_scene


def _rotmat(q):
    """Independent wxyz quaternion -> rotation matrix (Hamilton convention)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def test_frames_are_rotations_with_the_normal_last():
    n = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    n[0] = torch.tensor([0.0, 0.0, 1.0])
    R = frames_from_normals(n)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3).expand(100, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(100), atol=1e-5)
    assert torch.allclose(R[..., 2], n, atol=1e-6)


def test_seeds_lie_on_the_plane_with_the_normal_as_shortest_axis():
    views, renders = make_scene("plane", size=32, num_sources=1)
    view, (img, depth, normal, mask) = views[0], renders[0]
    new = seed_gaussians(depth, normal, img, view.K, view.world_to_camera, mask, stride=2,
                         max_new=10_000, initial_opacity=0.3, thin_ratio=0.1)
    assert len(new) == 16 * 16
    assert new.means[:, 2].abs().max() < 1e-4  # the world plane z = 0
    R = _rotmat(new.quats)
    shortest = new.scales.argmin(-1)
    axis = R[torch.arange(len(new)), :, shortest]
    world_up = torch.tensor([0.0, 0.0, 1.0])
    assert torch.allclose(axis.abs() @ world_up, torch.ones(len(new)), atol=1e-4)
    focal = view.K[0, 0].item()
    d = depth[0, ::2, ::2].reshape(-1)
    assert torch.allclose(new.scales[:, 0], d * 2 / focal, rtol=1e-4)
    assert torch.allclose(new.scales[:, 2], 0.1 * new.scales[:, 0], rtol=1e-5)
    assert torch.allclose(new.colors, img[:, ::2, ::2].reshape(3, -1).T)
    assert torch.all(new.opacities == 0.3)


def test_cap_and_mask_and_opacity_check():
    views, renders = make_scene("plane", size=32, num_sources=1)
    view, (img, depth, normal, mask) = views[0], renders[0]
    g = torch.Generator().manual_seed(0)
    capped = seed_gaussians(depth, normal, img, view.K, view.world_to_camera, mask, stride=1, max_new=50, generator=g)
    assert len(capped) == 50
    empty = seed_gaussians(depth, normal, img, view.K, view.world_to_camera, torch.zeros_like(mask))
    assert len(empty) == 0
    with pytest.raises(ValueError, match="opacity"):
        seed_gaussians(depth, normal, img, view.K, view.world_to_camera, mask, initial_opacity=1.0)


def test_seed_mask_selects_holes_and_wrong_surfaces_only():
    depth = torch.full((1, 4, 4), 2.0)
    keep = torch.ones(1, 4, 4, dtype=torch.bool)
    rendered = depth.clone()
    alpha = torch.ones(1, 4, 4)
    alpha[0, 0, 0] = 0.1  # hole
    rendered[0, 1, 1] = 2.2  # wrong surface (10 %)
    rendered[0, 2, 2] = 2.01  # agrees within 2 %
    rendered[0, 2, 3] = 1.8  # an opaque surface 10 % in front of PatchMatch's
    keep[0, 3, 3] = False
    alpha[0, 3, 3] = 0.0  # a hole, but filtered out
    sel = seed_mask(keep, depth, rendered, alpha, alpha_threshold=0.5, relative_depth=0.02, behind=True)
    assert sel.sum() == 3 and sel[0, 0, 0] and sel[0, 1, 1] and sel[0, 2, 3]
    # The default (DensifyConfig's): no seed behind an opaque rendered surface (a mirror image's depth, say)
    sel = seed_mask(keep, depth, rendered, alpha, alpha_threshold=0.5, relative_depth=0.02)
    assert sel.sum() == 2 and sel[0, 0, 0] and sel[0, 1, 1]


def _plane_view(size=12, f=20.0):
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    rays = torch.einsum("ij,jhw->ihw", torch.linalg.inv(K), torch.stack(torch.meshgrid(
        torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="xy") + (torch.ones(size, size),)))
    return K, rays


def test_plane_deviation_is_zero_on_a_tilted_plane_and_large_at_an_occlusion_edge():
    """A plane steeply tilted (70 degrees) at a coarse resolution keeps every neighbour on the
    pixel's plane (deviation at float rounding), which a depth-range test would not; a second
    surface behind it gives the depth gap's share of the depth at the pixels beside the edge."""
    K, rays = _plane_view()
    n = torch.tensor([0.0, math.sin(math.radians(70)), -math.cos(math.radians(70))])  # facing the camera
    d_plane = 2.0  # n . X = -2
    depth = (-d_plane / torch.einsum("c,chw->hw", n, rays))[None]
    assert float((depth.max() - depth.min()) / depth.min()) > 0.5  # depth varies a lot across the image
    normal = n.view(3, 1, 1).expand(3, 12, 12)
    dev = plane_deviation(depth, normal, K)
    assert float(dev.max()) < 1e-5
    stepped = depth.clone()
    stepped[..., 6:] *= 1.5  # the right half is a surface 50 % farther
    dev = plane_deviation(stepped, normal, K)
    assert float(dev[..., 5].min()) > 0.4 and float(dev[..., :4].max()) < 1e-5 and float(dev[..., 7:].max()) < 1e-5
    holes = depth.clone()
    holes[..., 3, 3] = 0  # no depth: 0 there, and ignored as a neighbour
    dev = plane_deviation(holes, normal, K)
    assert dev[0, 3, 3] == 0 and float(dev.max()) < 1e-5


def test_seed_mask_skips_occlusion_edges():
    """A hole straddling an occlusion edge (fronto-parallel surfaces at 2.0 and 3.0): the pixels
    next to the edge are not seeded, the ones inside either surface are."""
    K, _ = _plane_view(size=8)
    depth = torch.full((1, 8, 8), 2.0)
    depth[..., 4:] = 3.0
    normal = torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1).expand(3, 8, 8)
    keep = torch.ones(1, 8, 8, dtype=torch.bool)
    alpha = torch.zeros(1, 8, 8)  # a hole everywhere
    sel = seed_mask(keep, depth, torch.zeros_like(depth), alpha, normal=normal, K=K, max_plane_deviation=0.04)
    assert not sel[..., 3:5].any() and sel[..., :3].all() and sel[..., 5:].all()
    assert seed_mask(keep, depth, torch.zeros_like(depth), alpha).all()  # no planarity test
    with pytest.raises(ValueError, match="normal"):
        seed_mask(keep, depth, torch.zeros_like(depth), alpha, max_plane_deviation=0.04)
