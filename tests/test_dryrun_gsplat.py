"""Dry runs of gsplat's simple_trainer: the CPU stand-ins of ``gsplat.rasterization``, fused-ssim and
MCMC's relocation against the reference rasterizer and analytic truth, and the probe on gsplat's
strategies."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize as reference
from polargs_plugin.dryrun.standins import fused_ssim as fused
from polargs_plugin.dryrun.standins import gsplat as standin
from polargs_plugin.kit.patching import main as patch_main
from polargs_plugin.service.dryrun import DryRunRequest, describe, dry_run

ROOT = Path(__file__).resolve().parents[1]
TRAINERS = Path(__file__).resolve().parent / "data" / "trainers"

N, W, H = 120, 40, 30


@pytest.fixture(scope="module")
def gaussians():
    g = torch.Generator().manual_seed(3)
    means = torch.randn(N, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.nn.functional.normalize(torch.randn(N, 4, generator=g), dim=-1)
    scales = torch.rand(N, 3, generator=g) * 0.08 + 0.02
    opac = torch.rand(N, generator=g) * 0.8 + 0.1
    sh = torch.randn(N, 4, 3, generator=g) * 0.3
    return means, quats, scales, opac, sh


def _K() -> torch.Tensor:
    f = W / (2 * math.tan(0.4))
    return torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])


def _viewmat() -> torch.Tensor:
    """A camera half a unit to the left of the world origin, looking along +z."""
    view = torch.eye(4)
    view[0, 3] = 0.5
    return view


def test_rasterization_matches_the_reference_with_sh_background_and_pixel_gradients(gaussians) -> None:
    means, quats, scales, opac, sh = gaussians
    means = means.clone().requires_grad_()
    background = torch.tensor([0.1, 0.2, 0.3])
    colors, alphas, meta = standin.rasterization(
        means, quats, scales, opac, sh, _viewmat()[None], _K()[None], W, H, sh_degree=1, packed=False,
        backgrounds=background[None], absgrad=True)
    ref = reference(means, quats, scales, opac, sh, _K(), _viewmat(), W, H, background=background, near=0.01, far=1e10,
                    backend="torch")
    assert colors.shape == (1, H, W, 3) and alphas.shape == (1, H, W, 1)
    assert torch.allclose(colors[0].permute(2, 0, 1), ref.color, atol=1e-5)
    assert torch.allclose(alphas[0].permute(2, 0, 1), ref.alpha, atol=1e-5)
    means2d = meta["means2d"]
    means2d.retain_grad()  # as DefaultStrategy.step_pre_backward does
    weights = torch.linspace(-1, 1, W)
    (colors[0].permute(2, 0, 1) * weights).sum().backward(retain_graph=True)
    (ref.color * weights).sum().backward()
    assert means2d.shape == (1, N, 2)
    # gsplat's means2d gradient is in pixels, as the reference's
    assert torch.allclose(means2d.grad[0], ref.means2d.grad, rtol=1e-4, atol=1e-6)
    assert int((means2d.grad[0].abs().sum(1) > 0).sum()) > N // 2
    # the absolute gradient bounds the signed one
    assert (means2d.absgrad[0] >= means2d.grad[0].abs() - 1e-6).all()
    assert (means2d.absgrad[0] > means2d.grad[0].abs() + 1e-6).any()


def test_radii_are_gsplat_s_3_33_sigma_per_axis() -> None:
    # a round Gaussian of scale s at depth z on the axis: screen variance (f s / z)^2 + 0.3 on both axes
    s, z = 0.05, 3.0
    _, _, meta = standin.rasterization(
        torch.tensor([[0.0, 0.0, z]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), s), torch.tensor([0.9]),
        torch.ones(1, 3), torch.eye(4)[None], _K()[None], W, H, packed=False)
    f = _K()[0, 0].item()
    radius = math.ceil(3.33 * math.sqrt((f * s / z) ** 2 + 0.3))
    assert meta["radii"].dtype == torch.int32 and meta["radii"].tolist() == [[[radius, radius]]]
    # behind the near plane: culled
    _, _, behind = standin.rasterization(
        torch.tensor([[0.0, 0.0, 0.005]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), s), torch.tensor([0.9]),
        torch.ones(1, 3), torch.eye(4)[None], _K()[None], W, H, packed=False)
    assert behind["radii"].tolist() == [[[0, 0]]]


def test_expected_depth_mode_divides_by_alpha() -> None:
    # one opaque flat Gaussian at depth z: RGB+ED's last channel is z wherever it covers the pixel
    z = 2.5
    colors, alphas, _ = standin.rasterization(
        torch.tensor([[0.0, 0.0, z]]), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[0.5, 0.5, 1e-4]]),
        torch.tensor([0.8]), torch.ones(1, 3), torch.eye(4)[None], _K()[None], W, H, packed=False,
        render_mode="RGB+ED")
    covered = alphas[0, ..., 0] > 0.1
    assert colors.shape == (1, H, W, 4) and int(covered.sum()) > 100
    assert torch.allclose(colors[0, ..., 3][covered], torch.full_like(colors[0, ..., 3][covered], z), rtol=1e-4)


def test_packed_rendering_is_refused_clearly(gaussians) -> None:
    means, quats, scales, opac, sh = gaussians
    with pytest.raises(NotImplementedError, match="packed=False"):
        standin.rasterization(means, quats, scales, opac, sh[:, 0], torch.eye(4)[None], _K()[None], W, H, packed=True)


def _ssim_by_hand(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM of two [1, C, H, W] images: 11x11 Gaussian window (sigma 1.5), valid positions only."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    window = (g[:, None] * g[None, :]) / g.sum() ** 2
    c = a.shape[1]
    kernel = window.expand(c, 1, 11, 11)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.conv2d(t, kernel, groups=c)

    a, b = a.double(), b.double()
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))).mean()


def test_fused_ssim_valid_padding_is_the_windowed_ssim() -> None:
    g = torch.Generator().manual_seed(5)
    a = torch.rand(1, 3, 24, 28, generator=g)
    b = (a + 0.1 * torch.randn(1, 3, 24, 28, generator=g)).clamp(0, 1)
    a.requires_grad_()
    value = fused.fused_ssim(a, b, padding="valid")
    assert value.item() == pytest.approx(_ssim_by_hand(a.detach(), b).item(), abs=1e-5)
    assert fused.fused_ssim(b, b, padding="valid").item() == pytest.approx(1.0, abs=1e-6)
    value.backward()
    assert a.grad is not None and a.grad.abs().sum() > 0


def test_relocation_keeps_the_centre_opacity_and_one_copy_unchanged() -> None:
    binoms = torch.tensor([[math.comb(n, k) for k in range(8)] for n in range(8)], dtype=torch.float32)
    opac = torch.tensor([0.3, 0.6, 0.9, 0.5])
    scales = torch.ones(4, 3)
    ratios = torch.tensor([1, 2, 3, 8])
    new_opac, new_scales = standin.compute_relocation(opac, scales, ratios, binoms)
    # n copies of opacity o' stacked at the centre composite to the old opacity: 1 - (1 - o')^n = o
    assert torch.allclose(1 - (1 - new_opac) ** ratios.float(), opac, atol=1e-6)
    assert new_opac[0] == opac[0] and torch.allclose(new_scales[0], scales[0])
    # two copies (MCMC paper, Eq. 9): scale o / (o' + o' - o'^2 / sqrt 2) of the old one
    o1 = new_opac[1]
    assert new_scales[1, 0].item() == pytest.approx((opac[1] / (2 * o1 - o1**2 / math.sqrt(2))).item(), rel=1e-6)


def test_the_probe_reads_the_strategy_arguments_given_through_kwargs() -> None:
    # gsplat's base Strategy.step_pre_backward(*args, **kwargs), which MCMCStrategy inherits
    strategy_module = pytest.importorskip("gsplat.strategy.base")
    from polargs_plugin.dryrun.probe_gsplat import GsplatProbe

    probe = GsplatProbe(None)
    probe._wrap(strategy_module.Strategy, "step_pre_backward", probe._step_pre_backward)
    try:
        params = {"means": torch.nn.Parameter(torch.zeros(5, 3))}
        strategy_module.Strategy().step_pre_backward(params=params, optimizers={}, state={}, step=0, info={})
    finally:
        probe.uninstall()
    assert probe.params is params and probe.initial_gaussians == 5 and probe._started()


def _gsplat_anchors():
    import importlib.util

    spec = importlib.util.spec_from_file_location("_gsplat_patch", ROOT / "adapters" / "gsplat" / "patch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.ANCHORS


@pytest.mark.slow
@pytest.mark.parametrize("trainer", ["gsplat", "gsplat-mcmc"])
def test_dry_run_of_the_placeholder_simple_trainer(trainer: str, tmp_path: Path) -> None:
    pytest.importorskip("gsplat")
    pytest.importorskip("tqdm")
    checkout = tmp_path / "examples"
    shutil.copytree(TRAINERS / "gsplat_support", checkout, ignore=shutil.ignore_patterns("README.md"))
    shutil.copy(TRAINERS / "gsplat_dryrun_simple_trainer.py", checkout / "simple_trainer.py")
    assert patch_main([str(checkout)], _gsplat_anchors(), "test", filename="simple_trainer.py") == 0
    before = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    # the unpatched run (the same script, PolarGS lines stripped) once, with DefaultStrategy
    request = DryRunRequest(checkout=checkout, trainer=trainer, workdir=tmp_path / "work", iterations=64, interval=8,
                            views=16, width=32, height=24, compare=trainer == "gsplat")
    result = dry_run(request)
    assert result.ok, "\n".join(describe(result.checks)) + "\n" + result.logs["patched"].read_text()[-3000:]
    names = {c.name for c in result.checks}
    assert {"finished (patched)", "Dense appended and survived (patched)", "checkpoint (patched)"} <= names
    after = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    assert after == before  # nothing written into the checkout


def test_dense_rows_follow_gsplat_s_ops() -> None:
    from polargs_plugin.dryrun.probe_gsplat import _rows_after

    rows = torch.tensor([True, False, True, True])
    mask = torch.tensor([True, True, False, False])
    # duplicate appends copies (not Dense's); split drops the parents and appends two children each
    assert _rows_after("duplicate", rows, {"mask": mask}).tolist() == [True, False, True, True, False, False]
    assert _rows_after("split", rows, {"mask": mask}).tolist() == [True, True, False, False, False, False]
    assert _rows_after("remove", rows, {"mask": mask}).tolist() == [True, True]
    # relocation overwrites the masked rows in place; sample_add appends n new ones
    assert _rows_after("relocate", rows, {"mask": mask}).tolist() == [False, False, True, True]
    assert _rows_after("sample_add", rows, {"n": 2}).tolist() == [True, False, True, True, False, False]
