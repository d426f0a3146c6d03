"""PolarDensifier on an analytic plane: schedule, hole filling, N_opt, checkpointing."""

import pytest
import torch

from polargs_plugin.config import PolarConfig
from polargs_plugin.densify.densifier import PolarDensifier
from polargs_plugin.densify.seeding import seed_mask, seed_relative_depth
from polargs_plugin.optics.azimuth import aolp_from_normals, zenith_from_normals
from polargs_plugin.optics.fresnel import dolp_diffuse
from polargs_plugin.types import PolarMaps, RenderOut
from test_patchmatch_scenes import make_scene

HOLE = (slice(None), slice(14, 26), slice(14, 26))


def _setup():
    views, renders = make_scene("plane", size=40, num_sources=4)
    by_name = {v.name: r for v, r in zip(views, renders)}
    cfg = PolarConfig.cpu_demo()
    model = cfg.densify.patchmatch.azimuth_model  # the maps follow the model the densifier inverts
    maps = {}
    for v, (img, depth, normal, mask) in zip(views, renders):
        maps[v.name] = PolarMaps(aolp=aolp_from_normals(normal, K=v.K, model=model),
                                 dolp=dolp_diffuse(zenith_from_normals(normal, K=v.K, model=model)), intensity=img)

    def render_fn(view):
        img, depth, normal, mask = by_name[view.name]
        alpha = torch.ones_like(depth)
        depth, normal = depth.clone(), normal.clone()
        if view.name == "v0":  # the model has a hole in the reference view
            alpha[HOLE] = 0.0
            depth[HOLE] = 0.0
            normal[(slice(None),) + HOLE[1:]] = 0.0
        return RenderOut(color=img, depth=depth, normal=normal, alpha=alpha)

    cfg.densify.patchmatch.iterations = 3
    cfg.densify.stride = 2
    return views, renders, maps, render_fn, cfg


def test_synthetic_preset_inverts_the_bundled_data_azimuth_model():
    from polargs_plugin.data.synthetic import AZIMUTH_MODEL

    for cfg in (PolarConfig.synthetic(), PolarConfig.cpu_demo()):
        assert cfg.densify.patchmatch.azimuth_model == AZIMUTH_MODEL
        assert cfg.densify.filters.azimuth_model == AZIMUTH_MODEL


def test_schedule_follows_config():
    views, renders, maps, render_fn, cfg = _setup()
    dens = PolarDensifier(cfg, views, maps)
    d = cfg.densify
    assert not dens.should_run(d.start_iter - d.interval)
    assert dens.should_run(d.start_iter) and dens.should_run(d.end_iter)
    assert not dens.should_run(d.start_iter + 1) and not dens.should_run(d.end_iter + d.interval)
    assert dens(d.start_iter + 1, views[0], render_fn, None) is None
    cfg.densify.enabled = False
    assert not dens.should_run(d.start_iter)


@pytest.mark.slow
def test_fills_a_render_hole_with_gaussians_on_the_plane():
    views, renders, maps, render_fn, cfg = _setup()
    dens = PolarDensifier(cfg, views, maps)
    assert dens.normal_target("v0") is None
    new = dens(cfg.densify.start_iter, views[0], render_fn, None)
    assert new is not None and len(new) > 10
    # on the world plane z = 0: within the 1 % relative-depth filter (depth ~ 4), mostly far better
    assert new.means[:, 2].abs().max() < 0.04 and new.means[:, 2].abs().median() < 0.005
    # seeds only inside the hole (elsewhere the render already agrees with PatchMatch)
    cam = new.means @ views[0].R.T.float() + views[0].t.float()
    pix = (cam @ views[0].K.T.float())
    u, v = pix[:, 0] / pix[:, 2], pix[:, 1] / pix[:, 2]
    inside = (u > 13) & (u < 27) & (v > 13) & (v < 27)
    assert inside.float().mean() > 0.9
    # about a quarter of the 12x12 hole at stride 2, minus filtered pixels
    assert len(new) <= 36
    normal, valid = dens.normal_target("v0")
    gt = renders[0][2]
    ang = torch.rad2deg(torch.arccos((normal * gt).sum(0).clamp(-1, 1)))
    assert valid.float().mean() > 0.5
    assert (ang[valid[0]] < 5).float().mean() > 0.9


@pytest.mark.slow
def test_the_budget_caps_the_appends_of_the_whole_run_at_a_fraction_of_the_model():
    """budget_fraction 0.1 of a 100-Gaussian model: 10 Gaussians over every call, the first call
    takes what it can, later ones get nothing, and PatchMatch's normal targets still refresh; the
    budget survives a checkpoint."""
    from types import SimpleNamespace

    views, renders, maps, render_fn, cfg = _setup()
    free = PolarDensifier(cfg, views, maps)
    unbounded = free(cfg.densify.start_iter, views[0], render_fn, None)
    assert unbounded is not None and len(unbounded) > 10  # more seeds than the budget below allows
    cfg.densify.budget_fraction = 0.1
    model = SimpleNamespace(means=torch.zeros(100, 3))
    dens = PolarDensifier(cfg, views, maps)
    first = dens(cfg.densify.start_iter, views[0], render_fn, model)
    assert len(first) == 10 and dens.budget == 10 and dens.appended == 10
    twice = SimpleNamespace(means=torch.zeros(200, 3))  # the budget is fixed at the first call
    second = dens(cfg.densify.start_iter + cfg.densify.interval, views[0], render_fn, twice)
    assert second is None and dens.appended == 10 and dens.calls == 2
    resumed = PolarDensifier(cfg, views, maps)
    resumed.load_state_dict(dens.state_dict())
    assert (resumed.budget, resumed.appended) == (10, 10)
    with pytest.raises(ValueError, match="needs the current Gaussians"):
        PolarDensifier(cfg, views, maps)(cfg.densify.start_iter, views[0], render_fn, None)


def test_seeding_threshold_is_a_number_of_pixel_footprints():
    """The same number of footprints at any resolution: the CPU preset's 2.5 is 1.42 % of the depth
    at the bundled scenes' 128 px (f = 175.8) and 5.68 % at this file's 40 px (f = 44)."""
    k = PolarConfig.cpu_demo().densify.seed_depth_footprints
    for focal, relative in ((175.84, 0.01422), (44.0, 0.05682)):
        K = torch.tensor([[focal, 0.0, 20.0], [0.0, focal, 20.0], [0.0, 0.0, 1.0]])
        assert abs(seed_relative_depth(k, K) - relative) < 1e-4
    # a render 1.5 footprints behind PatchMatch is wrong, 0.5 footprints behind is not
    K = torch.tensor([[44.0, 0.0, 20.0], [0.0, 44.0, 20.0], [0.0, 0.0, 1.0]])
    pm = torch.full((1, 1, 2), 4.0)
    rendered = pm + torch.tensor([[[1.5, 0.5]]]) * 4.0 / 44.0
    seeds = seed_mask(torch.ones(1, 1, 2, dtype=torch.bool), pm, rendered, torch.ones(1, 1, 2),
                      relative_depth=seed_relative_depth(1.0, K))
    assert seeds.tolist() == [[[True, False]]]


def test_state_dict_round_trip():
    views, renders, maps, render_fn, cfg = _setup()
    dens = PolarDensifier(cfg, views, maps)
    dens(cfg.densify.start_iter, views[0], render_fn, None)
    state = dens.state_dict()
    other = PolarDensifier(cfg, views, maps)
    other.load_state_dict(state)
    n1, v1 = dens.normal_target("v0")
    n2, v2 = other.normal_target("v0")
    assert torch.equal(n1, n2) and torch.equal(v1, v2) and other.calls == 1
    a = dens(cfg.densify.start_iter + cfg.densify.interval, views[1], render_fn, None)
    b = other(cfg.densify.start_iter + cfg.densify.interval, views[1], render_fn, None)
    assert (a is None) == (b is None)
    if a is not None:
        assert torch.equal(a.means, b.means)


class _FolderMaps(dict):
    """Maps with a cache folder, as MapsStore on a run's maps/ (the densifier's state goes there)."""

    def __init__(self, maps, folder):
        super().__init__(maps)
        self.folder = folder


def test_the_state_in_a_folder_gives_the_same_densification_and_leaves_nothing_behind(tmp_path):
    """With a cache folder, each visited view's PatchMatch result lives in a file of a temporary
    folder there (nothing per view in memory); the appends, the L_n targets and the checkpoint
    state equal the in-memory densifier's bit for bit; the folder goes with the densifier."""
    import gc

    views, renders, maps, render_fn, cfg = _setup()
    memory = PolarDensifier(cfg, views, maps)
    spilled = PolarDensifier(cfg, views, _FolderMaps(maps, tmp_path))
    (folder,) = tmp_path.glob(".dense-state-*")
    for k, view in enumerate(views[:3]):  # the later calls read the earlier views' kept depths
        it = cfg.densify.start_iter + k * cfg.densify.interval
        a, b = memory(it, view, render_fn, None), spilled(it, view, render_fn, None)
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.equal(a.means, b.means) and torch.equal(a.scales, b.scales)
    assert spilled._states._memory == {} and len(list(folder.iterdir())) == 3
    for view in views[:3]:
        (n1, v1), (n2, v2) = memory.normal_target(view.name), spilled.normal_target(view.name)
        assert n2.device == views[0].device and torch.equal(n1, n2) and torch.equal(v1, v2)
    assert spilled.normal_target(views[3].name) is None
    state_a, state_b = memory.state_dict(), spilled.state_dict()
    assert state_a["depths"].keys() == state_b["depths"].keys()
    assert all(torch.equal(state_a["depths"][k], state_b["depths"][k]) for k in state_a["depths"])
    resumed = PolarDensifier(cfg, views, _FolderMaps(maps, tmp_path))
    resumed.load_state_dict(state_b)
    assert torch.equal(resumed.normal_target(views[1].name)[0], memory.normal_target(views[1].name)[0])
    del spilled, resumed
    gc.collect()
    assert list(tmp_path.glob(".dense-state-*")) == []


def test_source_depth_prefers_kept_patchmatch_then_opaque_render_then_unconfirmed_patchmatch():
    from polargs_plugin.densify.densifier import source_depth

    rendered = torch.tensor([[[2.0, 2.0, 2.0, 2.0]]])
    alpha = torch.tensor([[[0.9, 0.9, 0.1, 0.1]]])
    pm = torch.tensor([[[3.0, 3.0, 3.0, 0.0]]])
    kept = torch.tensor([[[True, False, False, False]]])
    assert torch.equal(source_depth(rendered, alpha, 0.5), torch.tensor([[[2.0, 2.0, 0.0, 0.0]]]))
    assert torch.equal(source_depth(rendered, alpha, 0.5, pm, kept), torch.tensor([[[3.0, 2.0, 3.0, 0.0]]]))


_FULL_RUN = r"""
import hashlib, json, sys
import torch
from polargs_plugin import PolarConfig, PolarHooks
from polargs_plugin.backends.reference.model import PARAM_NAMES
from polargs_plugin.backends.reference.strategy import DensityConfig
from polargs_plugin.backends.reference.trainer import TrainConfig, Trainer
from polargs_plugin.data.synthetic import generate_scene

# 6 neighbouring views of an 18-view orbit (every view has sources within the triangulation limits);
# surface masks: the textured floor inside them gives PatchMatch depth for Dense to append at
views = generate_scene("glossy_plane_sphere", num_views=18, width=32, height=32, mask="surface").views[:6]
cfg = PolarConfig.cpu_demo()
cfg.densify.start_iter, cfg.densify.end_iter, cfg.densify.interval = 20, 200, 10
cfg.densify.patchmatch.iterations = 2
train = TrainConfig.cpu(iterations=200, progress=False, num_init_points=300, init_resolution=32,
                        density=DensityConfig(max_gaussians=1500, opacity_reset=False))
trainer = Trainer(views, train, hooks=PolarHooks(cfg))
trainer.train()
digest = hashlib.sha256()
for name in PARAM_NAMES:
    digest.update(getattr(trainer.model, name).detach().contiguous().numpy().tobytes())
print(json.dumps({"params": digest.hexdigest(), "num": trainer.model.num,
                  "stats": trainer.hooks._densifier.stats}))
"""


@pytest.mark.slow
def test_two_full_runs_with_the_same_seed_are_bit_identical():
    """A Full run (PC + Dense scheduled every 10 iterations) repeated in a fresh process,
    with numba and torch on 2 threads, gives bit-identical parameters."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_NUM_THREADS="2", OMP_NUM_THREADS="2", PYTHONWARNINGS="ignore")
    runs = []
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", _FULL_RUN], env=env, capture_output=True, text=True,
                              timeout=900, cwd=os.path.dirname(__file__))
        assert done.returncode == 0, done.stderr[-2000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    assert runs[0]["stats"]["added"] > 0  # Dense did append Gaussians
    assert runs[0] == runs[1]


def test_even_propagation_distances_are_refused():
    """An even distance would read pixels of the colour being updated (a race between threads)."""
    import pytest

    from polargs_plugin.densify.patchmatch import patchmatch

    views, renders, maps, render_fn, cfg = _setup()
    cfg.densify.patchmatch.propagation_distances = (1, 2)
    ref, src = views[0], views[1]
    out = render_fn(src)
    with pytest.raises(ValueError, match="propagation_distances must be odd"):
        patchmatch(ref.image, ref.K, ref.world_to_camera, src.image[None], src.K[None], src.world_to_camera[None],
                   out.depth, out.normal, config=cfg.densify.patchmatch)
