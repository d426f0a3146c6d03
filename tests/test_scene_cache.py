"""The shared scene cache of the tests (tests/scene_cache.py): what it hands out is what
``generate_scene`` makes, a copy no test can change for another, and generating leaves the global
generators alone (so a test that gets a cached scene draws the same numbers as one that does not)."""

import numpy as np
import torch

import scene_cache
from polargs_plugin.data.synthetic import generate_scene

ARGS = dict(num_views=2, width=16, height=12, seed=4, mask="surface")


def _arrays(scene):
    for view in scene.views:
        yield from (view.K, view.world_to_camera, view.stokes, view.mask, view.normal_gt, view.depth_gt)
    yield from (*scene.angle_images, *scene.diffuse_gt, *scene.specular_gt, *scene.highlight_masks,
                *scene.overexposed_masks)
    yield from (torch.from_numpy(scene.mesh_vertices), torch.from_numpy(scene.mesh_triangles))


def test_a_cached_scene_is_the_generated_scene_bit_for_bit(synthetic_scene):
    fresh = generate_scene("shiny_torus", **ARGS)
    for cached in (synthetic_scene("shiny_torus", **ARGS), synthetic_scene("shiny_torus", **ARGS)):
        assert [v.name for v in cached.views] == [v.name for v in fresh.views] and cached.meta == fresh.meta
        for got, want in zip(_arrays(cached), _arrays(fresh), strict=True):
            assert got.dtype == want.dtype and torch.equal(got, want)
        assert np.array_equal(cached.object_triangles, fresh.object_triangles)
        assert np.array_equal(cached.visibility, fresh.visibility)


def test_spellings_of_one_call_share_an_entry_and_each_hand_out_is_a_copy(synthetic_views):
    scene_cache.scene("shiny_torus", **ARGS)
    entries = len(scene_cache._CACHE)
    first = scene_cache.scene("shiny_torus", 2, 16, 12, 4, mask="surface")  # the same call, positional
    assert len(scene_cache._CACHE) == entries
    first.views[0].stokes[0] += 1.0  # in place: a View keeps a plain tensor as it is
    first.views[1].name = "renamed"
    first.views.append(first.views[0])
    first.meta["changed"] = True
    first.mesh_vertices[:] = 0.0
    again = scene_cache.scene("shiny_torus", **ARGS)
    assert not torch.equal(first.views[0].stokes, again.views[0].stokes)  # the change took, on the copy
    assert len(again.views) == 2 and again.views[1].name == "view_001" and "changed" not in again.meta
    assert torch.equal(again.views[0].stokes, generate_scene("shiny_torus", **ARGS).views[0].stokes)
    assert again.mesh_vertices.any()
    assert synthetic_views("shiny_torus", **ARGS)[0] is not again.views[0]


def test_generating_draws_nothing_from_the_global_generators():
    torch.manual_seed(5)
    np.random.seed(5)
    generate_scene("bumpy_mixed", num_views=1, width=8, height=8, seed=9)
    after = torch.rand(3), np.random.rand(3)
    torch.manual_seed(5)
    np.random.seed(5)
    assert torch.equal(after[0], torch.rand(3)) and np.array_equal(after[1], np.random.rand(3))
