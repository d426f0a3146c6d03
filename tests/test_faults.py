"""Faults real runs meet, at the PolarHooks door: each case's message names the
file, argument or view, and nothing NaN remains."""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

from polargs_plugin.hooks import PolarHooks
from polargs_plugin.io import PolarInputError
from test_hooks import H, W, _config, _gaussians, _render, _view


def _finite(maps) -> bool:
    tensors = [t for t in dataclasses.asdict(maps).values() if isinstance(t, torch.Tensor)]
    tensors += [t for t in maps.extras.values() if t.is_floating_point()]
    return all(bool(torch.isfinite(t).all()) for t in tensors if t.is_floating_point())


def test_cache_entry_with_nan_values_is_recomputed(tmp_path):
    cfg = _config()
    cfg.cache_dir = str(tmp_path)
    view = _view()
    (first,) = PolarHooks(cfg).preprocess([view])
    (path,) = tmp_path.glob("*.pt")
    data = torch.load(path, weights_only=True)
    data["dolp"] = torch.full_like(data["dolp"], float("nan"))  # valid structure, NaN values
    torch.save(data, path)
    with pytest.warns(UserWarning, match=r"cache entry of view 'v0' not used \(dolp holds non-finite") as caught:
        (again,) = PolarHooks(cfg).preprocess([view])
    assert str(path) in str(caught[0].message)
    assert _finite(again) and torch.equal(again.dolp, first.dolp)
    assert torch.isfinite(torch.load(path, weights_only=True)["dolp"]).all()  # overwritten
    # A cache entry of the wrong size (same structure) is not trusted either.
    data["dolp"] = torch.zeros(1, H + 1, W)
    torch.save(data, path)
    with pytest.warns(UserWarning, match="dolp has shape"):
        (again,) = PolarHooks(cfg).preprocess([view])
    assert again.dolp.shape == (1, H, W)


def test_view_with_a_nan_pixel_is_refused_at_preprocess_naming_the_view():
    view = _view("cam_07")
    view.source = "captures/cam_07.npz"
    view.stokes[1, 2, 5, 9] = float("nan")
    hooks = PolarHooks(_config())
    with pytest.raises(PolarInputError) as err:
        hooks.preprocess([_view("v0"), view])
    message = str(err.value)
    assert "captures/cam_07.npz" in message and "view 'cam_07'" in message
    assert "stokes has 1 non-finite value(s)" in message and "[1, 2, 5, 9]" in message
    assert "cam_07" not in hooks.maps  # nothing half-done for the bad view


def test_view_with_a_wrong_size_mask_is_refused_naming_the_field():
    view = _view()
    view.mask = torch.ones(1, H, W + 2, dtype=torch.bool)
    with pytest.raises(PolarInputError, match=rf"view 'v0'.*mask has shape \(1, {H}, {W + 2}\), expected \(1, {H}, {W}\)"):
        PolarHooks(_config()).preprocess([view])


def test_impossible_stokes_are_counted_per_view_clamped_and_warned_once():
    view = _view("v3")
    view.stokes[0, :, 0, 0] = -0.2  # s0 < 0
    view.stokes[1, :, 1, 0:3] = 5.0  # s1 far beyond s0: DoLP > 1
    view.stokes[2, :, 2, 0] = view.stokes[0, :, 2, 0] + 0.001  # within the noise allowance: not counted
    hooks = PolarHooks(_config())
    with pytest.warns(UserWarning) as caught:
        (maps,) = hooks.preprocess([view])
    physics = [w for w in caught if "physically impossible" in str(w.message)]
    assert len(physics) == 1
    message = str(physics[0].message)
    assert "view 'v3'" in message and f"4 of {H * W} pixels" in message
    assert "1 with s0 < 0" in message and "3 with s1^2 + s2^2 > s0^2" in message
    assert _finite(maps)
    assert float(maps.dolp.max()) <= 1.0 and float(maps.intensity.min()) >= 0.0
    assert float(maps.i_diff.min()) >= 0.0
    # Once per view: a second preprocess of the same hooks does not repeat it.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hooks.preprocess([view])


def test_impossible_stokes_beyond_the_tolerated_fraction_are_refused():
    view = _view("halved")
    view.source = "data/halved"
    view.stokes[0] /= 4  # a reader that scaled s0 but not s1, s2: DoLP > 1 on the highlight and patch
    view.stokes[1] += 0.5
    cfg = _config()
    with pytest.raises(PolarInputError) as err:
        PolarHooks(cfg).preprocess([view])
    message = str(err.value)
    assert message.startswith("data/halved: ") and "view 'halved'" in message
    assert "max_impossible_fraction" in message and "convention" in message
    cfg.correction.max_impossible_fraction = 1.0  # accepted (and clamped) when tolerated
    with pytest.warns(UserWarning, match="physically impossible"):
        (maps,) = PolarHooks(cfg).preprocess([view])
    assert _finite(maps) and float(maps.dolp.max()) <= 1.0


def test_hdr_input_warns_once_naming_the_view_and_source():
    view = _view("pan_000")
    view.source = "neisf/copper_pan/pan_000.exr"
    view.stokes *= 9.0  # s0/2 up to ~9, as in NeISF++ EXR Stokes
    hooks = PolarHooks(_config())
    with pytest.warns(UserWarning) as caught:
        (maps,) = hooks.preprocess([view])
    hdr = [w for w in caught if "not the [0, 1]" in str(w.message)]
    assert len(hdr) == 1
    message = str(hdr[0].message)
    assert "view 'pan_000'" in message and "pan_000.exr" in message and "white_level" in message
    assert _finite(maps)
    assert bool((maps.specular_mask | maps.overexposed_mask).any())  # cores above 1 are not excluded
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hooks.preprocess([view])  # warned once


@pytest.mark.parametrize(
    ("field", "bad", "expected"),
    [
        ("color", (3, H, W - 4), (3, H, W)),
        ("normal", (3, H, W - 4), (3, H, W)),
        ("depth", (H, W), (1, H, W)),
        ("alpha", (1, H + 1, W), (1, H, W)),
    ],
)
def test_loss_checks_render_shapes_naming_the_argument(field, bad, expected):
    cfg = _config()
    cfg.losses.depth_normal_from_iter = 1  # every render field is read
    hooks = PolarHooks(cfg)
    view = _view()
    hooks.preprocess([view])
    render = dataclasses.replace(_render(), **{field: torch.zeros(bad)})
    with pytest.raises(ValueError) as err:
        hooks.loss(5, view, render, _gaussians())
    assert str(err.value) == f"hooks.loss: render.{field} has shape {bad}, expected {expected} like view 'v0'"


def test_loss_checks_gaussian_scales_and_unknown_views():
    hooks = PolarHooks(_config())
    view = _view()
    hooks.preprocess([view])
    gaussians = dataclasses.replace(_gaussians(), scales=torch.ones(7, 2))
    with pytest.raises(ValueError, match=r"hooks.loss: gaussians.scales has shape \(7, 2\), expected \(N, 3\)"):
        hooks.loss(1, view, _render(), gaussians)
    with pytest.raises(KeyError, match="hooks.loss: view 'other' was not preprocessed"):
        hooks.loss(1, _view("other"), _render(), _gaussians())
    small = dataclasses.replace(view, stokes=view.stokes[..., :-2])
    with pytest.raises(ValueError, match=rf"view.stokes is {H}x{W - 2}, but view 'v0' was preprocessed at {H}x{W}"):
        hooks.loss(1, small, _render(), _gaussians())


def test_densify_checks_the_render_and_render_fn_shapes():
    from test_densifier import _setup

    views, renders, maps, render_fn, cfg = _setup()
    hooks = PolarHooks(cfg)
    hooks.preprocess(views)
    it = cfg.densify.start_iter
    h, w = views[0].height, views[0].width
    bad = dataclasses.replace(render_fn(views[0]), normal=torch.zeros(3, h, w - 1))
    with pytest.raises(ValueError) as err:
        hooks.densify(it, views[0], render_fn, None, render=bad)
    assert str(err.value) == (f"hooks.densify: render.normal has shape (3, {h}, {w - 1}), expected (3, {h}, {w}) "
                              f"like view '{views[0].name}'")

    def wrong_sources(view):
        out = render_fn(view)
        return dataclasses.replace(out, depth=out.depth[0]) if view.name != views[0].name else out

    with pytest.raises(ValueError, match=r"hooks.densify: render_fn\(view 'v\d'\).depth has shape \(\d+, \d+\), "
                                         r"expected \(1, \d+, \d+\) like view 'v\d'"):
        hooks.densify(it, views[0], wrong_sources, None)


def test_training_stops_at_the_first_non_finite_parameter_naming_iteration_and_tensor() -> None:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer, TrainingDiverged
    from polargs_plugin.data.synthetic import generate_scene

    views = generate_scene("bumpy_mixed", num_views=3, width=24, height=24).views
    trainer = Trainer(views, TrainConfig.cpu(progress=False, num_init_points=200))
    trainer.step()
    with torch.no_grad():
        trainer.model.log_scales[3, 1] = float("nan")
    with pytest.raises(TrainingDiverged, match=r"iteration 2: .*(loss is nan|non-finite parameters: .*'log_scales' has)"):
        trainer.step()


def test_trainer_refuses_nan_views_and_nan_checkpoints(tmp_path) -> None:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
    from polargs_plugin.data.synthetic import generate_scene

    views = generate_scene("bumpy_mixed", num_views=3, width=24, height=24).views
    bad = views[1].stokes.clone()
    bad[0, 0, 5, 5] = float("nan")
    with pytest.raises(ValueError, match=r"Trainer: view 'view_001' .*stokes has 1 non-finite value\(s\)"):
        Trainer([views[0], dataclasses.replace(views[1], stokes=bad)], TrainConfig.cpu(progress=False))
    trainer = Trainer(views, TrainConfig.cpu(progress=False, num_init_points=200))
    trainer.step()
    with torch.no_grad():
        trainer.model.means[0, 0] = float("nan")
    trainer.save_checkpoint(tmp_path / "nan.pt")
    fresh = Trainer(views, TrainConfig.cpu(progress=False, num_init_points=200))
    with pytest.raises(ValueError, match=r"nan.pt: checkpoint: non-finite parameters: 'means' has 1 of 600"):
        fresh.load_checkpoint(tmp_path / "nan.pt")


def test_load_views_refuses_a_nan_pixel_naming_the_file(tmp_path, monkeypatch) -> None:
    """A reader's NaN (e.g. an EXR Stokes pixel) is caught at the door, not in training."""
    from polargs_plugin.data import registry
    from polargs_plugin.data.synthetic import generate_scene

    view = generate_scene("bumpy_mixed", num_views=1, width=16, height=16).views[0]
    stokes = view.stokes.clone()
    stokes[1, 0, 3, 4] = float("nan")
    bad = dataclasses.replace(view, stokes=stokes, source=str(tmp_path / "s1_000.exr"))
    reader = registry.FORMATS["polargs"]
    monkeypatch.setitem(registry.FORMATS, "polargs", (reader[0], reader[1], lambda folder, **kw: [bad]))
    with pytest.raises(PolarInputError, match=r"s1_000.exr: load_views: view 'view_000' .*stokes has 1 non-finite "
                                              r"value\(s\) \(NaN or inf\), the first at index \[1, 0, 3, 4\]"):
        registry.load_views(tmp_path, fmt="polargs")
