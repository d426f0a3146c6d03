"""Consistency filters against ground-truth geometry of an analytic sphere."""

import math

import torch

from polargs_plugin.config import FilterConfig
from polargs_plugin.densify.filters import consistency_filter, reprojection_check
from polargs_plugin.optics.azimuth import aolp_from_normals, zenith_from_normals
from polargs_plugin.optics.fresnel import dolp_diffuse
from test_patchmatch_scenes import make_scene


def _scene():
    views, renders = make_scene("sphere", size=48, num_sources=4, textured=False, distance=3.5, focal_ratio=1.6)
    depths = [r[1] for r in renders]
    normals = [r[2] for r in renders]
    aolps = [aolp_from_normals(n) for n in normals]
    dolps = [dolp_diffuse(zenith_from_normals(n)) * r[3] for n, r in zip(normals, renders)]
    return views, renders, depths, normals, aolps, dolps


def test_true_depths_reproject_within_a_pixel():
    views, renders, depths, *_ = _scene()
    reproj, rel, valid, _ = reprojection_check(depths[0], views[0].K, views[0].world_to_camera,
                                               depths[1], views[1].K, views[1].world_to_camera)
    assert valid.float().sum() > 0.5 * renders[0][3].float().sum()
    assert (reproj[valid] < 1.0).float().mean() > 0.95
    assert (rel[valid] < 0.01).float().mean() > 0.95


def test_ground_truth_passes_and_wrong_depth_is_rejected():
    views, renders, depths, normals, aolps, dolps = _scene()
    mask = renders[0][3]
    keep = consistency_filter(depths, normals, views, aolps=aolps, dolps=dolps, reference=0)
    assert keep.shape == mask.shape and not keep[~mask].any()
    assert keep[mask].float().mean() > 0.8
    bad = [d.clone() for d in depths]
    bad[0][:, 10:30, 10:30] *= 1.05
    keep_bad = consistency_filter(bad, normals, views, aolps=aolps, dolps=dolps, reference=0)
    region = mask[:, 10:30, 10:30]
    assert keep_bad[:, 10:30, 10:30][region].float().mean() < 0.05
    # stacking all views gives the same answer for the reference
    assert torch.equal(consistency_filter(depths, normals, views, aolps=aolps, dolps=dolps)[0], keep)


def test_polarimetric_residual_rejects_normals_with_wrong_azimuth():
    views, renders, depths, normals, aolps, dolps = _scene()
    n = normals[0]
    rot = math.radians(30.0)  # rotate every normal about the optical axis: azimuth + 30 deg
    c, s = math.cos(rot), math.sin(rot)
    turned = torch.stack([c * n[0] + s * n[1], -s * n[0] + c * n[1], n[2]])
    wrong = [turned] + normals[1:]
    cfg = FilterConfig()
    keep_ok = consistency_filter(depths, normals, views, aolps=aolps, dolps=dolps, reference=0, config=cfg)
    keep_wrong = consistency_filter(depths, wrong, views, aolps=aolps, dolps=dolps, reference=0, config=cfg)
    polarized = (dolps[0] > cfg.polar_dolp_reference) & keep_ok
    assert polarized.sum() > 20
    assert keep_wrong[polarized].float().mean() < 0.1
    cfg.use_polar = False
    keep_geo = consistency_filter(depths, wrong, views, aolps=aolps, dolps=dolps, reference=0, config=cfg)
    assert torch.equal(keep_geo & keep_ok, keep_ok)


def test_min_consistent_views_counts_sources():
    views, renders, depths, normals, *_ = _scene()
    cfg = FilterConfig(min_consistent_views=1)
    one = consistency_filter(depths[:2], None, views[:2], config=cfg, reference=0)
    cfg.min_consistent_views = 2
    two = consistency_filter(depths[:2], None, views[:2], config=cfg, reference=0)
    assert one.any() and not two.any()


def test_low_dolp_azimuth_noise_rejects_only_in_proportion_to_its_signal():
    """A 30 deg azimuth error gives r = |sin 60 deg| = 0.87 in every source: at DoLP 0.02
    (confidence 0.2) the residual is 0.17 < 0.3 and the pixel stays; at DoLP 0.05 (0.5) it is
    0.43 and the pixel goes. Renormalising the weights would reject both."""
    views, renders, depths, normals, aolps, _ = _scene()
    n = normals[0]
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    wrong = [torch.stack([c * n[0] + s * n[1], -s * n[0] + c * n[1], n[2]])] + normals[1:]
    cfg = FilterConfig()
    geometric = consistency_filter(depths, None, views, reference=0, config=cfg)
    assert geometric.sum() > 20
    for rho, kept in ((0.02, 1.0), (0.05, 0.0)):
        dolps = [torch.full_like(d, rho) for d in depths]
        keep = consistency_filter(depths, wrong, views, aolps=aolps, dolps=dolps, reference=0, config=cfg)
        # a few grazing pixels have a smaller turn of the predicted AoLP in the sources
        assert abs(keep[geometric].float().mean() - kept) < 0.1


def test_incidence_test_keeps_what_two_sources_and_the_reference_see_steeply():
    """max_incidence_deg 45 on the sphere: a pixel stays only when the reference and at least two
    consistent sources see its point at an incidence below 45 deg, computed here independently
    from world points, world normals and camera centres."""
    from polargs_plugin.densify.filters import incidence_cosine

    views, renders, depths, normals, aolps, dolps = _scene()
    loose = consistency_filter(depths, normals, views, reference=0, config=FilterConfig(use_polar=False))
    strict = consistency_filter(depths, normals, views, reference=0,
                                config=FilterConfig(use_polar=False, max_incidence_deg=45.0))
    ref = views[0]
    h, w = depths[0].shape[-2:]
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    K, R, t = ref.K.double(), ref.world_to_camera[:3, :3].double(), ref.world_to_camera[:3, 3].double()
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)]).double()
    world = torch.einsum("ji,jhw->ihw", R, depths[0][0].double() * rays - t[:, None, None])
    normal = torch.einsum("ji,jhw->ihw", R, normals[0].double())

    def cosine(view) -> torch.Tensor:
        towards = view.camera_center.double()[:, None, None] - world
        return (normal * towards).sum(0) / towards.norm(dim=0)

    limit = math.cos(math.radians(45.0))
    steep_sources = sum((cosine(view) >= limit).long() for view in views[1:])
    expected = loose[0] & (cosine(ref) >= limit) & (steep_sources >= 2)
    assert not (strict[0] & ~loose[0]).any()
    assert expected.sum() > 50 and (loose[0] & ~expected).sum() > 50  # the test removes a real share
    assert (strict[0] == expected).float().mean() > 0.98
    assert torch.allclose(incidence_cosine(depths[0], normals[0], ref.K, ref.world_to_camera, ref.world_to_camera)[0][loose[0]],
                          cosine(ref)[loose[0]].float(), atol=1e-4)
