"""Faults real runs meet, in the library: at the PolarHooks door (NaN, shapes, dtypes, devices, a
view without Stokes), in the readers (bit depths that lie, views far brighter or darker than the
others), in run folders (full disks, killed writers, stale locks taken over at once, other data
under the same names, relative paths) and in the ablation runner (dot-named scenes, the temporary
folder a run is built in). Each message names the file, argument or view, in one line; nothing is
half-written and no run that can resume is lost. The tables (``*_FAULTS``) list the cases."""

from __future__ import annotations

import dataclasses
import json
import shutil
import types
import warnings
from pathlib import Path

import cv2
import numpy as np
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
    with pytest.warns(UserWarning, match=r"cache entry of view 'v0' rebuilt: dolp holds non-finite") as caught:
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


def test_training_stops_at_the_first_non_finite_parameter_naming_iteration_and_tensor(synthetic_views) -> None:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer, TrainingDiverged

    views = synthetic_views("bumpy_mixed", num_views=3, width=24, height=24)
    trainer = Trainer(views, TrainConfig.cpu(progress=False, num_init_points=200))
    trainer.step()
    with torch.no_grad():
        trainer.model.log_scales[3, 1] = float("nan")
    with pytest.raises(TrainingDiverged, match=r"iteration 2: .*(loss is nan|non-finite parameters: .*'log_scales' has)"):
        trainer.step()


def test_trainer_refuses_nan_views_and_nan_checkpoints(tmp_path, synthetic_views) -> None:
    from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer

    views = synthetic_views("bumpy_mixed", num_views=3, width=24, height=24)
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


def test_load_views_refuses_a_nan_pixel_naming_the_file(tmp_path, monkeypatch, synthetic_views) -> None:
    """A reader's NaN (e.g. an EXR Stokes pixel) is caught at the door, not in training."""
    from polargs_plugin.data import registry

    view = synthetic_views("bumpy_mixed", num_views=1, width=16, height=16)[0]
    stokes = view.stokes.clone()
    stokes[1, 0, 3, 4] = float("nan")
    bad = dataclasses.replace(view, stokes=stokes, source=str(tmp_path / "s1_000.exr"))
    reader = registry.FORMATS["polargs"]
    monkeypatch.setitem(registry.FORMATS, "polargs", (reader[0], reader[1], lambda folder, **kw: [bad]))
    with pytest.raises(PolarInputError, match=r"s1_000.exr: load_views: view 'view_000' .*stokes has 1 non-finite "
                                              r"value\(s\) \(NaN or inf\), the first at index \[1, 0, 3, 4\]"):
        registry.load_views(tmp_path, fmt="polargs")


# ------------------------------------------------------------------------------------------------
# Fault tables: each row is an input a careful user (or an adversarial one) gives, and the one-line
# message it must get (or the state it must leave).

def _loss_door():
    """Preprocessed hooks whose loss reads every render field, a view, a render and Gaussians."""
    cfg = _config()
    cfg.losses.depth_normal_from_iter = 1
    hooks = PolarHooks(cfg)
    view = _view()
    hooks.preprocess([view])
    return hooks, view, _render(), _gaussians()


_TOO_LATE = "expected a tensor on the device the trainer renders on"
def _without_stokes(view):
    """A duck-typed view (a trainer's own camera object) whose Stokes are missing; a
    :class:`View` itself refuses ``stokes=None`` when it is built."""
    fields = {field.name: getattr(view, field.name) for field in dataclasses.fields(view)}
    return types.SimpleNamespace(**{**fields, "stokes": None})


def test_view_refuses_missing_stokes_when_built():
    with pytest.raises(TypeError, match=r"^View\.stokes is required$"):
        dataclasses.replace(_view(), stokes=None)


LOSS_FAULTS = [
    # (case, change of (iteration, view, render, gaussians), the message of hooks.loss)
    ("float64 colour", lambda it, v, r, g: (it, v, dataclasses.replace(r, color=r.color.double()), g),
     "hooks.loss: render.color has dtype torch.float64, expected torch.float32 like the maps of view 'v0'"),
    ("float64 depth", lambda it, v, r, g: (it, v, dataclasses.replace(r, depth=r.depth.double()), g),
     "hooks.loss: render.depth has dtype torch.float64, expected torch.float32 like the maps of view 'v0'"),
    ("a render on the meta device", lambda it, v, r, g: (it, v, dataclasses.replace(r, normal=r.normal.to("meta")), g),
     f"hooks.loss: render.normal is on the meta device, which holds no values; {_TOO_LATE}"),
    ("Gaussians on the meta device",
     lambda it, v, r, g: (it, v, r, dataclasses.replace(g, scales=g.scales.detach().to("meta"))),
     f"hooks.loss: gaussians.scales is on the meta device, which holds no values; {_TOO_LATE}"),
    ("a view without Stokes", lambda it, v, r, g: (it, _without_stokes(v), r, g),
     "hooks.loss: view 'v0' has no Stokes (view.stokes is NoneType); expected a (3, C, H, W) tensor"),
    ("iteration 0", lambda it, v, r, g: (0, v, r, g),
     "hooks.loss: iteration must be an integer >= 1 (iterations are 1-based), got 0"),
    ("a negative iteration", lambda it, v, r, g: (-4, v, r, g),
     "hooks.loss: iteration must be an integer >= 1 (iterations are 1-based), got -4"),
]


@pytest.mark.parametrize(("case", "change", "message"), LOSS_FAULTS, ids=[row[0] for row in LOSS_FAULTS])
def test_loss_door_names_the_argument_in_one_line(case, change, message):
    hooks, view, render, gaussians = _loss_door()
    with pytest.raises(ValueError) as err:
        hooks.loss(*change(5, view, render, gaussians))
    assert str(err.value) == message


def test_loss_door_takes_float64_gaussians_and_a_render_on_another_device_than_the_view():
    """What works is not refused: float64 scales (the scale loss promotes), and the views' maps
    follow the render's device (here both on the CPU; the check compares the tensors given)."""
    hooks, view, render, gaussians = _loss_door()
    extra, _ = hooks.loss(5, view, render, dataclasses.replace(gaussians, scales=gaussians.scales.double()))
    assert torch.isfinite(extra)


DENSIFY_FAULTS = [
    # (case, change of (iteration, view, render_fn, render), the message of hooks.densify)
    ("a float64 render", lambda it, v, fn, r: (it, v, fn, dataclasses.replace(r, depth=r.depth.double())),
     "hooks.densify: render.depth has dtype torch.float64, expected torch.float32 like the maps of view 'v0'"),
    ("render_fn rendering on the meta device",
     lambda it, v, fn, r: (it, v, lambda view: dataclasses.replace(fn(view), alpha=fn(view).alpha.to("meta")), None),
     f"hooks.densify: render_fn(view 'v0').alpha is on the meta device, which holds no values; {_TOO_LATE}"),
    ("a view without Stokes", lambda it, v, fn, r: (it, _without_stokes(v), fn, r),
     "hooks.densify: view 'v0' has no Stokes (view.stokes is NoneType); expected a (3, C, H, W) tensor"),
    ("iteration 0", lambda it, v, fn, r: (0, v, fn, r),
     "hooks.densify: iteration must be an integer >= 1 (iterations are 1-based), got 0"),
]


@pytest.mark.parametrize(("case", "change", "message"), DENSIFY_FAULTS, ids=[row[0] for row in DENSIFY_FAULTS])
def test_densify_door_names_the_argument_in_one_line(case, change, message):
    from test_densifier import _setup

    views, _, _, render_fn, cfg = _setup()
    hooks = PolarHooks(cfg)
    hooks.preprocess(views)
    iteration, view, fn, render = change(cfg.densify.start_iter, views[0], render_fn, render_fn(views[0]))
    with pytest.raises(ValueError) as err:
        hooks.densify(iteration, view, fn, None, render=render)
    assert str(err.value) == message


class _NotPlainData:
    """An object torch's weights-only loader refuses (it would run code to rebuild it)."""


def _truncated_checkpoint(path):
    torch.save({"format": "polargs-reference-checkpoint-v1", "data": torch.zeros(1000)}, path)
    path.write_bytes(path.read_bytes()[:300])


_NOT_OURS = "not a checkpoint of this package"
CHECKPOINT_FAULTS = [
    # (case, how the file is made, the message after "PATH: ")
    ("random bytes", lambda p: p.write_bytes(bytes(range(256)) * 16),
     f"{_NOT_OURS} (torch cannot read it as plain tensors and containers)"),
    ("an object torch refuses to unpickle", lambda p: torch.save({"x": _NotPlainData()}, p),
     f"{_NOT_OURS} (torch cannot read it as plain tensors and containers)"),
    ("a truncated checkpoint", _truncated_checkpoint,
     f"{_NOT_OURS} (torch cannot read it: PytorchStreamReader failed reading zip archive: failed finding central directory)"),
    ("another program's torch file", lambda p: torch.save({"state_dict": {"w": torch.zeros(2)}}, p),
     f'{_NOT_OURS} (no "format": "polargs-reference-checkpoint-v1" entry)'),
    ("an empty file", lambda p: p.write_bytes(b""), f"{_NOT_OURS} (the file is empty)"),
]


@pytest.mark.parametrize(("case", "make", "message"), CHECKPOINT_FAULTS, ids=[row[0] for row in CHECKPOINT_FAULTS])
def test_a_file_that_is_no_checkpoint_of_ours_is_refused_in_one_line(tmp_path, case, make, message):
    from polargs_plugin.backends.reference.trainer import read_checkpoint

    path = tmp_path / "checkpoint.pt"
    make(path)
    with pytest.raises(PolarInputError) as err:
        read_checkpoint(path)
    assert str(err.value) == f"{path}: {message}"  # one line, never torch's advice to load with weights_only=False
    assert err.value.__cause__ is None


SCENE_NAME_FAULTS = [
    # (--scenes entry, the message): names whose run folders gather and --status would skip
    ("..=DATA", "scene '..=DATA': name '..' starts with '.'; give another name (NAME=PATH)"),
    (".=DATA", "scene '.=DATA': name '.' starts with '.'; give another name (NAME=PATH)"),
    (".hidden=DATA", "scene '.hidden=DATA': name '.hidden' starts with '.'; give another name (NAME=PATH)"),
    ("DATA/.scan", "scene 'DATA/.scan': name '.scan' starts with '.'; give another name (NAME=PATH)"),
    ("a/b=DATA", "scene 'a/b=DATA': name 'a/b' may only hold letters, digits, '_', '.', '-'"),
]


@pytest.mark.parametrize(("entry", "message"), SCENE_NAME_FAULTS, ids=[row[0] for row in SCENE_NAME_FAULTS])
def test_scene_names_that_gather_would_lose_are_refused(tmp_path, monkeypatch, entry, message):
    from polargs_plugin.ablation.scenes import parse_scene

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError) as err:
        parse_scene(entry, tmp_path / "cache")
    assert str(err.value) == message
    assert parse_scene("scan.v2=DATA", tmp_path / "cache").name == "scan.v2"  # a dot inside is fine


# ------------------------------------------------------------------------------ data that lies
@pytest.fixture(scope="module")
def scene16(tmp_path_factory):
    """A 16-bit scene folder of 4 views (the bundled scene's angle images, written exactly)."""
    import scene_cache
    from polargs_plugin.data.scene_format import write_scene

    scene = scene_cache.scene("glossy_plane_sphere", num_views=4, width=24, height=24)
    scene.meta["quantize_bits"] = 16
    return write_scene(scene, tmp_path_factory.mktemp("scene16") / "scene")


def _rewrite_angles(folder, view: str, change) -> None:
    """Rewrite the four angle images of ``view`` with ``change(array)`` (dtype kept unless changed)."""
    for path in sorted((folder / "polar").glob(f"{view}_*.png")):
        cv2.imwrite(str(path), change(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))


def _as_8bit(array):
    return np.rint(array / 257).astype(np.uint8)


def _8bit_in_16bit_files(array):
    return np.rint(array / 257).astype(np.uint16)


def _scene8_with_16bit_view(folder):
    _rewrite_angles(folder, "view_000", _as_8bit)
    _rewrite_angles(folder, "view_001", _as_8bit)
    _rewrite_angles(folder, "view_002", _8bit_in_16bit_files)
    _rewrite_angles(folder, "view_003", _as_8bit)
    header = folder / "cameras.json"
    header.write_text(json.dumps({**json.loads(header.read_text()), "bit_depth": 8}))


READ_FAULTS = [
    # (case, how the 16-bit folder is changed, the message, naming the file)
    ("16-bit files holding 0-255 in a folder whose cameras.json says 8-bit", _scene8_with_16bit_view,
     "polar/view_002_000.png: 16-bit image, but cameras.json declares bit_depth 8"),
    ("8-bit files in a folder whose cameras.json says 16-bit", lambda f: _rewrite_angles(f, "view_001", _as_8bit),
     "polar/view_001_000.png: 8-bit image, but cameras.json declares bit_depth 16"),
]


@pytest.mark.parametrize(("case", "change", "message"), READ_FAULTS, ids=[row[0] for row in READ_FAULTS])
def test_declared_bit_depth_is_checked_against_the_files(tmp_path, scene16, case, change, message):
    from polargs_plugin.service import load_dataset

    folder = Path(shutil.copytree(scene16, tmp_path / "scene"))
    change(folder)
    with pytest.raises(PolarInputError) as err:
        load_dataset(str(folder))
    assert str(err.value) == f"{folder}/{message}"


def test_8bit_values_in_16bit_files_warn_naming_the_file_and_the_view(tmp_path, scene16):
    """The issue's view, 257 times too dark: the value range of its files and its brightness
    against the other views each give a warning, the first naming the file, the second the view."""
    from polargs_plugin.service import load_dataset

    folder = Path(shutil.copytree(scene16, tmp_path / "scene"))
    _rewrite_angles(folder, "view_002", _8bit_in_16bit_files)
    with pytest.warns(UserWarning) as caught:
        dataset = load_dataset(str(folder))
    messages = [str(w.message) for w in caught]
    assert (f"{folder}/polar/view_002_000.png: values only up to 255 of 65535 (cameras.json declares bit_depth 16): "
            "8-bit data in a 16-bit file? It reads 257 times too dark") in messages
    brightness = [m for m in messages if "median view's brightness" in m]
    assert len(brightness) == 1 and brightness[0].startswith(f"{folder}: 1 of 4 views differ")
    assert "'view_002' (" in brightness[0] and "times darker)" in brightness[0]
    assert len(dataset.views) == 4


def test_a_bit_depth_beyond_the_files_is_refused_for_angle_images_and_raw_mosaics(tmp_path, synthetic_views):
    from polargs_plugin.data.polar_folder import write_polar_folder
    from polargs_plugin.optics.mosaic import demosaic_polar
    from polargs_plugin.service import ReaderOptions, load_dataset

    views = synthetic_views("glossy_plane_sphere", num_views=3, width=24, height=24)
    folder = write_polar_folder(views, tmp_path / "polar", mode="angles", bit_depth=8)
    with pytest.raises(PolarInputError) as err:
        load_dataset(str(folder), ReaderOptions(bit_depth=16))
    assert str(err.value) == (f"{folder}/images/view_000_0.png: 8-bit file, but --bit-depth 16 was given: "
                              "it holds at most 8 bits")
    raw = torch.full((8, 8), 200, dtype=torch.uint8)
    with pytest.raises(PolarInputError) as err:
        demosaic_polar(raw, "mono", bit_depth=16, source="raw/f.png")
    assert str(err.value) == "raw/f.png: 8-bit raw mosaic, but bit_depth 16 was given: it holds at most 8 bits"
    assert float(demosaic_polar(raw, "mono", bit_depth=8).max()) == pytest.approx(200 / 255)


@pytest.mark.parametrize(("darker", "named"), [(257.0, True), (4.01, True), (3.99, False), (1 / 4.01, True), (1 / 3.99, False)])
def test_brightness_outliers_are_views_a_factor_4_or_more_off_the_median(darker, named):
    from polargs_plugin.data.checks import brightness_outliers

    views = [_view(f"v{i}", seed=i) for i in range(5)]
    for view in views:  # the same mean brightness, 1.0, in every view
        view.stokes[0] /= view.stokes[0].double().mean().float()
    views[3].stokes[0] /= darker
    outliers = brightness_outliers(views)
    assert outliers == ([("v3", pytest.approx(1 / darker, rel=1e-5))] if named else [])
    assert brightness_outliers(views[:2]) == []  # no median to compare with


def test_no_bundled_scene_has_a_brightness_outlier(synthetic_views):
    """Views that see more or less of the object differ in brightness by less than the factor 4."""
    from polargs_plugin.data.checks import brightness_outliers
    from polargs_plugin.data.synthetic import SCENE_NAMES

    for name in SCENE_NAMES:
        assert brightness_outliers(synthetic_views(name, num_views=24, width=32, height=32)) == [], name


# ------------------------------------------------------------------------- run folders and disks
@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """A scene folder of 3 views of 24x24 (trains in about a second)."""
    import scene_cache
    from polargs_plugin.data.scene_format import write_scene

    return write_scene(scene_cache.scene("bumpy_mixed", num_views=3, width=24, height=24),
                       tmp_path_factory.mktemp("tiny") / "scene")


def _request(dataset, out, polar=False, iterations=4, **fields):
    from polargs_plugin.backends.reference.trainer import TrainConfig
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.service import TrainRequest

    train = TrainConfig.cpu(progress=False, iterations=iterations, num_init_points=300)
    return TrainRequest(dataset=str(dataset), out=Path(out), train=train,
                        polar=PolarConfig.cpu_demo() if polar else None, **fields)


# What torch.save raises when the disk is full (or a file size limit is reached): its writer's
# check, not an OSError.
_TORCH_DISK_FULL = "[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534"
_CANNOT_WRITE = "cannot write the file (torch: unexpected pos 576 vs 534; is the disk full?)"


def _disk_full_at(monkeypatch, call: int) -> None:
    """torch.save works until its ``call``-th call, which fails as on a full disk."""
    real, calls = torch.save, []

    def save(obj, f, *args, **kwargs):
        calls.append(f)
        if len(calls) == call:
            Path(f).write_bytes(b"PK\x03\x04 half")  # what a full disk leaves of the file
            raise RuntimeError(_TORCH_DISK_FULL)
        return real(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)


WRITE_FAULTS = [
    # (case, PolarGS on, the torch.save call that fails, what the message names, what it says is kept)
    ("the first checkpoint", False, 1, "checkpoint.pt", "nothing of this run is kept"),
    ("the maps cache, before training", True, 1, "maps/view_000-", "nothing of this run is kept"),
    ("a later periodic checkpoint", False, 2, "checkpoint.pt",
     "RUN/checkpoint.pt keeps the last checkpoint (resume with --resume once there is room)"),
]


@pytest.mark.parametrize(("case", "polar", "call", "named", "kept"), WRITE_FAULTS, ids=[row[0] for row in WRITE_FAULTS])
def test_a_full_disk_is_one_line_and_keeps_only_a_resumable_run(tmp_path, monkeypatch, tiny_scene, case, polar, call,
                                                                 named, kept):
    from polargs_plugin.backends.reference.trainer import read_checkpoint
    from polargs_plugin.service import train_run

    out = tmp_path / "run"
    _disk_full_at(monkeypatch, call)
    with pytest.raises(PolarInputError) as err:
        train_run(_request(tiny_scene, out, polar=polar, checkpoint_every=2))
    message = str(err.value)
    assert message.startswith(f"{out}/{named}") and "\n" not in message
    assert message.endswith(f": {_CANNOT_WRITE}; {kept.replace('RUN', str(out))}")
    if call == 1:  # nothing trained: nothing left, not even the folder this run created
        assert not out.exists()
        return
    # the run trained: its last good checkpoint, its fingerprint, nothing half-written
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "fingerprint.json"]
    assert read_checkpoint(out / "checkpoint.pt")["iteration"] == 2
    monkeypatch.undo()  # room again: the run resumes to its end
    assert train_run(_request(tiny_scene, out, resume=True)).summary["iterations"] == 4


def test_a_full_disk_keeps_a_folder_the_run_did_not_create_and_the_maps_it_found(tmp_path, monkeypatch, tiny_scene):
    from polargs_plugin.service import train_run

    out = tmp_path / "run"
    (out / "maps").mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    _disk_full_at(monkeypatch, 1)
    with pytest.raises(PolarInputError, match="nothing of this run is kept"):
        train_run(_request(tiny_scene, out, polar=True))
    assert sorted(p.name for p in out.iterdir()) == ["maps", "notes.txt"]
    assert list((out / "maps").iterdir()) == []  # nothing half-written in it either


@pytest.mark.slow
def test_a_real_file_size_limit_ends_training_in_one_line_with_nothing_left(tmp_path, tiny_scene):
    """A quota a process cannot exceed (RLIMIT_FSIZE, no root needed): small files are written,
    the checkpoint is not; torch's writer fails the way it does on a full disk."""
    import os
    import resource
    import signal
    import subprocess
    import sys

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG) instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "polargs_plugin.cli", "train", str(tiny_scene), "--out", str(out),
                             "--iters", "4", "--quiet"], capture_output=True, text=True, timeout=300, preexec_fn=limit,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert errors == [line for line in result.stderr.splitlines() if "Traceback" in line or line.startswith("error")]
    assert len(errors) == 1 and errors[0].startswith(f"error: {out}/checkpoint.pt: cannot write the file (torch: ")
    assert errors[0].endswith("; is the disk full?); nothing of this run is kept")
    assert not out.exists()


def test_run_folders_record_absolute_paths(tmp_path, monkeypatch, tiny_scene):
    """A run trained on `base` (relative) records where `base` is, so that mesh and eval read
    the same data from any folder."""
    from polargs_plugin.service import EvalSettings, evaluate, train_run

    shutil.copytree(tiny_scene, tmp_path / "base")
    (tmp_path / "settings.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    request = _request("base", "run", polar=True, iterations=2)
    request.labels = {"config_file": "settings.json"}
    summary = train_run(request).summary
    assert summary["dataset"] == str(tmp_path / "base")
    assert summary["checkpoint"] == str(tmp_path / "run" / "checkpoint.pt")
    assert summary["maps_cache"] == summary["polar_config"]["cache_dir"] == str(tmp_path / "run" / "maps")
    assert summary["config_file"] == str(tmp_path / "settings.json")
    assert json.loads(Path("run/fingerprint.json").read_text())["dataset"] == str(tmp_path / "base")
    metrics = evaluate(Path("run"), EvalSettings(normals=True))
    assert metrics["target"] == str(tmp_path / "run")


def test_mesh_and_eval_refuse_other_data_under_the_same_names(tmp_path, tiny_scene):
    from polargs_plugin.service import load_run, train_run

    data = Path(shutil.copytree(tiny_scene, tmp_path / "base"))
    train_run(_request(data, tmp_path / "run", iterations=2))
    assert load_run(tmp_path / "run").dataset.spec == str(data)
    _rewrite_angles(data, "view_001", lambda a: (a // 2).astype(a.dtype))  # darker: other data, same names
    with pytest.raises(PolarInputError) as err:
        load_run(tmp_path / "run")
    assert str(err.value) == (f"{tmp_path}/run/fingerprint.json: {data} is not the data this run was trained on: "
                              "the images of 1 of 3 views (view_001) differ from those this run was trained on")


def test_a_resume_after_sigkill_removes_the_temporaries_and_takes_over_the_lock(tmp_path, tiny_scene):
    """What SIGKILL leaves in a run folder (a stale lock, a half-written checkpoint under its
    temporary name) is cleaned up by the next training that resumes it."""
    import os
    import socket
    import tempfile

    from polargs_plugin.service import train_run

    out = tmp_path / "run"
    train_run(_request(tiny_scene, out, iterations=2))
    dead = os.fork()
    if dead == 0:
        os._exit(0)
    os.waitpid(dead, 0)
    (out / "train.lock").write_text(json.dumps({"pid": dead, "host": socket.gethostname(), "started": 0.0}))
    for name in ("checkpoint.pt", "summary.json"):  # the temporary names atomic_path gives
        stem, suffix = name.split(".")
        fd, _ = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".{suffix}", dir=out)
        os.write(fd, b"half")
        os.close(fd)
    (out / ".checkpoint.notes.pt").write_text("not a temporary name")
    notes = []
    result = train_run(_request(tiny_scene, out, iterations=4, resume=True), notify=notes.append)
    assert result.summary["iterations"] == 4
    assert any("took over the stale lock of pid" in note for note in notes)
    assert sorted(p.name for p in out.iterdir()) == [".checkpoint.notes.pt", "checkpoint.pt", "fingerprint.json",
                                                      "summary.json"]


_LOCK_RACE = r'''
import json, os, socket, sys, tempfile
from pathlib import Path
from polargs_plugin.io import FolderLock, FolderLockedError

def dead_pid():
    pid = os.fork()
    if pid == 0:
        os._exit(0)
    os.waitpid(pid, 0)
    return pid

def race(lock, racers):
    """racers processes take over one stale lock at once; each says whether it got it."""
    lock.write_text(json.dumps({"pid": dead_pid(), "host": socket.gethostname(), "started": 0.0}))
    go, results, done = os.pipe(), os.pipe(), os.pipe()
    children = []
    for _ in range(racers):
        pid = os.fork()
        if pid == 0:
            os.read(go[0], 1)
            try:
                FolderLock(lock).acquire()
                won = b"1"
            except FolderLockedError:
                won = b"0"
            os.write(results[1], won)
            os.read(done[0], 1)  # alive until every racer has decided: a winner's lock stays live
            os._exit(0)
        children.append(pid)
    os.write(go[1], b"g" * racers)
    outcome = b"".join(os.read(results[0], 1) for _ in range(racers))
    os.write(done[1], b"d" * racers)
    for pid in children:
        os.waitpid(pid, 0)
    for fd in (*go, *results, *done):
        os.close(fd)
    lock.unlink()
    return outcome.count(b"1")

folder = Path(tempfile.mkdtemp())
print(json.dumps([race(folder / "train.lock", int(sys.argv[2])) for _ in range(int(sys.argv[1]))]))
'''


@pytest.mark.slow
def test_processes_taking_over_one_stale_lock_at_once_leave_exactly_one_holder():
    """Many rounds of three processes taking over the same stale lock at the same moment."""
    import os
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", _LOCK_RACE, "150", "3"], capture_output=True, text=True,
                            timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    winners = json.loads(result.stdout)
    assert winners == [1] * 150


@pytest.mark.slow
def test_an_ablation_run_records_its_run_folder_not_the_folder_it_was_built_in(tmp_path, monkeypatch, tiny_scene):
    """A cell is built in ``<out>/.tmp-<name>-<pid>`` and renamed: what it records (metrics.json,
    the mesh's settings) names the run folder, as an absolute path (here from a relative --out)."""
    from polargs_plugin.ablation.cell import Cell, run_cell
    from polargs_plugin.ablation.scenes import SceneSpec

    monkeypatch.chdir(tmp_path)
    cell = Cell(SceneSpec("tiny", str(tiny_scene)), "base", 0, "grid", eval={"num_samples": 20000},
                train_overrides={"iterations": 20, "num_init_points": 300})
    run_cell(cell)
    run_dir = tmp_path / "grid" / cell.name
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["target"] == str(run_dir) and metrics["mesh"] == str(run_dir / "tsdf_mesh.ply")
    assert json.loads((run_dir / "tsdf_mesh.json").read_text())["run_dir"] == str(run_dir)
    assert not [path.name for path in run_dir.glob("*.json") if ".tmp-" in path.read_text()]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a second device (CUDA)")
def test_loss_door_takes_a_render_on_the_gpu_of_cpu_views_but_not_mixed_devices():
    hooks, view, render, gaussians = _loss_door()
    on_gpu = dataclasses.replace(render, **{name: getattr(render, name).detach().cuda()
                                            for name in ("color", "depth", "normal", "alpha")})
    extra, _ = hooks.loss(5, view, on_gpu, dataclasses.replace(gaussians, scales=gaussians.scales.detach().cuda()))
    assert extra.device.type == "cuda"
    with pytest.raises(ValueError) as err:
        hooks.loss(5, view, on_gpu, gaussians)
    assert str(err.value) == ("hooks.loss: gaussians.scales is on cpu but render.color on cuda:0; give every tensor "
                              "on one device")
