"""The compiled plane depth against the torch operations it replaces: equal to the last bit."""

import numba
import pytest
import torch

from polargs_plugin.geometry import _PLANE_EPS, _image_rays, depth_from_plane, plane_distances, ray_plane_depth
from polargs_plugin.plane_depth import plane_depth_fused


def _torch_plane_depth(distance, normal, K, pixel_center=0.5):
    _, height, width = distance.shape
    rays = _image_rays(K.to(distance), height, width, pixel_center)
    return ray_plane_depth(distance[0], normal.permute(1, 2, 0), rays, min_cosine=_PLANE_EPS)[None]


def _inputs(dtype, seed, height=23, width=31):
    gen = torch.Generator().manual_seed(seed)
    K = torch.tensor([[40.0, 0.3, 15.2], [0.0, 38.0, 11.7], [0.0, 0.0, 1.0]], dtype=dtype)
    distance = torch.rand(1, height, width, generator=gen, dtype=dtype) * 3 - 0.5
    normal = torch.randn(3, height, width, generator=gen, dtype=dtype)
    # Planes met at exactly the floor and just above and below it, and a ray parallel to its plane.
    rays = _image_rays(K, height, width, 0.5)
    normal[:, 0, 0] = torch.tensor([0.0, 0.0, -_PLANE_EPS], dtype=dtype)
    normal[:, 0, 1] = torch.tensor([0.0, 0.0, -2 * _PLANE_EPS], dtype=dtype)
    normal[:, 0, 2] = torch.tensor([0.0, 0.0, -0.5 * _PLANE_EPS], dtype=dtype)
    normal[:, 0, 3] = torch.stack([rays[0, 3, 1], -rays[0, 3, 0], torch.zeros((), dtype=dtype)])
    grad = torch.randn(1, height, width, generator=gen, dtype=dtype)
    return distance, normal, K, grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_values_and_gradients_equal_the_torch_operations_bit_for_bit(dtype, seed):
    distance, normal, K, grad = _inputs(dtype, seed)
    d_ref, n_ref = distance.clone().requires_grad_(), normal.clone().requires_grad_()
    expected = _torch_plane_depth(d_ref, n_ref, K)
    expected_grads = torch.autograd.grad(expected, (d_ref, n_ref), grad)
    d, n = distance.clone().requires_grad_(), normal.clone().requires_grad_()
    got = depth_from_plane(d, n, K)  # CPU float: the compiled pass
    grads = torch.autograd.grad(got, (d, n), grad)
    assert got.grad_fn is not None and type(got.grad_fn).__name__ == "_PlaneDepthBackward"
    assert torch.equal(got, expected)
    assert all(torch.equal(a, b) for a, b in zip(grads, expected_grads))
    assert (got[0, 0, :4] == 0).tolist() == [True, False, True, True]  # the floor is exclusive


def test_analytic_tilted_plane_and_gradcheck():
    # The plane z = 2 + 0.5 x: n ~ (0.5, 0, -1) (unnormalised), d = 2 (n . x = -d at x = (0, 0, 2)).
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    normal = torch.tensor([0.5, 0.0, -1.0], dtype=torch.float64)[:, None, None].expand(3, 6, 8).contiguous()
    depth = depth_from_plane(torch.full((1, 6, 8), 2.0, dtype=torch.float64), normal, K)
    rays = _image_rays(K, 6, 8, 0.5)
    expected = 2.0 / (1.0 - 0.5 * rays[..., 0])  # z = 2 + 0.5 z r_x
    torch.testing.assert_close(depth[0], expected, rtol=1e-12, atol=0)
    rays = _image_rays(K, 6, 8, 0.5)
    distance = (torch.rand(1, 6, 8, dtype=torch.float64) + 0.5).requires_grad_()
    torch.autograd.gradcheck(lambda d, n: plane_depth_fused(d, n, rays, _PLANE_EPS), (distance, normal.clone().requires_grad_()))


def test_thread_count_and_the_rays_cache_do_not_change_the_result():
    distance, normal, K, _ = _inputs(torch.float32, 5, 40, 44)
    first = depth_from_plane(distance, normal, K)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        assert torch.equal(depth_from_plane(distance, normal, K), first)
    finally:
        numba.set_num_threads(previous)
    K2 = K.clone()
    K2[0, 2] += 1.0  # another camera: its own rays, not the cached ones
    assert torch.equal(depth_from_plane(distance, normal, K2), _torch_plane_depth(distance, normal, K2))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_plane_distances_equal_the_torch_operations_bit_for_bit(dtype):
    gen = torch.Generator().manual_seed(3)
    means = torch.randn(257, 3, generator=gen, dtype=dtype) * 2
    normals = torch.nn.functional.normalize(torch.randn(257, 3, generator=gen, dtype=dtype), dim=-1)
    angle = torch.tensor(0.7, dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = torch.tensor([[angle.cos(), 0, angle.sin()], [0, 1, 0], [-angle.sin(), 0, angle.cos()]], dtype=dtype)
    w2c[:3, 3] = torch.tensor([0.3, -0.2, 4.0], dtype=dtype)
    grad = torch.randn(257, generator=gen, dtype=dtype)
    m_ref, n_ref = means.clone().requires_grad_(), normals.clone().requires_grad_()
    expected = -(n_ref * (m_ref @ w2c[:3, :3].T + w2c[:3, 3])).sum(-1)
    expected_grads = torch.autograd.grad(expected, (m_ref, n_ref), grad)
    m, n = means.clone().requires_grad_(), normals.clone().requires_grad_()
    got = plane_distances(n, m, w2c)
    assert type(got.grad_fn).__name__ == "_PlaneDistancesBackward"
    assert torch.equal(got, expected)
    assert all(torch.equal(a, b) for a, b in zip(torch.autograd.grad(got, (m, n), grad), expected_grads))
    # Analytic: the camera-frame mean's distance along the normal, d = -n . (R mu + t).
    manual = -(normals * (means @ w2c[:3, :3].T + w2c[:3, 3])).sum(-1)
    torch.testing.assert_close(got.detach(), manual, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_plane_distances_with_a_camera_gradient_take_the_torch_operations():
    w2c = torch.eye(4, requires_grad=True)
    got = plane_distances(torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.3, 0.0, 1.0]]), w2c)
    got.sum().backward()
    # n = -z: d = (R mu + t)_z, so dd/dt_z = 1 and dd/dR_zx = mu_x
    assert got.tolist() == [1.0] and w2c.grad[2, 3] == 1.0 and abs(float(w2c.grad[2, 0]) - 0.3) < 1e-7
