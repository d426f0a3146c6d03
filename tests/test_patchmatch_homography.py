"""Plane-induced homography sign conventions, checked against explicit point transfer."""

import math

import torch

from polargs_plugin.densify.homography import pixel_rays, plane_homography, relative_pose
from polargs_plugin.geometry import ray_plane_depth, ray_plane_distance
from test_patchmatch_scenes import intrinsics, look_at


def _cameras():
    K_ref = intrinsics(80.0, 64, 48)
    K_src = torch.tensor([[95.0, 0, 30.0], [0, 90.0, 26.0], [0, 0, 1]], dtype=torch.float64)
    ref = look_at((0.3, -3.0, 1.2))
    src = look_at((1.2, -2.7, 1.5), target=(0.1, 0.0, 0.2))
    return K_ref, K_src, ref, src


def test_relative_pose_maps_reference_points_to_source_points():
    _, _, ref, src = _cameras()
    x_world = torch.tensor([[0.2, -0.1, 0.3], [1.0, 0.5, -0.4]], dtype=torch.float64)
    x_ref = x_world @ ref[:3, :3].T + ref[:3, 3]
    x_src = x_world @ src[:3, :3].T + src[:3, 3]
    R, t = relative_pose(ref, src)
    assert torch.allclose(x_ref @ R.T + t, x_src, atol=1e-12)


def test_plane_homography_transfers_pixels_of_the_plane():
    K_ref, K_src, ref, src = _cameras()
    R, t = relative_pose(ref, src)
    g = torch.Generator().manual_seed(0)
    rays = pixel_rays(K_ref, 48, 64)
    for _ in range(5):
        u, v = int(torch.randint(64, (1,), generator=g)), int(torch.randint(48, (1,), generator=g))
        depth = torch.tensor(2.0 + torch.rand(1, generator=g, dtype=torch.float64).item())
        normal = torch.nn.functional.normalize(
            torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64) + 0.3 * torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        ray = rays[:, v, u]
        d_plane = ray_plane_distance(depth, normal, ray)
        assert d_plane > 0  # facing normal -> positive camera-to-plane distance
        H = plane_homography(K_ref, K_src, R, t, normal, d_plane)
        # another pixel q: intersect its ray with the plane through X_p, project explicitly
        x_p = depth * ray
        q = torch.tensor([u + 7.5, v - 3.5, 1.0], dtype=torch.float64)
        ray_q = torch.linalg.inv(K_ref) @ q
        x_q = ray_q * (normal @ x_p) / (normal @ ray_q)
        proj = K_src @ (R @ x_q + t)
        expected = proj[:2] / proj[2]
        mapped = H @ q
        assert torch.allclose(mapped[:2] / mapped[2], expected, atol=1e-9)
        # the plane depth at q from ray_plane_depth agrees with the explicit intersection
        assert math.isclose(float(ray_plane_depth(d_plane, normal, ray_q)), float(x_q[2]), rel_tol=1e-12)


def test_pixel_rays_have_unit_z_and_pixel_centres_at_half():
    K = intrinsics(50.0, 10, 8)
    rays = pixel_rays(K, 8, 10)
    assert torch.allclose(rays[2], torch.ones(8, 10, dtype=torch.float64))
    # pixel (u=5, v=4) centre (5.5, 4.5) lies 0.5 px right/below the principal point (5, 4)
    assert torch.allclose(rays[:2, 4, 5], torch.tensor([0.5 / 50, 0.5 / 50], dtype=torch.float64))
