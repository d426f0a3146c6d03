"""Reference trainer on a tiny scene rendered from known Gaussians: learning, determinism,
resume equivalence, hook order, checkpoint errors."""

import dataclasses
import math

import pytest
import torch

from polargs_plugin.backends.reference.model import PARAM_NAMES, LearningRates
from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.backends.reference.strategy import DensityConfig
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.io import PolarInputError
from polargs_plugin.types import NewGaussians, View

SIZE = 24


def _look_at(eye: torch.Tensor) -> torch.Tensor:
    z = -eye / eye.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def _tiny_views(num_views: int = 6) -> list[View]:
    """Views of 40 coloured Gaussians in a unit ball, rendered by the reference rasterizer."""
    g = torch.Generator().manual_seed(123)
    n = 40
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=g)
    opacities = 0.6 + 0.3 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    f = SIZE * 1.2
    K = torch.tensor([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1]], dtype=torch.float64)
    views = []
    for i in range(num_views):
        a = 2 * math.pi * i / num_views
        eye = torch.tensor([3 * math.cos(a), 3 * math.sin(a), 0.8 * (-1) ** i], dtype=torch.float64)
        w2c = _look_at(eye)
        with torch.no_grad():
            out = rasterize(means, quats, scales, opacities, colors, K.float(), w2c.float(), SIZE, SIZE)
        image = out.color.clamp(0, 1)
        stokes = torch.zeros(3, 3, SIZE, SIZE)
        stokes[0] = 2 * image  # the training colour is s0 / 2
        views.append(View(name=f"v{i}", K=K, world_to_camera=w2c, stokes=stokes, mask=out.alpha > 0.5))
    return views


def _config(**overrides) -> TrainConfig:
    # factor 0.005: refine from iteration 2 every iteration, opacity reset every 15,
    # SH degree up every 5; so that every piece of state changes within a few iterations.
    base = dict(
        iterations=20,
        schedule_scale=0.005,
        sh_degree=1,
        num_init_points=150,
        init_resolution=24,
        progress=False,
        use_masks=True,
        density=DensityConfig(max_gaussians=300),
    )
    base.update(overrides)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def views():
    return _tiny_views()


def _params(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: getattr(trainer.model, k).detach().clone() for k in PARAM_NAMES}


def test_loss_decreases_and_psnr_rises(views):
    # factor 0.1: no refinement before 50 (the density control is tested elsewhere);
    # rates x10 because vanilla rates are tuned for 30k iterations, not 40
    fast = LearningRates(
        means_init=1.6e-3, means_final=1.6e-5, sh_dc=0.025, sh_rest=0.025 / 20, opacity_logits=0.25, log_scales=0.05, quats=0.01
    )
    trainer = Trainer(views, _config(iterations=40, schedule_scale=0.1, lrs=fast))
    before = trainer.evaluate()
    losses = [trainer.step()["loss"] for _ in range(40)]
    after = trainer.evaluate()
    assert sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5
    assert after > before + 3.0


def test_same_seed_same_parameters_and_seed_matters(views):
    a = Trainer(views, _config())
    a.train()
    b = Trainer(views, _config())
    b.train()
    pa, pb = _params(a), _params(b)
    assert all(torch.equal(pa[k], pb[k]) for k in PARAM_NAMES)
    c, d = Trainer(views, _config(seed=1)), Trainer(views, _config())
    assert not torch.equal(c.model.means, d.model.means)  # the seed drives the initialisation


def test_resume_equals_uninterrupted_run(views, tmp_path):
    full = Trainer(views, _config())
    full.train()
    first = Trainer(views, _config())
    first.train(until=8, checkpoint=tmp_path / "ckpt.pt")
    torch.manual_seed(999)  # disturb the global generators: the checkpoint must restore them
    resumed = Trainer(views, _config(seed=5))  # a different seed, overridden by the checkpoint
    resumed.load_checkpoint(tmp_path / "ckpt.pt")
    assert resumed.iteration == 8
    resumed.train()
    assert resumed.iteration == full.iteration == 20
    pf, pr = _params(full), _params(resumed)
    assert all(torch.equal(pf[k], pr[k]) for k in PARAM_NAMES)
    sf = full.model.optimizer.state_dict()["state"]
    sr = resumed.model.optimizer.state_dict()["state"]
    assert all(torch.equal(sf[i]["exp_avg_sq"], sr[i]["exp_avg_sq"]) for i in sf)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # atomic write leaves no temporaries


def test_checkpoint_errors_name_the_file(views, tmp_path):
    trainer = Trainer(views, _config(iterations=2))
    with pytest.raises(PolarInputError, match="not found"):
        trainer.load_checkpoint(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(PolarInputError, match="bad.pt"):
        trainer.load_checkpoint(bad)
    trainer.train(checkpoint=tmp_path / "ok.pt")
    other = Trainer(views[:-1], _config(iterations=2))
    with pytest.raises(PolarInputError, match="different views"):
        other.load_checkpoint(tmp_path / "ok.pt")


class RecordingHooks:
    """Fake PolarHooks recording the calls and the state of training at each call."""

    def __init__(self, trainer_ref: list, extra: float = 5.0, append_at: int = 3, not_due: tuple[int, ...] = ()):
        self.events: list[tuple] = []
        self.trainer_ref = trainer_ref
        self.extra = extra
        self.append_at = append_at
        self.not_due = not_due
        self.loaded = None

    def preprocess(self, views):
        self.events.append(("preprocess", len(views)))
        return ["maps"] * len(views)

    def loss(self, iteration, view, render, gaussians):
        self.last_loss_render = render
        model = self.trainer_ref[0].model
        before_backward = model.means.grad is None
        self.events.append(("loss", iteration, before_backward, torch.is_grad_enabled(), gaussians.num))
        # zero-gradient extra term: must change the logged loss but not the optimisation
        extra = self.extra + 0.0 * gaussians.scales.sum() + 0.0 * render.color.sum()
        return extra, {"fake": 1.0}

    def densify_due(self, iteration):
        return iteration not in self.not_due

    def densify(self, iteration, view, render_fn, gaussians, render=None):
        model = self.trainer_ref[0].model
        adam_step = int(model.optimizer.state[model.means]["step"])
        out = render_fn(view)
        # the caller's render of this view from this iteration, without its autograd graph
        same_render = torch.equal(render.depth, self.last_loss_render.depth.detach())
        self.events.append(
            ("densify", iteration, adam_step, torch.is_grad_enabled(), tuple(out.color.shape),
             same_render and not render.color.requires_grad)
        )
        if iteration != self.append_at:
            return None
        return NewGaussians(
            means=torch.zeros(2, 3),
            quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
            scales=torch.full((2, 3), 0.05),
            colors=torch.full((2, 3), 0.5),
            opacities=torch.full((2,), 0.5),
        )

    def state_dict(self):
        return {"calls": torch.tensor(len(self.events))}

    def load_state_dict(self, state):
        self.loaded = int(state["calls"])


def test_hooks_called_in_order_at_the_right_points(views, tmp_path):
    ref: list = []
    hooks = RecordingHooks(ref)
    cfg = _config(iterations=5, schedule_scale=1.0)  # no native densification in 5 iterations
    trainer = Trainer(views, cfg, hooks=hooks)
    ref.append(trainer)
    n0 = trainer.model.num
    logs = []
    for it in range(1, 6):
        logs.append(trainer.step())
        if it == 2:
            snapshot = _params(trainer)
    kinds = [e[0] for e in hooks.events]
    assert kinds == ["preprocess"] + ["loss", "densify"] * 5
    assert hooks.events[0] == ("preprocess", len(views))
    for it in range(1, 6):
        loss_ev, dens_ev = hooks.events[2 * it - 1], hooks.events[2 * it]
        assert loss_ev[1] == it and loss_ev[2] and loss_ev[3]  # before backward, with autograd
        assert dens_ev[1] == it and dens_ev[2] == it and not dens_ev[3]  # after the step, no_grad
        assert dens_ev[4] == (3, SIZE, SIZE) and dens_ev[5]
        assert loss_ev[4] == n0 + (2 if it > 3 else 0)  # the appended Gaussians are trained on
    assert trainer.model.num == n0 + 2 and logs[2]["appended"] == 2.0
    # the zero-gradient extra term is added to the loss but changes nothing else
    base = Trainer(views, cfg)
    base_logs = [base.step() for _ in range(2)]
    for lh, lb in zip(logs[:2], base_logs):
        assert lh["loss"] == pytest.approx(lb["loss"] + 5.0, abs=1e-5)
    base_params = _params(base)
    assert all(torch.equal(snapshot[k], base_params[k]) for k in PARAM_NAMES)
    # hooks state travels with the checkpoint
    trainer.save_checkpoint(tmp_path / "h.pt")
    ref2: list = []
    hooks2 = RecordingHooks(ref2)
    again = Trainer(views, cfg, hooks=hooks2)
    ref2.append(again)
    again.load_checkpoint(tmp_path / "h.pt")
    assert hooks2.loaded == len(hooks.events) and hooks2.events == [("preprocess", len(views))]
    assert again.model.num == n0 + 2
    with pytest.raises(PolarInputError, match="with hooks"):
        Trainer(views, cfg).load_checkpoint(tmp_path / "h.pt")


def test_densify_is_not_called_where_it_is_not_due(views):
    ref: list = []
    hooks = RecordingHooks(ref, not_due=(2, 3))
    ref.append(trainer := Trainer(views, _config(iterations=4, schedule_scale=1.0), hooks=hooks))
    n0 = trainer.model.num
    trainer.train()
    assert [(e[0], e[1]) for e in hooks.events[1:] if e[0] == "densify"] == [("densify", 1), ("densify", 4)]
    assert trainer.model.num == n0  # iteration 3, where the fake appends, was not due


def test_hooks_with_zero_gradient_do_not_change_base_training(views):
    ref: list = []
    trainer = Trainer(views, _config(iterations=8), hooks=RecordingHooks(ref, append_at=-1))
    ref.append(trainer)
    trainer.train()
    base = Trainer(views, _config(iterations=8))
    base.train()
    pt, pb = _params(trainer), _params(base)
    assert all(torch.equal(pt[k], pb[k]) for k in PARAM_NAMES)
    # L_dn's plane depth is rendered for the hooks only (a Base run has no use for it)
    assert trainer.render(views[0]).plane_depth is not None and base.render(views[0]).plane_depth is None


def test_masked_target_uses_the_background(views):
    trainer = Trainer(views, _config(background=(0.2, 0.4, 0.6)))
    v = trainer.views[0]
    t = trainer.target(v)
    outside = ~v.mask[0]
    assert bool(outside.any())
    assert torch.allclose(t[:, outside], torch.tensor([0.2, 0.4, 0.6])[:, None].expand(3, int(outside.sum())))
    assert torch.equal(t[:, v.mask[0]], v.image.clamp(0, 1)[:, v.mask[0]])


def _square_mask_view(view: View, lo: int, hi: int) -> View:
    mask = torch.zeros(1, SIZE, SIZE, dtype=torch.bool)
    mask[:, lo:hi, lo:hi] = True
    return dataclasses.replace(view, mask=mask)


@pytest.mark.parametrize("width", [1, 2])
def test_mask_edge_band_is_the_ring_of_pixels_just_outside_the_mask(views, width):
    lo, hi = 8, 20  # a 12 x 12 square well inside the image
    trainer = Trainer([_square_mask_view(views[0], lo, hi)], _config(mask_edge_band=width))
    band = trainer.edge_band(trainer.views[0])[0]
    rows, cols = torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij")
    # Chebyshev distance to the square: 0 inside it
    dist = torch.maximum((lo - rows).clamp(min=0).maximum((rows - hi + 1).clamp(min=0)),
                         (lo - cols).clamp(min=0).maximum((cols - hi + 1).clamp(min=0)))
    assert torch.equal(band, (dist >= 1) & (dist <= width))
    assert int(band.sum()) == (12 + 2 * width) ** 2 - 12**2
    assert Trainer(views, _config()).edge_band(views[0]) is None  # off by default
    assert Trainer(views, _config(mask_edge_band=1, use_masks=False)).edge_band(views[0]) is None
    with pytest.raises(ValueError, match="mask_edge_band"):
        Trainer(views, _config(mask_edge_band=-1))


def test_mask_edge_band_pixels_give_the_colour_loss_no_gradient(views):
    """The colour's gradient is exactly 0 in the band, and the band's pixels do not count in the
    loss: it equals the colour loss with the band's rendered pixels set to the target."""
    view = _square_mask_view(views[0], 6, 22)
    trainer = Trainer([view], _config(mask_edge_band=1))
    band = trainer.edge_band(trainer.views[0])
    colors: list[torch.Tensor] = []
    render = trainer.render

    def keep_color(v, state=None):
        out = render(v, state)
        out.color.retain_grad()
        colors.append(out.color)
        return out

    trainer.render = keep_color
    logs = trainer.step()
    color, target = colors[0], trainer.target(trainer.views[0])
    grad = color.grad.abs().sum(0, keepdim=True)
    assert float(grad[band].max()) == 0.0
    differs = (color.detach() - target).abs().sum(0, keepdim=True) > 1e-3
    assert bool((differs & band).any())  # the render spills into the band: it would have counted
    assert bool((grad[~band & differs] > 0).all())
    ignored = torch.where(band, target, color.detach())
    assert float(logs["loss"]) == pytest.approx(float(trainer.base_loss(ignored, target)), abs=1e-7)
    assert float(logs["loss"]) < float(trainer.base_loss(color.detach(), target))


def test_config_round_trip_and_cpu_preset_scaling():
    cfg = TrainConfig.cpu(0.1, seed=3)
    assert cfg.iterations == 3000 and cfg.seed == 3 and TrainConfig.cpu().iterations == 5000
    assert (cfg.mask_edge_band, TrainConfig().mask_edge_band) == (1, 0)  # vanilla keeps every pixel
    again = TrainConfig.from_dict(cfg.to_dict())
    assert again == cfg
    d = cfg.density.scaled(cfg.schedule_scale)
    assert (d.refine_start, d.refine_stop, d.refine_every, d.reset_every) == (50, 1500, 10, 300)


def test_base_loss_is_vanilla_colour_loss_on_the_background_target(views):
    import kornia

    from polargs_plugin.losses import photometric_loss

    trainer = Trainer(views, _config(background=(0.2, 0.4, 0.6)))  # no hooks: vanilla's SSIM share 0.2
    pred, target = torch.rand(3, SIZE, SIZE), trainer.target(trainer.views[0])
    ssim = kornia.metrics.ssim(pred[None], target[None], 11).mean()
    vanilla = 0.8 * (pred - target).abs().mean() + 0.2 * (1 - ssim)
    assert torch.allclose(trainer.base_loss(pred, target), vanilla, atol=1e-6)
    # the very function PolarHooks' reflective replacement assumes, so the cancellation is exact
    assert torch.equal(trainer.base_loss(pred, target), photometric_loss(pred, target, ssim_weight=0.2))


@pytest.mark.slow
def test_lazy_step_logs_equal_the_figures_computed_every_step(views):
    """StepLogs read late (or never) give the figures the eager step computed: loss, PSNR of that
    step's render against its target, hook logs, counts; train() reports the window's mean loss."""
    ref: list = []

    class Capturing(Trainer):
        def base_loss(self, image, target):
            self.captured = (image.detach().clone(), target)
            return super().base_loss(image, target)

    eager = Capturing(views, _config(iterations=12, log_every=4), hooks=RecordingHooks(ref, append_at=3))
    ref.append(eager)
    figures_every_step = []
    for _ in range(12):
        logs = eager.step()
        image, target = eager.captured
        mse = float(((image - target) ** 2).mean())
        assert logs["psnr"] == pytest.approx(-10 * math.log10(mse), abs=1e-9)
        assert logs["fake"] == 1.0 and logs["num"] == float(eager.model.num)
        figures_every_step.append(dict(logs))
    # the same run (same seed), nothing read until the end: the global generators are re-seeded
    # by the constructor, so the runs are identical
    ref[0] = lazy = Trainer(views, _config(iterations=12, log_every=4), hooks=RecordingHooks(ref, append_at=3))
    kept = [lazy.step() for _ in range(12)]
    assert [dict(k) for k in kept] == figures_every_step
    assert kept[2]["appended"] == 2.0 and "appended" not in kept[3]
    assert dict(kept[0]) == dict(kept[0])  # read again: cached, unchanged
    assert isinstance(kept[0].loss, torch.Tensor) and not kept[0].loss.requires_grad
    # train(): the loss figure is the mean over the last log_every iterations
    a = Trainer(views, _config(iterations=10, log_every=4))
    figures = a.train()
    b = Trainer(views, _config(iterations=10, log_every=4))
    losses = [b.step()["loss"] for _ in range(10)]
    assert figures["loss"] == pytest.approx(sum(losses[8:]) / 2, rel=1e-6)
    with pytest.raises(ValueError, match="log_every"):
        Trainer(views, _config(log_every=0))


def test_progress_bar_ends_on_the_summary_psnr(views, capsys):
    """The bar's last PSNR is the one train() returns (all views), not the last view's."""
    import re

    trainer = Trainer(views, _config(iterations=6, progress=True))
    figures = trainer.train()
    shown = re.findall(r"psnr=([0-9.]+)", capsys.readouterr().err)
    assert shown and float(shown[-1]) == pytest.approx(figures["psnr"], abs=0.006)


def test_cpu_preset_runs_the_paper_polargs_schedule_at_half_its_counts():
    """The CPU preset: 5000 vanilla iterations (x1/6) with the paper's Dense window 1k-7k every
    100 and L_dn start 7k scaled by 1/2 (at most 2x), the same in the library, `polargs ablate` and
    `polargs train --schedule cpu`; a --factor F scales PolarGS by min(1, 3F)."""
    from polargs_plugin.ablation.variants import polar_config as variant_polar, train_config as variant_train
    from polargs_plugin.service.configs import polar_config as cli_polar
    from polargs_plugin.config import PolarConfig, polar_schedule_factor

    paper = PolarConfig.synthetic()
    assert (paper.densify.start_iter, paper.densify.end_iter, paper.densify.interval) == (1000, 7000, 100)
    assert paper.losses.depth_normal_from_iter == 7000
    train = TrainConfig.cpu()
    assert train.iterations == 5000 and variant_train().iterations == 5000
    for polar in (PolarConfig.cpu_demo(), variant_polar("full"), cli_polar("synthetic", train.schedule_scale, {}, "test")):
        d = polar.densify
        assert (d.start_iter, d.end_iter, d.interval) == (500, 3500, 50)
        assert polar.losses.depth_normal_from_iter == 3500
        assert d.end_iter < train.iterations
    assert polar_schedule_factor(0.002) == pytest.approx(0.006) and polar_schedule_factor(0.5) == 1.0
    with pytest.raises(ValueError):
        polar_schedule_factor(0)


def test_the_trainer_takes_the_ssim_share_of_its_colour_loss_from_the_hooks() -> None:
    """One home for the SSIM share: the reference trainer's colour loss uses the hooks'
    ``losses.ssim_weight`` (the loss their replacement cancels), vanilla 3DGS's 0.2 without them."""
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.losses import photometric_loss

    from polargs_plugin.config import PolarConfig
    from polargs_plugin.hooks import PolarHooks
    from polargs_plugin.types import View

    world_to_camera = torch.eye(4, dtype=torch.float64)
    world_to_camera[2, 3] = 3.0
    view = View("v", torch.tensor([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]], dtype=torch.float64), world_to_camera,
                torch.rand(3, 3, 8, 8))
    config = PolarConfig.synthetic()
    config.losses.ssim_weight = 0.3
    pred, target = torch.rand(3, 8, 8), torch.rand(3, 8, 8)
    hooked = Trainer([view], TrainConfig.cpu(progress=False, num_init_points=50), hooks=PolarHooks(config))
    plain = Trainer([view], TrainConfig.cpu(progress=False, num_init_points=50))
    assert torch.equal(hooked.base_loss(pred, target), photometric_loss(pred, target, ssim_weight=0.3))
    assert torch.equal(plain.base_loss(pred, target), photometric_loss(pred, target, ssim_weight=0.2))
