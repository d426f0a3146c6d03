"""Fused SSIM (polargs_plugin.ssim) against kornia's metrics.ssim, the reference: values, gradients
(autograd of kornia, torch.autograd.gradcheck, central differences), edge cases, the torch (CUDA)
path, and the bit-exact box cut-out that the PC loss relies on."""

import kornia
import pytest
import torch

from polargs_plugin.losses import ReflectiveTargets, photometric_loss, photometric_loss_map, reflective_loss
from polargs_plugin.ssim import _ssim_torch, gaussian_filter, gaussian_kernel1d, ssim_map

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _images(shape, dtype=torch.float32, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=gen, dtype=dtype), torch.rand(shape, generator=gen, dtype=dtype)


class TestSSIMValues:
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("channels", [1, 2, 3])
    @pytest.mark.parametrize("batch", [1, 2])
    @pytest.mark.parametrize(("height", "width"), [(13, 17), (6, 7), (31, 23), (64, 65)])
    def test_matches_kornia(self, dtype, channels, batch, height, width):
        img1, img2 = _images((batch, channels, height, width), dtype, seed=height * width + channels)
        got = ssim_map(img1, img2, 11)
        expected = kornia.metrics.ssim(img1, img2, 11)
        assert got.shape == expected.shape and got.dtype == dtype
        assert (got - expected).abs().max() <= TOL[dtype]
        # The borders (reflected windows) on their own.
        for edge in (got[..., :5, :] - expected[..., :5, :], got[..., -5:] - expected[..., -5:]):
            assert edge.abs().max() <= TOL[dtype]

    @pytest.mark.parametrize("window", [1, 3, 5, 7, 9, 11, 13])
    def test_window_sizes(self, window):
        img1, img2 = _images((1, 3, 15, 14), torch.float64, seed=window)
        expected = kornia.metrics.ssim(img1, img2, window)
        assert torch.allclose(ssim_map(img1, img2, window), expected, atol=1e-12, rtol=0)

    def test_smallest_image_for_the_window(self):
        # 'reflect' padding needs H, W > window // 2: 6 x 6 with window 11 reflects whole rows.
        img1, img2 = _images((2, 6, 6), torch.float64, seed=3)
        expected = kornia.metrics.ssim(img1[None], img2[None], 11)[0]
        assert torch.allclose(ssim_map(img1, img2, 11), expected, atol=1e-12, rtol=0)
        with pytest.raises(ValueError, match="reflect"):
            ssim_map(img1[:, :5], img2[:, :5], 11)

    def test_shapes_and_dtypes(self):
        img1, img2 = _images((3, 10, 12))
        base = ssim_map(img1, img2)
        assert base.shape == (3, 10, 12)
        assert torch.equal(ssim_map(img1[None], img2[None])[0], base)
        assert torch.equal(ssim_map(img1[0], img2[0]), base[0])
        half = ssim_map(img1.half(), img2.half())
        assert half.dtype == torch.float32
        assert torch.allclose(half, ssim_map(img1.half().float(), img2.half().float()))
        mixed = ssim_map(img1, img2.double())
        assert mixed.dtype == torch.float64
        assert torch.allclose(mixed, ssim_map(img1.double(), img2.double()))
        assert ssim_map(torch.zeros(0, 3, 8, 8), torch.zeros(0, 3, 8, 8)).shape == (0, 3, 8, 8)

    def test_errors(self):
        img1, img2 = _images((3, 10, 12))
        with pytest.raises(ValueError, match="differ in shape"):
            ssim_map(img1, img2[:2])
        with pytest.raises(ValueError, match="odd"):
            ssim_map(img1, img2, 4)
        with pytest.raises(ValueError, match="H, W"):
            ssim_map(img1[0, 0], img2[0, 0])  # 1-D
        with pytest.raises(TypeError):
            ssim_map(img1.numpy(), img2)

    def test_identical_images_score_one(self):
        img1, _ = _images((1, 3, 21, 19))
        img1.requires_grad_()
        same = ssim_map(img1, img1.detach())
        assert torch.allclose(same, torch.ones_like(same), atol=1e-6, rtol=0)
        # SSIM(x, x) is the maximum: zero gradient.
        (grad,) = torch.autograd.grad(same.sum(), img1)
        assert grad.abs().max() < 1e-4
        flat = torch.full((1, 9, 9), 0.3, dtype=torch.float64)
        assert torch.allclose(ssim_map(flat, flat), torch.ones_like(flat), atol=1e-8, rtol=0)

    def test_kernel_is_kornias(self):
        for window in (3, 7, 11):
            for dtype in (torch.float32, torch.float64):
                expected = kornia.filters.get_gaussian_kernel1d(window, 1.5, dtype=dtype)[0]
                assert torch.allclose(gaussian_kernel1d(window, dtype=dtype), expected, atol=1e-7, rtol=0)

    def test_threads_do_not_change_the_result(self):
        img1, img2 = _images((3, 37, 41))
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            one = ssim_map(img1, img2)
            torch.set_num_threads(2)
            two = ssim_map(img1, img2)
        finally:
            torch.set_num_threads(threads)
        assert torch.equal(one, two)


class TestSSIMGradients:
    @pytest.mark.parametrize("shape", [(1, 2, 7, 9), pytest.param((3, 6, 6), marks=pytest.mark.slow),
                                       pytest.param((2, 11, 8), marks=pytest.mark.slow)])
    def test_gradcheck(self, shape):
        img1, img2 = _images(shape, torch.float64, seed=sum(shape))
        img1.requires_grad_()
        img2.requires_grad_()
        window = min(11, 2 * min(shape[-2:]) - 1)
        assert torch.autograd.gradcheck(ssim_map, (img1, img2, window), eps=1e-6, atol=1e-8)
        assert torch.autograd.gradcheck(lambda a: ssim_map(a, img2.detach(), 5), (img1,), eps=1e-6, atol=1e-8)
        assert torch.autograd.gradcheck(lambda b: ssim_map(img1.detach(), b, 5), (img2,), eps=1e-6, atol=1e-8)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize(("channels", "height", "width"), [(1, 9, 13), (3, 32, 29), (2, 64, 64)])
    def test_gradients_match_kornia(self, dtype, channels, height, width):
        img1, img2 = _images((1, channels, height, width), dtype, seed=channels + height)
        weights = torch.rand(1, channels, height, width, generator=torch.Generator().manual_seed(1), dtype=dtype)
        grads = []
        for fn in (ssim_map, kornia.metrics.ssim):
            a, b = img1.clone().requires_grad_(), img2.clone().requires_grad_()
            # Loss-like scaling (a weighted mean), as the colour loss backpropagates.
            loss = (fn(a, b, 11) * weights).sum() / weights.numel()
            grads.append(torch.autograd.grad(loss, (a, b)))
        (ga, gb), (ka, kb) = grads
        tol = 1e-5 * float(ka.abs().max()) if dtype == torch.float32 else 1e-12
        assert (ga - ka).abs().max() <= max(tol, 1e-9)
        assert (gb - kb).abs().max() <= max(tol, 1e-9)
        # Unscaled (sum of the map): still within 1e-5 of kornia's float32 autograd.
        a = img1.clone().requires_grad_()
        (g,) = torch.autograd.grad(ssim_map(a, img2, 11).sum(), a)
        a = img1.clone().requires_grad_()
        (k,) = torch.autograd.grad(kornia.metrics.ssim(a, img2, 11).sum(), a)
        assert (g - k).abs().max() <= TOL[dtype] * 10 * max(1.0, float(k.abs().max()))

    def test_central_differences_at_borders_and_interior(self):
        img1, img2 = _images((2, 12, 10), torch.float64, seed=5)
        weights = torch.rand(2, 12, 10, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        a = img1.clone().requires_grad_()
        (grad,) = torch.autograd.grad((ssim_map(a, img2) * weights).sum(), a)
        step = 1e-6
        for index in [(0, 0, 0), (1, 11, 9), (0, 0, 9), (1, 5, 0), (0, 6, 4), (1, 1, 8), (0, 10, 1)]:
            plus, minus = img1.clone(), img1.clone()
            plus[index] += step
            minus[index] -= step
            numeric = ((ssim_map(plus, img2) - ssim_map(minus, img2)) * weights).sum() / (2 * step)
            assert abs(float(numeric) - float(grad[index])) < 1e-7

    def test_needs_input_grad(self):
        img1, img2 = _images((3, 9, 10))
        b = img2.clone().requires_grad_()
        out = ssim_map(img1, b)
        assert out.requires_grad
        out.sum().backward()
        assert img1.grad is None and b.grad is not None
        k = img2.clone().requires_grad_()
        kornia.metrics.ssim(img1[None], k[None], 11).sum().backward()
        assert torch.allclose(b.grad, k.grad, atol=1e-5, rtol=0)
        with torch.no_grad():
            assert not ssim_map(img1, b).requires_grad
        assert not ssim_map(img1, img2).requires_grad
        # Expanded (broadcast) predictions, as the losses pass them: gradients summed.
        pred = img1.clone().requires_grad_()
        targets = torch.stack([img2, img1.flip(-1)])
        ssim_map(pred.expand_as(targets), targets).sum().backward()
        expected = sum(torch.autograd.grad(ssim_map(p, t).sum(), p)[0] for p, t in
                       ((img1.clone().requires_grad_(), img2), (img1.clone().requires_grad_(), img1.flip(-1))))
        assert torch.allclose(pred.grad, expected, atol=1e-6, rtol=0)


class TestTorchPath:
    """The non-CPU path (separable conv2d, autograd), checked on the CPU."""

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_matches_fused_and_kornia(self, dtype):
        img1, img2 = _images((3, 19, 24), dtype, seed=11)
        kernel = gaussian_kernel1d(11, dtype=dtype)
        a = img1.clone().requires_grad_()
        torch_map = _ssim_torch(a, img2, kernel)
        (torch_grad,) = torch.autograd.grad(torch_map.mean(), a)
        a = img1.clone().requires_grad_()
        fused = ssim_map(a, img2)
        (fused_grad,) = torch.autograd.grad(fused.mean(), a)
        assert (torch_map - fused).abs().max() <= TOL[dtype]
        assert (torch_map - kornia.metrics.ssim(img1[None], img2[None], 11)[0]).abs().max() <= TOL[dtype]
        assert (torch_grad - fused_grad).abs().max() <= TOL[dtype] * 1e-2

    def test_gaussian_filter_is_kornias(self):
        img, _ = _images((2, 3, 14, 16), torch.float64)
        kernel = gaussian_kernel1d(11, dtype=torch.float64)
        expected = kornia.filters.filter2d_separable(img, kernel[None], kernel[None], border_type="reflect")
        assert torch.allclose(gaussian_filter(img, kernel), expected, atol=1e-14, rtol=0)


class TestLosses:
    def test_box_cut_out_is_bit_exact(self):
        """The SSIM of a cut-out equals the whole image's wherever the cut-out holds the whole
        window or meets the image border: what makes the PC loss cancel the trainer's exactly."""
        img1, img2 = _images((3, 40, 44), seed=8)
        whole = ssim_map(img1, img2)
        rows, cols = slice(10, 30), slice(0, 20)
        part = ssim_map(img1[:, rows, cols], img2[:, rows, cols])
        assert torch.equal(part[:, 5:-5, :-5], whole[:, 15:25, 0:15])

    def test_photometric_loss_uses_kornias_ssim(self):
        pred, target = _images((3, 33, 27), seed=9)
        ssim = kornia.metrics.ssim(pred[None], target[None], 11)[0].mean(0, keepdim=True)
        expected = (0.8 * (pred - target).abs().mean(0, keepdim=True) + 0.2 * (1 - ssim)).mean()
        assert abs(float(photometric_loss(pred, target)) - float(expected)) < 1e-6
        small_pred, small_target = _images((3, 4, 5), seed=10)  # window shrunk to 7
        ssim = kornia.metrics.ssim(small_pred[None], small_target[None], 7)[0].mean(0, keepdim=True)
        expected = (0.8 * (small_pred - small_target).abs().mean(0, keepdim=True) + 0.2 * (1 - ssim)).mean()
        assert abs(float(photometric_loss(small_pred, small_target)) - float(expected)) < 1e-6

    def test_reflective_targets_box_cancels_exactly(self):
        """Box strategy: per-pixel losses on the reflective pixels equal the whole-image ones bit
        for bit (the masked sums then differ by the summation order at most)."""
        gen = torch.Generator().manual_seed(12)
        H, W = 36, 40
        pred = torch.rand(3, H, W, generator=gen, requires_grad=True)
        image, i_diff, i_chro = (torch.rand(3, H, W, generator=gen) for _ in range(3))
        spec = torch.rand(1, H, W, generator=gen) < 0.2
        spec[0, 0, 0] = True
        over = (torch.rand(1, H, W, generator=gen) < 0.05) & ~spec
        targets = ReflectiveTargets(image, spec, i_diff, over, i_chro, max_window_elements=0)
        assert targets.strategy == "box"
        corrected, plain = targets._losses(pred, 0.2)
        rows, cols = targets.box
        reflective = targets.reflective[0]
        whole_plain = photometric_loss_map(pred, image)[0][rows, cols]
        assert torch.equal(plain[reflective], whole_plain[reflective])
        assembled = torch.where(spec, i_diff, torch.where(over, i_chro, image))
        whole_corrected = photometric_loss_map(pred, assembled)[0][rows, cols]
        assert torch.equal(corrected[reflective], whole_corrected[reflective])
        extra, l_s, l_o, l_plain = targets(pred, lambda_ref=1.0)
        w_s, w_o = reflective_loss(pred, image, spec, i_diff, over, i_chro)
        expected = torch.stack([w_s, w_o, photometric_loss(pred, image, spec | over)])
        assert torch.allclose(torch.stack([l_s, l_o, l_plain]), expected, atol=1e-8, rtol=0)
        # Gradients of the replacement against the whole-image computation.
        (grad,) = torch.autograd.grad(extra, pred)
        (grad_expected,) = torch.autograd.grad(w_s + w_o - expected[2], pred)
        assert torch.allclose(grad, grad_expected, atol=1e-9, rtol=0)
