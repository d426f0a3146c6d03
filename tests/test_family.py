"""The procedural scene family: determinism, the protocol's seed split, the draws' ranges, the
camera layouts, the per-view visibility and the conductor polarization, against independent truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polargs_plugin.data.family import (
    LAYOUTS,
    LIGHTINGS,
    LIT_LAYOUTS,
    LIT_SEED_START,
    SPARSE_VIEWS,
    TEST_SEED_START,
    family_name,
    family_scene,
    family_settings,
    generate_family_scene,
    is_test_seed,
    parse_family,
)
from polargs_plugin.data.scenes import Light, Material, icosphere, intrinsics, look_at, spiral_cameras
from polargs_plugin.data.synthetic import SceneRenderer
from polargs_plugin.data.visibility import triangle_visibility
from polargs_plugin.optics.fresnel import dolp_specular_conductor
from test_synthetic import fresnel_dolps, sphere_spec

DEV_SEEDS = range(40)


def test_names_and_the_protocols_seed_split():
    assert family_name(17) == "family-17"
    assert parse_family("family:17") == 17 and parse_family("family-10003") == 10003
    assert parse_family("family:x") is None and parse_family("torus_knot") is None
    assert not is_test_seed(TEST_SEED_START - 1) and is_test_seed(TEST_SEED_START)
    # The second block: development from LIT_SEED_START, test 10000 seeds later.
    assert is_test_seed(LIT_SEED_START - 1) and not is_test_seed(LIT_SEED_START)
    assert not is_test_seed(LIT_SEED_START + TEST_SEED_START - 1) and is_test_seed(LIT_SEED_START + TEST_SEED_START)
    with pytest.raises(ValueError, match="seeds are >= 0"):
        family_settings(-1)


def test_the_same_seed_draws_the_same_scene_and_others_differ():
    first, again, other = family_scene(5), family_scene(5), family_scene(6)
    assert np.array_equal(first.spec.vertices, again.spec.vertices)
    assert np.array_equal(first.spec.triangles, again.spec.triangles)
    assert first.spec.materials == again.spec.materials and first.spec.lights == again.spec.lights
    assert first.describe() == again.describe()
    assert first.spec.vertices.shape != other.spec.vertices.shape or not np.allclose(first.spec.vertices, other.spec.vertices)


def test_settings_are_drawn_from_their_own_stream_and_within_their_ranges():
    for seed in range(3):  # the cheap draw is the scene's
        assert family_settings(seed) == family_scene(seed).settings
    layouts, floors = set(), 0
    for seed in DEV_SEEDS:
        settings = family_settings(seed)
        layouts.add(settings.layout)
        floors += settings.floor
        assert settings.layout in LAYOUTS
        assert settings.num_views == SPARSE_VIEWS if settings.layout == "sparse" else 24 <= settings.num_views <= 36
        assert 128 <= settings.size <= 160 and 0.002 <= settings.noise_std <= 0.012
        assert not (settings.floor and settings.layout == "orbit")
        if settings.layout == "low":
            assert settings.elevations_deg[1] <= 15.0
    assert layouts == set(LAYOUTS) and 0 < floors < len(DEV_SEEDS)


@pytest.mark.slow
def test_materials_cover_dielectrics_and_metals_within_their_ranges():
    metals = dielectrics = 0
    for seed in range(10):
        for material in family_scene(seed).spec.materials:
            if material.name == "floor":
                continue
            if material.is_conductor:
                metals += 1
                assert material.specular_tint != (1.0, 1.0, 1.0)
            else:
                dielectrics += 1
                assert 1.3 <= material.refractive_index <= 1.8
                assert 0.02 <= material.specular <= 2.5 and 5.0 <= material.shininess <= 300.0
    assert metals > 0 and dielectrics > metals


@pytest.mark.slow
def test_the_object_fits_the_cameras_and_a_floor_is_support():
    for seed in range(6):
        drawn = family_scene(seed)
        spec = drawn.spec
        mask = spec.object_mask()
        used = np.unique(spec.triangles[mask])
        radius = np.linalg.norm(spec.vertices[used], axis=1).max()
        # the whole bounding sphere inside the field of view, from every camera
        assert math.degrees(math.asin(radius / spec.camera_distance)) < spec.fov_deg / 2
        if drawn.settings.floor:
            floor = spec.vertices[np.unique(spec.triangles[~mask])]
            assert np.ptp(floor[:, 2]) == 0 and floor[0, 2] < spec.vertices[used, 2].min()
        else:
            assert mask.all()


def test_spiral_cameras_spread_evenly_over_the_band_and_look_at_the_target():
    band = (-30.0, 60.0)
    cameras = spiral_cameras(200, (0.0, 0.0, 0.0), 3.0, band, azimuth_deg=40.0)
    centres = np.array([-w[:3, :3].T @ w[:3, 3] for w in cameras])
    sines = np.sort(centres[:, 2] / 3.0)
    low, high = (math.sin(math.radians(e)) for e in band)
    # equal areas of the band: the sines of the elevations are uniform over [sin low, sin high]
    assert np.allclose(sines, low + (np.arange(200) + 0.5) / 200 * (high - low), atol=1e-9)
    K = intrinsics(64, 64, 40.0)
    for w2c in cameras[:5]:
        centre = w2c[:3, :3] @ np.zeros(3) + w2c[:3, 3]
        assert np.allclose((K @ centre)[:2] / centre[2], [32.0, 32.0])


def test_triangle_visibility_of_a_sphere_is_its_visible_cap():
    # a camera at distance D from a sphere of radius r sees the cap of area fraction (1 - r / D) / 2
    import open3d as o3d

    vertices, triangles, _ = icosphere(0.5, subdivisions=5)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    distance, size = 2.0, 512
    K = intrinsics(size, size, 40.0)
    w2c = look_at(np.array([distance, 0.0, 0.0]), np.zeros(3))
    seen = triangle_visibility(vertices, triangles, [(K, w2c, size, size)], scene)[0]
    corners = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert area[seen].sum() / area.sum() == pytest.approx((1 - 0.5 / distance) / 2, abs=0.01)
    # a second camera behind the first sees nothing more; one on the other side the rest
    behind = look_at(np.array([-distance, 0.0, 0.0]), np.zeros(3))
    both = triangle_visibility(vertices, triangles, [(K, w2c, size, size), (K, behind, size, size)], scene)
    assert not (both[0] & both[1]).any()


def test_a_metal_reflects_with_the_conductors_polarization_and_no_diffuse_one():
    n, k = 1.02, 2.58  # copper
    metal = Material("copper", (0.1, 0.07, 0.05), specular=1.5, shininess=4.0, refractive_index=n, extinction=k,
                     specular_tint=(0.95, 0.64, 0.54))
    spec = sphere_spec(metal, (Light("directional", (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)),), ambient=0.0)
    renderer = SceneRenderer(spec, shadows=False)
    K = intrinsics(64, 64, 40.0)
    w2c = look_at(np.array([0.0, -2.0, 1.0]), np.zeros(3))
    clean = renderer.render(K, w2c, 64, 64)
    mask = clean.mask[0].numpy()
    # the zenith from the camera-frame normal and the pixel's own ray (towards the camera: -ray)
    v, u = np.mgrid[0:64, 0:64] + 0.5
    rays = np.stack([u, v, np.ones_like(u)]).reshape(3, -1).T @ np.linalg.inv(K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    cosine = -np.einsum("ni,in->n", rays, clean.normal.numpy().reshape(3, -1)).reshape(64, 64)
    theta = np.arccos(np.clip(cosine, 0.0, 1.0))
    assert np.all(clean.dolp_diffuse[0].numpy()[mask] == 0)
    expected = dolp_specular_conductor(torch.from_numpy(theta[mask]), n, k).numpy()
    assert np.abs(clean.dolp_specular[0].numpy()[mask] - expected).max() < 1e-5
    # the highlight takes the metal's tint: red over blue as 0.95 over 0.54
    specular = clean.specular.numpy()[:, mask]
    lit = specular[0] > 1e-3
    assert np.allclose(specular[2][lit] / specular[0][lit], 0.54 / 0.95)
    # a dielectric of the material's own index renders with that index's Fresnel DoLP
    glass = Material("glass", (0.5, 0.5, 0.5), specular=0.0, refractive_index=1.7)
    glass_view = SceneRenderer(sphere_spec(glass, ()), refractive_index=1.3, shadows=False).render(K, w2c, 64, 64)
    rho_d, _ = fresnel_dolps(theta[mask], 1.7)
    assert np.abs(glass_view.dolp_diffuse[0].numpy()[mask] - rho_d).max() < 1e-5


def test_generated_family_scene_carries_its_draw_and_visibility():
    scene = generate_family_scene(3, num_views=4, size=(40, 40))
    assert scene.name == "family-3" and len(scene.views) == 4 and scene.views[0].width == 40
    assert scene.meta["family"]["seed"] == 3 and scene.meta["family"]["test_seed"] is False
    assert scene.meta["noise_std"] == family_settings(3).noise_std
    vertices, triangles = scene.object_mesh()
    assert scene.visibility.shape == (4, len(triangles)) and scene.visibility.any(axis=1).all()
    again = generate_family_scene(3, num_views=4, size=(40, 40))
    for a, b in zip(scene.angle_images, again.angle_images):
        assert torch.equal(a, b)


def test_the_whole_scene_generators_take_their_view_generators_arguments():
    """Each argument is declared once, on the view-at-a-time generator: the whole-scene twin shows
    and accepts the same ones (floor_texture and the family's forwarded options included) and
    yields the same views."""
    import inspect

    from polargs_plugin.data.family import generate_family_scene_views
    from polargs_plugin.data.synthetic import generate_scene, generate_scene_views

    for whole, parts in ((generate_scene, generate_scene_views), (generate_family_scene, generate_family_scene_views)):
        assert inspect.signature(whole).parameters == inspect.signature(parts).parameters
    floor = generate_scene("glossy_plane_sphere", num_views=1, width=24, height=24, floor_texture="speckle")
    plain = generate_scene("glossy_plane_sphere", num_views=1, width=24, height=24)
    assert not torch.equal(floor.angle_images[0], plain.angle_images[0])
    assert torch.equal(floor.views[0].depth_gt, plain.views[0].depth_gt)
    options = dict(num_views=2, size=(24, 20), quantize_bits=16, mask="surface", shadows=False)
    whole = generate_family_scene(3, **options)
    parts = list(generate_family_scene_views(3, **options))
    assert whole.meta["quantize_bits"] == 16 and whole.meta["mask"] == "surface" and "no shadows" in whole.meta["shading"]
    for view, part in zip(whole.views, parts, strict=True):
        assert torch.equal(view.stokes, part.views[0].stokes)
    with pytest.raises(TypeError, match="width"):
        generate_family_scene(3, width=24)  # the family's size is ``size``, not width/height


def test_the_ablation_spells_a_family_scene_family_colon_seed(tmp_path):
    from polargs_plugin.ablation.scenes import parse_scene
    from polargs_plugin.data.synthetic import GENERATOR_VERSION

    settings = family_settings(16)
    spec = parse_scene("family:16", tmp_path)
    assert (spec.name, spec.bundled, spec.seed) == ("family-16", "family", 16)
    assert (spec.views, spec.width, spec.height) == (settings.num_views, settings.size, settings.size)
    size = settings.size
    assert spec.path == str(tmp_path.resolve() / f"family-16-{settings.num_views}v-{size}x{size}-g{GENERATOR_VERSION}")
    smaller = parse_scene("family:16", tmp_path, views=6, width=32, height=32)
    assert (smaller.views, smaller.width) == (6, 32) and smaller.path != spec.path
    with pytest.raises(ValueError, match="family:SEED"):
        parse_scene("family:x", tmp_path)


LIT_DEV_SEEDS = range(LIT_SEED_START, LIT_SEED_START + 40)


def test_second_block_seeds_draw_their_lighting_and_the_stand_layout():
    lightings, layouts = set(), set()
    for seed in LIT_DEV_SEEDS:
        settings = family_settings(seed)
        layouts.add(settings.layout)
        assert settings.layout in LIT_LAYOUTS
        if settings.layout == "stand":
            assert settings.floor and settings.elevations_deg == (-15.0, 60.0)
    for seed in LIT_DEV_SEEDS[:16]:
        drawn = family_scene(seed)
        lightings.add(drawn.lighting)
        spec = drawn.spec
        assert (spec.environment is not None) == (drawn.lighting != "lights")
        assert (len(spec.lights) > 0) == (drawn.lighting != "environment")
        assert drawn.describe()["lighting"] == drawn.lighting
        if spec.environment is not None:
            assert 1 <= len(spec.environment.softboxes) <= 3
            for material in spec.materials[:1]:  # the body: glossy under surroundings
                assert material.specular >= 0.5
    assert lightings == set(LIGHTINGS) and layouts == set(LIT_LAYOUTS)
    # The first block is lit by lights alone, as it always was.
    assert all(family_scene(seed).lighting == "lights" and family_scene(seed).spec.environment is None for seed in range(3))


def test_the_stand_raises_the_object_on_a_thin_rod_whose_underside_few_views_see():
    seed = next(s for s in LIT_DEV_SEEDS if family_settings(s).layout == "stand")
    spec = family_scene(seed).spec
    on_object = spec.object_mask()
    object_z = spec.vertices[np.unique(spec.triangles[on_object]), 2]
    support = spec.triangles[~on_object]
    floor_z = spec.vertices[np.unique(support), 2].min()
    assert object_z.min() - floor_z == pytest.approx(0.35 + 1e-3, abs=1e-6)
    rod = [m for m in spec.materials if m.name == "stand"]
    assert len(rod) == 1
    rod_index = spec.materials.index(rod[0])
    rod_vertices = spec.vertices[np.unique(spec.triangles[spec.triangle_material == rod_index])]
    # A vertical rod of radius 0.035 from the floor up into the object's lowest point.
    radius = np.linalg.norm(rod_vertices[:, :2] - rod_vertices[:, :2].mean(axis=0), axis=1)
    assert np.allclose(radius, 0.035, atol=1e-9)
    assert rod_vertices[:, 2].min() == pytest.approx(floor_z + 1e-3, abs=1e-6) and rod_vertices[:, 2].max() > object_z.min()
