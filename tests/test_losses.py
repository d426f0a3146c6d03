"""Losses: hand cases, analytic geometry, finite-difference gradients, edge cases without NaN."""

import math

import kornia
import torch

from polargs_plugin.losses import (
    ReflectiveTargets,
    depth_normal_loss,
    depth_to_points,
    normal_from_depth,
    normal_loss,
    normals_within,
    photometric_loss,
    reflective_loss,
    reflective_replacement,
    scale_loss,
)

K = torch.tensor([[40.0, 0.0, 11.0], [0.0, 45.0, 9.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _plane_depth(normal, offset, H=18, W=22, dtype=torch.float64):
    """Camera-z depth of the plane n . X = offset (n unit, camera frame)."""
    u = torch.arange(W, dtype=torch.float64) + 0.5
    v = torch.arange(H, dtype=torch.float64) + 0.5
    x = ((u[None, :] - K[0, 2]) / K[0, 0]).expand(H, W)
    y = ((v[:, None] - K[1, 2]) / K[1, 1]).expand(H, W)
    rays = torch.stack([x, y, torch.ones_like(x)])
    return (offset / torch.einsum("c,chw->hw", normal, rays))[None].to(dtype)


def test_photometric_l1_hand_case_and_partition():
    pred = torch.tensor([[[0.5, 0.2], [0.1, 0.9]]])
    target = torch.tensor([[[0.1, 0.2], [0.4, 0.9]]])
    mask = torch.tensor([[[True, False], [True, True]]])
    # L1 only: (0.4 + 0.3 + 0) summed over the mask, divided by H*W = 4.
    assert math.isclose(float(photometric_loss(pred, target, mask, ssim_weight=0.0)), 0.7 / 4, rel_tol=1e-6)
    # With SSIM: the whole-image loss is vanilla 3DGS's, and masked parts add up to it.
    pred, target = torch.rand(3, 16, 20), torch.rand(3, 16, 20)
    mask = torch.rand(1, 16, 20) < 0.3
    whole = photometric_loss(pred, target)
    ssim = kornia.metrics.ssim(pred[None], target[None], 11).mean()
    assert math.isclose(float(whole), float(0.8 * (pred - target).abs().mean() + 0.2 * (1 - ssim)), rel_tol=1e-5)
    parts = photometric_loss(pred, target, mask) + photometric_loss(pred, target, ~mask)
    assert math.isclose(float(parts), float(whole), rel_tol=1e-5)


def test_reflective_loss_is_plain_loss_when_targets_equal_image():
    pred, image = torch.rand(3, 14, 15), torch.rand(3, 14, 15)
    spec = torch.zeros(1, 14, 15, dtype=torch.bool)
    spec[:, 2:5, 3:7] = True
    over = torch.zeros_like(spec)
    over[:, 9:12, 8:10] = True
    l_s, l_o = reflective_loss(pred, image, spec, image, over, image)
    assert math.isclose(float(l_s), float(photometric_loss(pred, image, spec)), rel_tol=1e-6)
    assert math.isclose(float(l_o), float(photometric_loss(pred, image, over)), rel_tol=1e-6)
    # A different I_diff changes only L_s; with SSIM off, L_s is the L1 to I_diff on the mask.
    i_diff = torch.rand(3, 14, 15)
    l_s, l_o2 = reflective_loss(pred, image, spec, i_diff, over, image, ssim_weight=0.0)
    expected = float(((pred - i_diff).abs().mean(0, keepdim=True) * spec).sum() / (14 * 15))
    assert math.isclose(float(l_s), expected, rel_tol=1e-6)


def test_normal_from_depth_recovers_plane_normal():
    normal = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    depth = _plane_depth(normal, offset=float(normal @ torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)))
    points = depth_to_points(depth, K)
    assert torch.allclose(torch.einsum("c,chw->hw", normal, points), torch.full(depth.shape[-2:], float(normal[2]) * 2, dtype=torch.float64))
    got, valid = normal_from_depth(depth, K)
    assert int(valid.sum()) == (18 - 2) * (22 - 2)
    assert torch.allclose(got[:, valid[0]], normal[:, None].expand(3, int(valid.sum())), atol=1e-10)


def test_depth_normal_loss_analytic():
    normal = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    depth = _plane_depth(normal, offset=-2.0)
    alpha = torch.full_like(depth, 0.7)
    rendered = normal[:, None, None].expand(3, 18, 22) * 0.7  # alpha-weighted, not unit
    assert float(depth_normal_loss(depth, rendered, alpha, K)) < 1e-12
    tilt = 0.3
    tilted = torch.tensor([math.sin(tilt), 0.0, -math.cos(tilt)], dtype=torch.float64)[:, None, None].expand(3, 18, 22)
    assert math.isclose(float(depth_normal_loss(depth, tilted, alpha, K)), 1 - math.cos(tilt), rel_tol=1e-9)


def test_gradients_match_finite_differences():
    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 6, 7, generator=gen, dtype=torch.float64, requires_grad=True)
    target = torch.rand(2, 6, 7, generator=gen, dtype=torch.float64)
    mask = torch.rand(1, 6, 7, generator=gen) < 0.5
    assert torch.autograd.gradcheck(lambda p: photometric_loss(p, target, mask), (pred,), fast_mode=True)

    normal = torch.randn(3, 6, 7, generator=gen, dtype=torch.float64, requires_grad=True)
    goal = torch.nn.functional.normalize(torch.randn(3, 6, 7, generator=gen, dtype=torch.float64), dim=0)
    valid = torch.rand(1, 6, 7, generator=gen) < 0.6
    assert torch.autograd.gradcheck(lambda n: normal_loss(n, goal, valid), (normal,), fast_mode=True)

    plane = torch.tensor([0.2, 0.1, -1.0], dtype=torch.float64)
    depth0 = _plane_depth(plane / plane.norm(), -2.0, H=7, W=8)
    depth = (depth0 + 0.01 * torch.rand(depth0.shape, generator=gen, dtype=torch.float64)).requires_grad_()
    rendered = torch.randn(3, 7, 8, generator=gen, dtype=torch.float64, requires_grad=True)
    alpha = torch.rand(1, 7, 8, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d, n: depth_normal_loss(d, n, alpha, K), (depth, rendered), fast_mode=True)

    scales = torch.rand(5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(scale_loss, (scales,))


def test_normal_loss_hand_case_divides_by_view_pixels():
    # Rendered normals alpha-weighted: 0.5 * (0, 0, -1) is (0, 0, -1) once made unit.
    normal = torch.zeros(3, 4, 5, dtype=torch.float64)
    normal[2] = -0.5
    target = torch.zeros_like(normal)
    target[2] = -1.0
    target[:, 1, 2] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # |(0,0,-1) - (1,0,0)|_1 = 2
    target[:, 3, 4] = torch.tensor([0.0, -0.6, -0.8], dtype=torch.float64)  # 0.6 + 0.2 = 0.8
    valid = torch.zeros(1, 4, 5, dtype=torch.bool)
    valid[0, 1, 2] = valid[0, 3, 4] = valid[0, 0, 0] = True
    assert math.isclose(float(normal_loss(normal, target, valid)), (2.0 + 0.8 + 0.0) / 20, rel_tol=1e-12)
    # A pixel's weight does not depend on how many others have a target.
    valid[0, 0, 0] = False
    assert math.isclose(float(normal_loss(normal, target, valid)), 2.8 / 20, rel_tol=1e-12)
    assert float(normal_loss(normal, target, torch.zeros_like(valid))) == 0.0


def test_normals_within_random_rotations_any_length_and_zero_vectors():
    # Targets in random directions; each rendered normal is its target rotated by a known angle
    # about a random perpendicular axis (Rodrigues), scaled by a random alpha.
    gen = torch.Generator().manual_seed(3)
    target = torch.nn.functional.normalize(torch.randn(3, 6, 7, generator=gen, dtype=torch.float64), dim=0)
    axis = torch.linalg.cross(target, torch.randn(3, 6, 7, generator=gen, dtype=torch.float64), dim=0)
    axis = torch.nn.functional.normalize(axis, dim=0)
    angle = torch.linspace(0.0, 30.0, 42, dtype=torch.float64).view(6, 7)
    rad = torch.deg2rad(angle)
    rotated = target * torch.cos(rad) + torch.linalg.cross(axis, target, dim=0) * torch.sin(rad)
    normal = rotated * (0.1 + torch.rand(1, 6, 7, generator=gen, dtype=torch.float64))
    for max_deg in (5.0, 10.0, 20.0):
        inside = normals_within(normal, target, max_deg)
        assert inside.shape == (1, 6, 7)
        away = (angle - max_deg).abs() > 1e-6  # leave out angles on the boundary itself
        assert torch.equal(inside[0][away], (angle <= max_deg)[away])
    assert not normals_within(torch.zeros(3, 2, 2, dtype=torch.float64), target[:, :2, :2], 10.0).any()


def test_scale_loss_hand_case():
    scales = torch.tensor([[0.3, 0.1, 0.2], [0.05, 0.5, 0.4]])
    assert math.isclose(float(scale_loss(scales)), (0.1 + 0.05) / 2, rel_tol=1e-6)


def _finite_grads(loss, *tensors):
    assert torch.isfinite(loss)
    for grad in torch.autograd.grad(loss, tensors, allow_unused=True):
        assert grad is None or torch.isfinite(grad).all()


def test_edge_cases_stay_finite():
    H, W = 9, 10
    pred = torch.zeros(3, H, W, requires_grad=True)
    black = torch.zeros(3, H, W)  # s0 = 0
    empty = torch.zeros(1, H, W, dtype=torch.bool)
    loss = photometric_loss(pred, black, empty)
    assert float(loss) == 0
    _finite_grads(loss, pred)
    _finite_grads(photometric_loss(pred, black), pred)
    l_s, l_o = reflective_loss(pred, black, empty, black, empty, black)
    assert float(l_s) == 0 and float(l_o) == 0
    _finite_grads(l_s + l_o, pred)

    zero_normal = torch.zeros(3, H, W, requires_grad=True)
    goal = torch.zeros(3, H, W)
    goal[2] = -1
    _finite_grads(normal_loss(zero_normal, goal, torch.ones(1, H, W, dtype=torch.bool)), zero_normal)
    assert float(normal_loss(zero_normal, goal, empty)) == 0

    depth = torch.zeros(1, H, W, requires_grad=True)  # nothing rendered, alpha = 0
    alpha = torch.zeros(1, H, W)
    loss = depth_normal_loss(depth, zero_normal, alpha, K.float())
    assert float(loss) == 0
    _finite_grads(loss, depth, zero_normal)
    # alpha = 0 on a valid depth map: still 0, finite gradients.
    plane = _plane_depth(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), -2.0, H, W, torch.float32)
    plane.requires_grad_()
    _finite_grads(depth_normal_loss(plane, zero_normal, alpha, K.float()), plane, zero_normal)

    no_gaussians = torch.zeros(0, 3, requires_grad=True)
    loss = scale_loss(no_gaussians)
    assert float(loss) == 0
    _finite_grads(loss, no_gaussians)


def test_reflective_replacement_equals_whole_image_computation():
    gen = torch.Generator().manual_seed(4)
    pred, image = torch.rand(3, 30, 34, generator=gen), torch.rand(3, 30, 34, generator=gen)
    i_diff, i_chro = torch.rand(3, 30, 34, generator=gen), torch.rand(3, 30, 34, generator=gen)
    for box in [(slice(12, 16), slice(14, 19)), (slice(0, 3), slice(30, 34)), (slice(27, 30), slice(0, 2))]:
        spec = torch.zeros(1, 30, 34, dtype=torch.bool)
        over = torch.zeros_like(spec)
        spec[(0, *box)] = True
        over[0, box[0].start, box[1].start] = True
        spec &= ~over
        extra, l_s, l_o, plain = reflective_replacement(pred, image, spec, i_diff, over, i_chro, lambda_ref=0.6)
        # Whole-image reference: L_ref on the assembled target, plain loss on the reflective pixels.
        w_s, w_o = reflective_loss(pred, image, spec, i_diff, over, i_chro)
        w_plain = photometric_loss(pred, image, spec | over)
        assert torch.allclose(torch.stack([l_s, l_o, plain]), torch.stack([w_s, w_o, w_plain]), atol=1e-6)
        assert torch.allclose(extra, 0.6 * (w_s + w_o) - w_plain, atol=1e-6)
    empty = torch.zeros(1, 30, 34, dtype=torch.bool)
    pred.requires_grad_()
    extra, *_ = reflective_replacement(pred, image, empty, i_diff, empty, i_chro)
    extra.backward()
    assert float(extra) == 0 and float(pred.grad.abs().sum()) == 0


def test_reflective_targets_strategies_match_whole_image_values_and_gradients():
    """Sparse highlights (pixels strategy), and any mask with the box forced, against the
    whole-image kornia computation: values and gradients."""
    gen = torch.Generator().manual_seed(7)
    H, W = 40, 44
    pred = torch.rand(3, H, W, generator=gen, requires_grad=True)
    image, i_diff, i_chro = (torch.rand(3, H, W, generator=gen) for _ in range(3))
    for fraction in (0.01, 0.3):
        spec = torch.rand(1, H, W, generator=gen) < fraction
        spec[0, 0, :3] = True  # windows reflected at the image border
        spec[0, -2:, -1] = True
        over = (torch.rand(1, H, W, generator=gen) < fraction / 2) & ~spec
        w_s, w_o = reflective_loss(pred, image, spec, i_diff, over, i_chro)
        w_plain = photometric_loss(pred, image, spec | over)
        expected = 0.6 * (w_s + w_o) - w_plain
        (grad_expected,) = torch.autograd.grad(expected, pred)
        strategies = set()
        for limit in (1 << 20, 0):  # 0 forces the box
            targets = ReflectiveTargets(image, spec, i_diff, over, i_chro, max_window_elements=limit)
            strategies.add(targets.strategy)
            extra, l_s, l_o, plain = targets(pred, lambda_ref=0.6)
            assert torch.allclose(torch.stack([l_s, l_o, plain]), torch.stack([w_s, w_o, w_plain]), atol=1e-6)
            assert torch.allclose(extra, expected, atol=1e-6)
            (grad,) = torch.autograd.grad(extra, pred)
            assert torch.allclose(grad, grad_expected, atol=1e-7)
            # SSIM off: L1 only, analytic.
            _, l_s, _, plain = targets(pred, ssim_weight=0.0)
            l1 = (pred - image).abs().mean(0, keepdim=True)
            assert torch.allclose(plain, (l1 * (spec | over)).sum() / (H * W), atol=1e-7)
        assert strategies == ({"pixels", "box"} if fraction < 0.1 else {"box"})
