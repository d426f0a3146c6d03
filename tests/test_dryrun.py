"""Dry runs: the CPU stand-ins of the upstream CUDA extensions against the reference rasterizer and
each fork's output contract, the CUDA->CPU mapping, the import hook, the probe, and a dry run of
the placeholder graphdeco trainer (tests/data/trainers/, with inria_support/ as its modules)."""

from __future__ import annotations

import json
import math
import shutil
import sys
import types
from pathlib import Path

import pytest
import torch

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.dryrun import cuda_cpu
from polargs_plugin.dryrun.finder import install_standins
from polargs_plugin.dryrun.probe import state_problems
from polargs_plugin.dryrun.standins import gof, graphdeco_2023, graphdeco_2024, plane, simple_knn, surfel
from polargs_plugin.kit.patching import main as patch_main
from polargs_plugin.service.dryrun import Check, DryRunRequest, describe, dry_run, verdict
from provenance_check import check_provenance

ROOT = Path(__file__).resolve().parents[1]
TRAINERS = Path(__file__).resolve().parent / "data" / "trainers"
N, W, H = 120, 40, 30
FOVX = 0.8
FOVY = 2 * math.atan(math.tan(FOVX / 2) * H / W)


@pytest.fixture(scope="module")
def gaussians():
    g = torch.Generator().manual_seed(1)
    means = torch.randn(N, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.nn.functional.normalize(torch.randn(N, 4, generator=g), dim=-1)
    scales = torch.rand(N, 3, generator=g) * 0.08 + 0.02
    opac = torch.rand(N, generator=g) * 0.8 + 0.1
    colors = torch.rand(N, 3, generator=g)
    return means, quats, scales, opac, colors


def _view() -> torch.Tensor:
    return torch.eye(4)  # world = camera; its transpose is the same


def _K() -> torch.Tensor:
    fx, fy = W / (2 * math.tan(FOVX / 2)), H / (2 * math.tan(FOVY / 2))
    return torch.tensor([[fx, 0, W / 2], [0, fy, H / 2], [0, 0, 1.0]])


def _screen() -> torch.Tensor:
    t = torch.zeros(N, 3, requires_grad=True) + 0
    t.retain_grad()
    return t


def _settings_2023(**extra):
    return graphdeco_2023.GaussianRasterizationSettings(
        H, W, math.tan(FOVX / 2), math.tan(FOVY / 2), torch.tensor([0.2, 0.3, 0.4]), 1.0, _view(), _view(), 0,
        torch.zeros(3), False, False)


def test_graphdeco_2023_matches_the_reference_and_gives_ndc_screen_gradients(gaussians) -> None:
    means, quats, scales, opac, colors = gaussians
    means = means.clone().requires_grad_()
    screen = _screen()
    image, radii = graphdeco_2023.GaussianRasterizer(_settings_2023())(
        means, screen, opac[:, None], colors_precomp=colors, scales=scales, rotations=quats)
    ref = rasterize(means, quats, scales, opac, colors, _K(), torch.eye(4), W, H, near=0.2, backend="torch",
                    background=torch.tensor([0.2, 0.3, 0.4]))
    assert image.shape == (3, H, W) and radii.dtype == torch.int32 and radii.shape == (N,)
    assert torch.allclose(image, ref.color, atol=1e-6)
    (image * torch.linspace(0, 1, W)).sum().backward(retain_graph=True)
    (ref.color * torch.linspace(0, 1, W)).sum().backward()
    # upstream's means2D gradient is dL/d(pixel) times W/2 (x) and H/2 (y): the NDC units.
    # atol: float32 summation error, eps_f32 x sum|per-pixel terms| (up to 80 here) = 1e-5; seen 1.4e-5
    assert torch.allclose(screen.grad[:, 0], ref.means2d.grad[:, 0] * W / 2, rtol=1e-4, atol=2e-5)
    assert torch.allclose(screen.grad[:, 1], ref.means2d.grad[:, 1] * H / 2, rtol=1e-4, atol=2e-5)
    assert int((screen.grad[:, :2].abs().sum(1) > 0).sum()) > N // 2


def test_radii_are_three_sigma_of_the_dilated_covariance() -> None:
    # one round Gaussian of scale s at depth z on the axis: screen variance v = (f s / z)^2 + 0.3 on
    # both axes, and upstream's largest eigenvalue is mid + sqrt(max(0.1, mid^2 - det)) = v + sqrt(0.1)
    s, z = 0.05, 3.0
    settings = _settings_2023()
    _, radii = graphdeco_2023.GaussianRasterizer(settings)(
        torch.tensor([[0.0, 0.0, z]]), torch.zeros(1, 3), torch.tensor([[0.9]]), colors_precomp=torch.ones(1, 3),
        scales=torch.full((1, 3), s), rotations=torch.tensor([[1.0, 0, 0, 0]]))
    fx = _K()[0, 0].item()
    assert radii.item() == math.ceil(3 * math.sqrt((fx * s / z) ** 2 + 0.3 + math.sqrt(0.1)))


def test_graphdeco_2024_inverse_depth_and_dc(gaussians) -> None:
    means, quats, scales, opac, colors = gaussians
    settings = graphdeco_2024.GaussianRasterizationSettings(*_settings_2023(), antialiasing=False)
    sh = torch.rand(N, 4, 3)
    rasterizer = graphdeco_2024.GaussianRasterizer(settings)
    image, radii, invdepth = rasterizer(means, _screen(), opac[:, None], shs=sh[:, 1:], dc=sh[:, :1],
                                        scales=scales, rotations=quats)
    together, _, _ = rasterizer(means, _screen(), opac[:, None], shs=sh, scales=scales, rotations=quats)
    assert torch.equal(image, together) and invdepth.shape == (1, H, W)
    # one opaque Gaussian: the inverse depth is alpha / z of its mean
    one = rasterizer(torch.tensor([[0.0, 0.0, 2.0]]), torch.zeros(1, 3), torch.tensor([[0.9]]),
                     colors_precomp=torch.ones(1, 3), scales=torch.full((1, 3), 0.3), rotations=torch.tensor([[1.0, 0, 0, 0]]))
    alpha = (one[0] - 0.2 * 0 - torch.tensor([0.2, 0.3, 0.4])[:, None, None]).abs()  # colour 1 over the background
    centre = one[2][0, H // 2, W // 2]
    assert centre.item() == pytest.approx(alpha[0, H // 2, W // 2].item() / 0.8 / 2.0, rel=1e-4)


def test_antialiasing_scales_opacity_by_the_determinant_ratio() -> None:
    s, z = 0.01, 3.0  # a footprint well under a pixel: the 0.3 px^2 dilation dominates
    args = dict(colors_precomp=torch.ones(1, 3), scales=torch.full((1, 3), s), rotations=torch.tensor([[1.0, 0, 0, 0]]))
    base = _settings_2023()._replace(bg=torch.zeros(3))
    plain = graphdeco_2024.GaussianRasterizer(graphdeco_2024.GaussianRasterizationSettings(*base, antialiasing=False))
    aa = graphdeco_2024.GaussianRasterizer(graphdeco_2024.GaussianRasterizationSettings(*base, antialiasing=True))
    mean = torch.tensor([[0.0, 0.0, z]])
    a = plain(mean, torch.zeros(1, 3), torch.tensor([[0.5]]), **args)[0].max()
    b = aa(mean, torch.zeros(1, 3), torch.tensor([[0.5]]), **args)[0].max()
    var = (_K()[0, 0].item() * s / z) ** 2
    # same footprint, opacity times sqrt(det(cov) / det(cov + 0.3 I)) = var / (var + 0.3) for a round one
    assert (b / a).item() == pytest.approx(var / (var + 0.3), rel=1e-4)


def test_gof_channels_and_absolute_gradient(gaussians) -> None:
    means, quats, scales, opac, colors = gaussians
    settings = gof.GaussianRasterizationSettings(H, W, math.tan(FOVX / 2), math.tan(FOVY / 2), 0.0, torch.zeros(H, W, 2),
                                                 torch.zeros(3), 1.0, _view(), _view(), 0, torch.zeros(3), False, False)
    screen = _screen()
    render, radii = gof.GaussianRasterizer(settings)(means, screen, opac[:, None], colors_precomp=colors,
                                                     scales=scales, rotations=quats)
    ref = rasterize(means, quats, scales, opac, colors, _K(), torch.eye(4), W, H, near=0.2, backend="torch", eps2d=0.0)
    assert render.shape == (9, H, W) and len(gof.CHANNELS) == 9
    assert torch.allclose(render[0:3], ref.color, atol=1e-5)
    assert torch.allclose(render[3:6], ref.normal, atol=1e-5)
    assert torch.allclose(render[7:8], ref.alpha, atol=1e-5)
    assert (render[3:6][2][ref.alpha[0] > 0.5] < 0).all()  # facing the camera
    covered = ref.median_depth > 0
    assert torch.allclose(render[6:7][covered], ref.median_depth[covered], atol=1e-5)
    assert (render[8] >= -1e-6).all()
    (render[:3] * torch.linspace(-1, 1, W)).sum().backward()
    # the absolute gradient bounds the signed one and is zero only where the signed one is
    signed = screen.grad[:, :2].abs().sum(1)
    assert (screen.grad[:, 2] >= signed - 1e-6).all()
    assert (screen.grad[:, 2] > signed + 1e-6).any()


def test_gof_distortion_of_two_layers() -> None:
    # two opaque flat layers at z1 < z2 covering a pixel: sum_ij w_i w_j (m_i - m_j)^2 / alpha^2 over NDC depths
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.tensor([[1.0, 1.0, 1e-4]] * 2)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]])
    settings = gof.GaussianRasterizationSettings(H, W, math.tan(FOVX / 2), math.tan(FOVY / 2), 0.0, torch.zeros(H, W, 2),
                                                 torch.zeros(3), 1.0, _view(), _view(), 0, torch.zeros(3), False, False)
    render, _ = gof.GaussianRasterizer(settings)(means, torch.zeros(2, 3), torch.tensor([[0.6], [0.5]]),
                                                 colors_precomp=torch.ones(2, 3), scales=scales, rotations=quats)
    w1, w2 = 0.6, 0.4 * 0.5  # the footprints are ~20 px wide: exp(-sigma) is 1 to 3e-4 at the centre pixel
    m = [100 / 99.8 * (1 - 0.2 / z) for z in (2.0, 4.0)]
    expected = w1 * w2 * (m[0] - m[1]) ** 2 / (w1 + w2) ** 2
    assert render[8, H // 2, W // 2].item() == pytest.approx(expected, rel=2e-3)
    assert render[7, H // 2, W // 2].item() == pytest.approx(w1 + w2, rel=1e-3)
    assert render[6, H // 2, W // 2].item() == pytest.approx(2.0, rel=1e-4)  # T > 0.5 only before the first


def test_pgsr_all_map_plane_depth_and_observe(gaussians) -> None:
    means, quats, scales, opac, colors = gaussians
    settings = plane.GaussianRasterizationSettings(H, W, math.tan(FOVX / 2), math.tan(FOVY / 2), torch.zeros(3), 1.0,
                                                   _view(), _view(), 0, torch.zeros(3), False, True, False)
    n = torch.tensor([0.0, 0.0, -1.0])
    all_map = torch.cat([n.expand(N, 3), torch.ones(N, 1), means[:, 2:3]], dim=1)
    screen, screen_abs = _screen(), _screen()
    color, radii, observe, maps, depth = plane.GaussianRasterizer(settings)(
        means, screen, screen_abs, opac[:, None], colors_precomp=colors, scales=scales, rotations=quats, all_map=all_map)
    assert maps.shape == (5, H, W) and depth.shape == (1, H, W) and observe.dtype == torch.int32
    # fronto-parallel planes: the plane depth is distance / alpha, whatever the ray
    covered = maps[3] > 0.3
    assert torch.allclose(depth[0][covered], (maps[4] / maps[3])[covered], rtol=1e-4)
    assert int(observe.sum()) > 0 and (observe[radii == 0] == 0).all()
    color.sum().backward()
    assert (screen_abs.grad[:, :2] >= screen.grad[:, :2].abs() - 1e-6).all()
    without = plane.GaussianRasterizer(settings._replace(render_geo=False))(
        means, _screen(), _screen(), opac[:, None], colors_precomp=colors, scales=scales, rotations=quats)
    assert without[3].numel() == 0 and without[4].numel() == 0


def test_surfel_allmap_rows(gaussians) -> None:
    means, quats, scales, opac, colors = gaussians
    screen = _screen()
    color, radii, allmap = surfel.GaussianRasterizer(_settings_2023())(
        means, screen, opac[:, None], colors_precomp=colors, scales=scales[:, :2], rotations=quats)
    assert allmap.shape == (7, H, W)
    alpha = allmap[1]
    assert (alpha <= 1).all() and (alpha >= 0).all()
    covered = alpha > 0.5
    assert (allmap[4][covered] < 0).float().mean() > 0.9  # camera-facing normals (edge-on ones aside)
    mean_depth = allmap[0][covered] / alpha[covered]
    assert ((mean_depth > 1.0) & (mean_depth < 5.0)).all()
    color.sum().backward()
    assert screen.grad[:, :2].abs().sum() > 0


def test_dist_cuda2_is_the_mean_squared_distance_to_three_neighbours() -> None:
    points = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0], [10.0, 10, 10]])
    d = simple_knn.distCUDA2(points)
    assert d[0].item() == pytest.approx((1 + 4 + 9) / 3)
    assert d.dtype == torch.float32 and d.shape == (5,)


def test_cuda_requests_go_to_the_cpu() -> None:
    cuda_cpu.install()
    try:
        t = torch.zeros(3, device="cuda")
        assert t.device.type == "cpu"
        assert torch.tensor([1.0], device=torch.device("cuda:0")).device.type == "cpu"
        assert t.cuda().device.type == "cpu" and t.to("cuda").device.type == "cpu"
        assert torch.nn.Linear(2, 2).cuda().weight.device.type == "cpu"
        assert t.new_zeros(2, device="cuda").device.type == "cpu"
        torch.cuda.set_device(0)
        torch.cuda.synchronize()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        end.record()
        assert start.elapsed_time(end) >= 0.0 and torch.cuda.memory_allocated() == 0
    finally:
        cuda_cpu.uninstall()
    assert not cuda_cpu.installed()


def test_the_finder_serves_standins_under_upstream_names() -> None:
    finder = install_standins({"simple_knn": "polargs_plugin.dryrun.standins.simple_knn",
                               "simple_knn._C": "polargs_plugin.dryrun.standins.simple_knn"})
    try:
        from simple_knn._C import distCUDA2  # noqa: PLC0415

        assert distCUDA2 is simple_knn.distCUDA2
    finally:
        sys.meta_path.remove(finder)
        for name in ("simple_knn", "simple_knn._C"):
            sys.modules.pop(name, None)


def test_state_problems_name_a_statistic_and_a_stale_optimizer_state() -> None:
    p = torch.nn.Parameter(torch.zeros(4, 3))
    opt = torch.optim.Adam([{"params": [p], "name": "xyz"}])
    p.grad = torch.ones_like(p)
    opt.step()
    model = types.SimpleNamespace(_xyz=p, denom=torch.zeros(3, 1), optimizer=opt)
    assert state_problems(model) == ["denom has 3 rows for 4 Gaussians"]
    opt.param_groups[0]["params"][0] = torch.nn.Parameter(torch.zeros(4, 3))  # replaced, state left behind
    model._xyz, model.denom = opt.param_groups[0]["params"][0], torch.zeros(4, 1)
    assert state_problems(model) == ["1 optimizer state(s) belong to parameters no longer in the optimizer"]


def test_verdict_fails_on_a_bad_report() -> None:
    good = {"finished": True, "iterations": 40, "losses_finite": True, "loss_first": 1.0, "loss_last": 0.5,
            "dense_rounds": [[20, 5]], "native_densify": [30], "dense_rows_final": 3, "problems": [],
            "checkpoint": {"ok": True, "detail": "fine"}, "step_seconds": [0.1] * 30}
    assert all(c.ok is not False for c in verdict({"patched": good}, 40))
    bad = dict(good, native_densify=[10], problems=["at iteration 31: denom has 3 rows for 4 Gaussians"])
    failed = {c.name for c in verdict({"patched": bad}, 40) if c.ok is False}
    assert failed == {"Dense appended and survived (patched)", "per-Gaussian state (patched)"}
    assert describe([Check("x", None, "y")]) == ["info  x  y"]


def test_an_unpatched_checkout_is_refused(tmp_path: Path) -> None:
    from polargs_plugin.io import PolarInputError

    (tmp_path / "train.py").write_text("print(1)\n")
    with pytest.raises(PolarInputError, match="is not patched"):
        dry_run(DryRunRequest(checkout=tmp_path, trainer="graphdeco", workdir=tmp_path / "w"))


def _placeholder_checkout(tmp_path: Path, fixture: str) -> Path:
    checkout = tmp_path / "checkout"
    shutil.copytree(TRAINERS / "inria_support", checkout, ignore=shutil.ignore_patterns("README.md"))
    shutil.copy(TRAINERS / fixture, checkout / "train.py")
    assert patch_main([str(checkout)], _graphdeco_anchors(), "test") == 0
    return checkout


def _graphdeco_anchors():
    import importlib.util

    spec = importlib.util.spec_from_file_location("_graphdeco_patch", ROOT / "adapters" / "graphdeco" / "patch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.ANCHORS


@pytest.mark.slow
@pytest.mark.parametrize(("fixture", "trainer"), [("graphdeco_2024_train.py", "graphdeco"),
                                                  ("graphdeco_2023_train.py", "graphdeco-2023")])
def test_dry_run_of_the_placeholder_trainer(fixture: str, trainer: str, tmp_path: Path) -> None:
    checkout = _placeholder_checkout(tmp_path, fixture)
    before = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    request = DryRunRequest(checkout=checkout, trainer=trainer, workdir=tmp_path / "work", iterations=48, interval=8,
                            views=16, width=32, height=24, command=f"polargs dryrun {checkout} --trainer {trainer}")
    result = dry_run(request)
    assert result.ok, "\n".join(describe(result.checks)) + "\n" + result.logs["patched"].read_text()[-3000:]
    names = {c.name for c in result.checks}
    assert {"finished (patched)", "Dense appended and survived (patched)", "checkpoint (patched)"} <= names
    summary = json.loads((tmp_path / "work" / "summary.json").read_text())
    assert summary["ok"] is True and [c["name"] for c in summary["checks"]] == [c.name for c in result.checks]
    check_provenance(summary["provenance"], command=request.command)
    after = sorted(p.name for p in checkout.rglob("*") if "__pycache__" not in p.parts)
    assert after == before  # nothing written into the checkout


_BLOCK_OPTIONAL = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('open3d', 'kornia', 'OpenEXR', 'pycolmap'):
            raise ModuleNotFoundError(f'No module named {name!r} (blocked)', name=name)
sys.meta_path.insert(0, Block())
"""


@pytest.mark.parametrize("module", [
    "polargs_plugin.hooks", "polargs_plugin.backends.reference.trainer", "polargs_plugin.service.train",
    "polargs_plugin.dryrun.launch", "polargs_adapters.gof",
])
def test_training_parts_import_without_the_optional_packages(module: str) -> None:
    """What a GPU machine without open3d (or kornia, OpenEXR, pycolmap) runs must import there."""
    import subprocess

    done = subprocess.run([sys.executable, "-c", _BLOCK_OPTIONAL + f"import {module}"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_training_a_scene_folder_with_dense_needs_no_open3d(tmp_path: Path) -> None:
    """GPU machines often lack open3d: reading a scene folder and training it (Full, with Dense
    calls) must run without it, OpenEXR and pycolmap; only meshes need open3d."""
    import json
    import subprocess

    from polargs_plugin.cli import main

    scene, run = tmp_path / "scene", tmp_path / "run"
    assert main(["generate", "--scene", "glossy_plane_sphere", "--out", str(scene), "--views", "8", "--size", "48x48"]) == 0
    config = tmp_path / "dense_early.json"
    config.write_text(json.dumps({"polar": {"densify": {"start_iter": 4, "end_iter": 8, "interval": 4}}}))
    block = _BLOCK_OPTIONAL.replace("'kornia', ", "")  # Dense's seeding needs kornia, a required package
    train = ["train", str(scene), "--out", str(run), "--schedule", "cpu", "--iters", "10", "--config", str(config), "--quiet"]
    code = block + f"from polargs_plugin.cli import main; sys.exit(main({train!r}))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 10 and summary["polar"]
    assert summary["num_gaussians"] > 2000  # the initial cloud plus what the two Dense calls appended


def test_gpu_check_reports_clearly_without_a_gpu(tmp_path: Path) -> None:
    import os
    import subprocess

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    env = dict(os.environ, PYTHON=sys.executable)
    done = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--out", str(tmp_path)], capture_output=True,
                          text=True, env=env)
    assert done.returncode == 0
    assert "not done: every step: no CUDA device" in done.stdout


def test_gpu_check_names_what_its_python_cannot_import(tmp_path: Path) -> None:
    """A GPU machine whose python lacks a requirement (a wheel installed by another interpreter's
    pip): one line naming the module and the interpreter, exit status 1, nothing run."""
    import os
    import subprocess

    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(
        "import sys, importlib.abc\n"
        "class _Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name == 'kornia':\n"
        "            raise ModuleNotFoundError('kornia blocked')\n"
        "sys.meta_path.insert(0, _Block())\n"
        "import torch\n"
        "torch.cuda.is_available = lambda: True\n"
        "torch.cuda.get_device_name = lambda index=0: 'stand-in GPU'\n"
    )
    env = dict(os.environ, PYTHON=sys.executable, PYTHONPATH=str(site))
    done = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, env=env)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "stand-in GPU" in done.stdout
    lines = [line for line in done.stdout.splitlines() if "error:" in line]
    assert len(lines) == 1 and "cannot import: kornia;" in lines[0] and sys.executable in lines[0]
    assert "CUDA-only tests" not in done.stdout
