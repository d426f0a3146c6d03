"""Synthetic scene generator checked against analytic geometry and Fresnel physics."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from polargs_plugin.data.scenes import (
    Light,
    Material,
    SceneSpec,
    Texture,
    build_scene,
    evaluate_albedo,
    icosphere,
    intrinsics,
    look_at,
    orbit_cameras,
)
from polargs_plugin.data.environment import Environment, Softbox
from polargs_plugin.data.synthetic import SCENE_NAMES, SceneRenderer, apply_sensor, generate_scene

N_IOR = 1.5
SIZE = 64


# --- independent truth ------------------------------------------------------------------------


def fresnel_dolps(theta: np.ndarray, n: float = N_IOR) -> tuple[np.ndarray, np.ndarray]:
    """(rho_diffuse, rho_specular) from the Fresnel amplitude coefficients (not the closed forms)."""
    cos_i = np.cos(theta)
    cos_t = np.sqrt(1 - np.sin(theta) ** 2 / n**2)
    r_s = ((cos_i - n * cos_t) / (cos_i + n * cos_t)) ** 2
    r_p = ((n * cos_i - cos_t) / (n * cos_i + cos_t)) ** 2
    t_s, t_p = 1 - r_s, 1 - r_p
    return (t_p - t_s) / (t_p + t_s), (r_s - r_p) / (r_s + r_p)


def pixel_grid_rays(K: np.ndarray, w2c: np.ndarray, height: int, width: int):
    """Camera centre and per-pixel world ray directions (H, W, 3) through pixel centres."""
    v, u = np.mgrid[0:height, 0:width] + 0.5
    cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    rotation, translation = w2c[:3, :3], w2c[:3, 3]
    return -rotation.T @ translation, cam @ rotation


def ray_sphere(origin, dirs, center, radius):
    """Nearest positive ray parameter per ray, inf where missed."""
    oc = origin - np.asarray(center)
    a = np.einsum("...i,...i", dirs, dirs)
    b = 2 * dirs @ oc
    c = oc @ oc - radius**2
    disc = b**2 - 4 * a * c
    t = (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def sphere_spec(material: Material, lights: tuple[Light, ...], ambient: float = 0.3) -> SceneSpec:
    vertices, triangles, normals = icosphere(0.5, subdivisions=5)
    return SceneSpec(
        name="test_sphere",
        description="unit test sphere",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=np.zeros(len(triangles), dtype=np.int64),
        materials=(material,),
        lights=lights,
        ambient=ambient,
        target=(0.0, 0.0, 0.0),
        camera_distance=2.0,
        fov_deg=40.0,
        elevations_deg=(10.0, 40.0),
    )


def project(K, w2c, point):
    cam = w2c[:3, :3] @ np.asarray(point) + w2c[:3, 3]
    pix = K @ cam
    return pix[:2] / pix[2]


def wrapped_diff(a, b, period=math.pi):
    d = np.remainder(a - b, period)
    return np.minimum(d, period - d)


def clean_aolp_dolp(stokes: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    s = stokes.mean(dim=1).numpy()  # channel mean (3, H, W)
    return 0.5 * np.arctan2(s[2], s[1]) % math.pi, np.hypot(s[1], s[2]) / np.maximum(s[0], 1e-12)


@pytest.fixture(scope="module")
def camera():
    K = intrinsics(SIZE, SIZE, 40.0)
    w2c = orbit_cameras(3, (0.0, 0.0, 0.35), 3.0, (20.0, 50.0))[1]
    return K, w2c


# --- cameras and meshes -----------------------------------------------------------------------


def test_orbit_cameras_look_at_target_with_world_up_upwards():
    K = intrinsics(80, 60, 40.0)
    target = np.array([0.1, -0.2, 0.3])
    for w2c in orbit_cameras(7, target, 2.5, (-20.0, 50.0)):
        rotation = w2c[:3, :3]
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-12) and np.linalg.det(rotation) > 0
        assert np.allclose(project(K, w2c, target), [40.0, 30.0], atol=1e-9)
        assert np.linalg.norm(-rotation.T @ w2c[:3, 3] - target) == pytest.approx(2.5)
        above = project(K, w2c, target + [0, 0, 0.1])
        assert above[1] < 30.0 and abs(above[0] - 40.0) < 1e-9  # no roll: world up is image up


def test_look_at_opencv_axes():
    w2c = look_at(np.array([0.0, -3.0, 0.0]), np.zeros(3))
    # Looking along +y with z up: camera x = world +x, camera y (down) = world -z, camera z = +y.
    assert np.allclose(w2c[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]])


def test_torus_vertices_satisfy_implicit_equation():
    spec = build_scene("shiny_torus")
    c, s = math.cos(math.radians(35.0)), math.sin(math.radians(35.0))
    untilt = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])  # inverse of the 35 deg x rotation
    p = spec.vertices @ untilt.T
    assert np.allclose((np.hypot(p[:, 0], p[:, 1]) - 0.62) ** 2 + p[:, 2] ** 2, 0.24**2, atol=1e-9)
    ring = 0.62 * np.stack([p[:, 0], p[:, 1], 0 * p[:, 2]], 1) / np.hypot(p[:, 0], p[:, 1])[:, None]
    assert np.allclose(spec.vertex_normals @ untilt.T, (p - ring) / 0.24, atol=1e-9)


# --- geometry: depth, normals, mask ------------------------------------------------------------


def test_depth_normals_match_analytic_sphere_and_plane(camera):
    K, w2c = camera
    clean = SceneRenderer(build_scene("glossy_plane_sphere")).render(K, w2c, SIZE, SIZE)
    origin, dirs = pixel_grid_rays(K, w2c, SIZE, SIZE)
    t_sphere = ray_sphere(origin, dirs, (0, 0, 0.5), 0.5)
    t_plane = -origin[2] / dirs[..., 2]
    p_plane = origin + t_plane[..., None] * dirs
    t_plane = np.where((t_plane > 0) & (np.abs(p_plane[..., :2]) <= 1.5).all(-1), t_plane, np.inf)
    t = np.minimum(t_sphere, t_plane)
    points = origin + np.where(np.isfinite(t), t, 0)[..., None] * dirs
    depth_true = (points @ w2c[:3, :3].T + w2c[:3, 3])[..., 2]
    on_sphere = np.isfinite(t_sphere) & (t_sphere <= t_plane)
    normal_world = np.where(on_sphere[..., None], (points - [0, 0, 0.5]) / 0.5, [0.0, 0.0, 1.0])
    normal_true = normal_world @ w2c[:3, :3].T

    mask = clean.mask[0].numpy()
    hit_true = np.isfinite(t)
    assert (mask != hit_true).mean() < 0.01  # only silhouette pixels of the tessellation differ
    depth = clean.depth[0].numpy()
    normal = clean.normal.numpy().transpose(1, 2, 0)
    assert np.all(depth[~mask] == 0) and np.all(normal[~mask] == 0)
    # Away from grazing silhouettes (where the tessellation matters) depth is exact to 1e-3.
    cos_view = -np.einsum("hwi,hwi->hw", normal_true, dirs @ w2c[:3, :3].T) / np.linalg.norm(dirs, axis=-1)
    good = mask & hit_true & (cos_view > 0.3)
    assert good.sum() > 0.3 * SIZE * SIZE
    assert np.abs(depth - depth_true)[good].max() < 1e-3
    plane_px = good & ~on_sphere
    assert np.abs(depth - depth_true)[plane_px].max() < 1e-4 * depth_true[plane_px].max()
    angle = np.arccos(np.clip(np.einsum("hwi,hwi->hw", normal, normal_true), -1, 1))
    assert np.degrees(angle[good]).max() < 0.5
    assert np.allclose(np.linalg.norm(normal[mask], axis=-1), 1.0, atol=1e-6)
    # Facing the camera along the pixel ray.
    ray_cam = dirs @ w2c[:3, :3].T
    assert np.all(np.einsum("hwi,hwi->hw", normal, ray_cam)[mask] < 1e-3)


def test_checker_on_a_plane_at_a_cell_boundary_has_one_parity_per_cell(camera):
    # glossy_plane_sphere's floor lies at height 0, a checker cell boundary: the renderer's hit
    # points (float32 ray distances) are a rounding error above or below it, which must not flip
    # the cell's colour from pixel to pixel.
    K, w2c = camera
    origin, dirs = pixel_grid_rays(K, w2c, SIZE, SIZE)
    t = (-origin[2] / dirs[..., 2]).astype(np.float32).astype(np.float64)
    points = (origin + t[..., None] * dirs).reshape(-1, 3)
    points = points[(t.reshape(-1) > 0) & (np.abs(points[:, :2]) <= 1.5).all(axis=1)]  # the floor's extent
    assert (points[:, 2] < 0).any() and (points[:, 2] > 0).any()  # rounding on both sides
    scale = 0.3
    offsets = points[:, :2] / scale - np.rint(points[:, :2] / scale)
    inside = (np.abs(offsets) > 1e-3).all(axis=1)  # away from the cells' side boundaries
    parity = (np.floor(points[inside, 0] / scale) + np.floor(points[inside, 1] / scale)) % 2
    floor = Material("floor", albedo=(0.5, 0.5, 0.5), texture=Texture("checker", scale, 0.2))
    albedo = evaluate_albedo(points[inside], floor)
    np.testing.assert_allclose(albedo[:, 0], np.where(parity == 0, 0.6, 0.4))


def test_speckle_value_noise_is_its_lattice_values_at_lattice_points_and_their_mean_halfway():
    from polargs_plugin.data.textures import _lattice_values, _value_noise

    rng = np.random.default_rng(4)
    cells = rng.integers(-50, 50, size=(200, 3))
    scale = 0.08
    np.testing.assert_allclose(_value_noise(cells * scale, scale), _lattice_values(cells), atol=1e-12)
    axis = np.eye(3, dtype=np.int64)[rng.integers(0, 3, 200)]
    halfway = (cells + 0.5 * axis) * scale  # the smoothstep fade is 1/2 there
    np.testing.assert_allclose(_value_noise(halfway, scale),
                               (_lattice_values(cells) + _lattice_values(cells + axis)) / 2, atol=1e-12)
    values = _lattice_values(rng.integers(-10**6, 10**6, size=(20000, 3)))
    assert -1 <= values.min() and values.max() < 1 and abs(values.mean()) < 0.03 and 0.5 < values.std() < 0.65


def test_speckle_texture_is_continuous_and_varies_at_its_scale():
    from polargs_plugin.data.textures import pattern_at as _pattern

    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 1, (5000, 3))
    texture = Texture("speckle", 0.08, 0.6)
    pattern = _pattern(points, texture)
    np.testing.assert_array_equal(pattern, _pattern(points.copy(), texture))  # a function of the point only
    assert 0.3 < pattern.std() < 0.6
    near = _pattern(points + 1e-4 * _unit_rows(rng, 5000), texture)
    far = _pattern(points + 0.08 * _unit_rows(rng, 5000), texture)
    assert np.abs(near - pattern).max() < 0.02  # continuous: no jumps between cells
    assert np.abs(far - pattern).mean() > 0.3  # a cell away, the value is another


def _unit_rows(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_floor_texture_replaces_the_floor_material_only():
    from polargs_plugin.data.family import family_scene, family_settings
    from polargs_plugin.data.scenes import FLOOR_TEXTURES, build_scene, with_floor_texture

    spec = build_scene("glossy_plane_sphere")
    speckled = with_floor_texture(spec, "speckle")
    floor = int(np.unique(spec.triangle_material[~spec.object_triangles])[0])
    for i, (before, after) in enumerate(zip(spec.materials, speckled.materials)):
        assert after.texture == (FLOOR_TEXTURES["speckle"] if i == floor else before.texture)
        assert (after.albedo, after.specular) == (before.albedo, before.specular)
    with pytest.raises(ValueError, match="shiny_torus has no floor"):
        with_floor_texture(build_scene("shiny_torus"), "speckle")
    with pytest.raises(ValueError, match="one of uniform, checker, speckle"):
        with_floor_texture(spec, "marble")
    seed = next(k for k in range(100) if family_settings(k).floor)
    family = family_scene(seed).spec
    textured = with_floor_texture(family, "uniform")
    changed = [i for i, (a, b) in enumerate(zip(family.materials, textured.materials)) if a != b]
    assert changed and all(not family.object_triangles[family.triangle_material == i].any() for i in changed)


# --- polarization -------------------------------------------------------------------------------


def _sphere_camera() -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and pose of the sphere tests' camera."""
    # Aim beside the sphere: off the optical axis, PPA and orthographic azimuths differ.
    return intrinsics(SIZE, SIZE, 40.0), look_at(np.array([1.6, -1.0, 0.6]), np.array([0.25, 0.3, 0.2]))


def _sphere_render(material, lights, ambient=0.3, environment=None):
    spec = replace(sphere_spec(material, lights, ambient), environment=environment)
    K, w2c = _sphere_camera()
    clean = SceneRenderer(spec, refractive_index=N_IOR).render(K, w2c, SIZE, SIZE)
    origin, dirs = pixel_grid_rays(K, w2c, SIZE, SIZE)
    t = ray_sphere(origin, dirs, (0, 0, 0), 0.5)
    points = origin + np.where(np.isfinite(t), t, 1.0)[..., None] * dirs  # misses: any point
    to_camera = (origin - points) / np.linalg.norm(origin - points, axis=-1, keepdims=True)
    zenith = np.arccos(np.clip(np.einsum("hwi,hwi->hw", points / 0.5, to_camera), -1, 1))
    centre = project(K, w2c, np.zeros(3))
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    radial = np.arctan2(-(v - centre[1]), u - centre[0]) % math.pi  # image up is -v
    interior = clean.mask[0].numpy() & np.isfinite(t) & (zenith < np.radians(80))
    return clean, zenith, radial, interior


def test_diffuse_sphere_aolp_radial_and_dolp_fresnel():
    lights = (Light("directional", (0.0, 0.0, 1.0), (0.5, 0.5, 0.5)),)
    clean, zenith, radial, interior = _sphere_render(Material("matte", (0.6, 0.5, 0.4)), lights)
    aolp, dolp = clean_aolp_dolp(clean.stokes)
    rho_d, _ = fresnel_dolps(zenith)
    sel = interior & (rho_d > 0.01)
    assert sel.sum() > 200
    assert np.abs(dolp - rho_d)[sel].max() < 2e-3
    # PPA: the plane of incidence contains the sphere centre, so diffuse AoLP is exactly radial
    # around the centre's projection (docs/conventions.md: diffuse AoLP = azimuth, ccw from +x towards up).
    assert wrapped_diff(aolp, radial)[sel].max() < 1e-3
    assert np.allclose(clean.dolp_diffuse[0].numpy()[sel], rho_d[sel], atol=2e-3)


def test_specular_sphere_aolp_tangential_and_dolp_fresnel():
    lights = (Light("directional", (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)), Light("directional", (1.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    material = Material("mirror_like", (0.0, 0.0, 0.0), specular=1.0, shininess=2.0)
    clean, zenith, radial, interior = _sphere_render(material, lights, ambient=0.0)
    aolp, dolp = clean_aolp_dolp(clean.stokes)
    _, rho_s = fresnel_dolps(zenith)
    sel = interior & (clean.specular.mean(0).numpy() > 1e-3) & (rho_s > 0.05)
    assert sel.sum() > 100
    # rho_s is steep (up to ~3 per radian), so the tessellation's ~1e-3 rad normal error shows.
    assert np.abs(dolp - rho_s)[sel].max() < 5e-3 and np.median(np.abs(dolp - rho_s)[sel]) < 1e-3
    assert wrapped_diff(aolp, radial + math.pi / 2)[sel].max() < 1e-3


# --- environment lighting --------------------------------------------------------------------

CONSTANT_SKY = (0.3, 0.45, 0.6)


def constant_environment(level=CONSTANT_SKY, softboxes=()) -> Environment:
    """Surroundings of one radiance in every direction (no texture), plus ``softboxes``."""
    return Environment(zenith=level, horizon=level, ground=level, texture_amplitude=0.0, softboxes=softboxes,
                       samples=512)


def fresnel_mean(theta: np.ndarray, n: float = N_IOR) -> np.ndarray:
    """(R_s + R_p) / 2 from the amplitude coefficients (independent of the library's formulas)."""
    cos_i = np.cos(theta)
    cos_t = np.sqrt(1 - np.sin(theta) ** 2 / n**2)
    r_s = ((cos_i - n * cos_t) / (cos_i + n * cos_t)) ** 2
    r_p = ((n * cos_i - cos_t) / (n * cos_i + cos_t)) ** 2
    return (r_s + r_p) / 2


def test_mirror_sphere_in_a_constant_environment_reflects_ks_fresnel_times_the_radiance():
    ks = 0.8
    mirror = Material("mirror", (0.0, 0.0, 0.0), specular=ks, shininess=1e5)
    clean, zenith, radial, interior = _sphere_render(mirror, (), ambient=0.0, environment=constant_environment())
    expected = ks * fresnel_mean(zenith)[None] * np.asarray(CONSTANT_SKY)[:, None, None]
    sel = interior
    assert sel.sum() > 300
    relative = np.abs(clean.specular.numpy() / expected - 1)[:, sel]
    # F(theta) is steep near grazing, so the tessellation's ~1e-3 rad normal error shows there.
    assert relative.max() < 0.02 and np.median(relative) < 1e-3
    assert np.abs(clean.diffuse.numpy()[:, sel]).max() == 0  # black albedo: no diffuse part
    aolp, dolp = clean_aolp_dolp(clean.stokes)
    _, rho_s = fresnel_dolps(zenith)
    keep = sel & (rho_s > 0.05)
    # A pure reflection: DoLP = rho_s, AoLP perpendicular to the diffuse (radial) one.
    assert np.abs(dolp - rho_s)[keep].max() < 5e-3 and np.median(np.abs(dolp - rho_s)[keep]) < 1e-3
    assert wrapped_diff(aolp, radial + math.pi / 2)[keep].max() < 1e-3


def test_matte_sphere_in_a_constant_environment_has_colour_albedo_times_radiance():
    # The white-furnace case: a convex Lambertian body lit from every side by radiance L reflects
    # albedo * L whatever its normal (irradiance pi L over the pi of the Lambertian lobe).
    albedo = (0.6, 0.5, 0.4)
    clean, zenith, radial, interior = _sphere_render(Material("matte", albedo), (), ambient=0.0,
                                                     environment=constant_environment())
    expected = np.asarray(albedo)[:, None] * np.asarray(CONSTANT_SKY)[:, None]
    assert np.abs(clean.diffuse.numpy()[:, interior] / expected - 1).max() < 0.03
    aolp, dolp = clean_aolp_dolp(clean.stokes)
    rho_d, _ = fresnel_dolps(zenith)
    keep = interior & (rho_d > 0.01)
    assert wrapped_diff(aolp, radial)[keep].max() < 1e-3  # diffuse AoLP: the normal's azimuth


def test_metal_sphere_reflects_by_the_conductor_fresnel_equations():
    n, k, tint = 0.96, 6.69, (0.91, 0.92, 0.92)
    metal = Material("aluminium", (0.0, 0.0, 0.0), specular=1.0, shininess=1e5, refractive_index=n, extinction=k,
                     specular_tint=tint)
    clean, zenith, radial, interior = _sphere_render(metal, (), ambient=0.0, environment=constant_environment())
    index = complex(n, k)
    cos_i = np.cos(zenith)
    cos_t = np.sqrt(1 - np.sin(zenith) ** 2 / index**2 + 0j)
    r_s = np.abs((cos_i - index * cos_t) / (cos_i + index * cos_t)) ** 2
    r_p = np.abs((index * cos_i - cos_t) / (index * cos_i + cos_t)) ** 2
    expected = ((r_s + r_p) / 2)[None] * (np.asarray(tint) * np.asarray(CONSTANT_SKY))[:, None, None]
    relative = np.abs(clean.specular.numpy() / expected - 1)[:, interior]
    assert relative.max() < 0.01 and np.median(relative) < 1e-3
    _, dolp = clean_aolp_dolp(clean.stokes)
    rho = (r_s - r_p) / (r_s + r_p)
    assert np.abs(dolp - rho)[interior].max() < 5e-3  # no diffuse polarization on a metal


def test_a_softbox_lights_a_matte_sphere_as_an_area_light_and_a_mirror_shows_it_where_it_reflects():
    box = Softbox((0.0, 0.0, 1.0), 10.0, (5.0, 5.0, 5.0))
    dark = constant_environment((0.0, 0.0, 0.0), softboxes=(box,))
    clean, zenith, _, interior = _sphere_render(Material("matte", (0.5, 0.5, 0.5)), (), ambient=0.0, environment=dark)
    # The irradiance of a small disc of radiance L and solid angle omega at incidence cos i is
    # L omega cos i; over pi, times the albedo. Here the normals are the sphere's (centre 0, r 0.5).
    origin, dirs = pixel_grid_rays(*_sphere_camera(), SIZE, SIZE)
    t = ray_sphere(origin, dirs, (0, 0, 0), 0.5)
    normals_z = (origin + np.where(np.isfinite(t), t, 1.0)[..., None] * dirs)[..., 2] / 0.5
    omega = 2 * math.pi * (1 - math.cos(math.radians(10.0)))
    expected = 0.5 * 5.0 * omega / math.pi * np.clip(normals_z, 0, None)
    assert np.abs(clean.diffuse.numpy()[0] - expected)[interior].max() < 2e-3
    mirror = Material("mirror", (0.0, 0.0, 0.0), specular=1.0, shininess=1e5)
    clean, zenith, _, interior = _sphere_render(mirror, (), ambient=0.0, environment=dark)
    to_camera = origin - (origin + np.where(np.isfinite(t), t, 1.0)[..., None] * dirs)
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    normal = (origin + np.where(np.isfinite(t), t, 1.0)[..., None] * dirs) / 0.5
    reflected = 2 * np.einsum("hwi,hwi->hw", normal, to_camera)[..., None] * normal - to_camera
    angle = np.degrees(np.arccos(np.clip(reflected[..., 2], -1, 1)))
    inside, outside = interior & (angle < 9.0), interior & (angle > 11.0)
    assert inside.sum() > 3 and outside.sum() > 300
    assert np.allclose(clean.specular.numpy()[0][inside], 5.0 * fresnel_mean(zenith)[inside], rtol=1e-3)
    assert clean.specular.numpy()[0][outside].max() == 0


def test_an_environment_lit_scene_is_multi_view_consistent_and_clips_its_brightest_reflections():
    scene = generate_scene("glazed_pot", num_views=3, width=64, height=64, seed=1)
    assert scene.meta["environment"]["softboxes"] and "environment lighting" in scene.meta["shading"]
    overexposed = torch.stack(scene.overexposed_masks) & torch.stack([v.mask for v in scene.views])
    assert 0 < overexposed.float().sum() / torch.stack([v.mask for v in scene.views]).float().sum() < 0.1
    for i, view in enumerate(scene.views):
        unclipped = ~scene.overexposed_masks[i][0] & view.mask[0]
        err = (view.image - (scene.diffuse_gt[i] + scene.specular_gt[i]))[:, unclipped]
        assert err.abs().mean() < 0.01
        # The background shows the surroundings, not the dim backdrop.
        assert scene.diffuse_gt[i][:, ~view.mask[0]].mean() > 0.1


def test_environment_rejects_bad_settings():
    with pytest.raises(ValueError, match="radius_deg"):
        Softbox((0.0, 0.0, 1.0), 0.0, (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="unit vector"):
        Softbox((0.0, 0.0, 2.0), 5.0, (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="texture_amplitude"):
        Environment(texture_amplitude=1.0)
    with pytest.raises(ValueError, match="ground"):
        Environment(ground=(-0.1, 0.0, 0.0))


def test_glossy_scene_aolp_flips_where_specular_dominates(camera):
    K, w2c = camera
    clean = SceneRenderer(build_scene("glossy_plane_sphere")).render(K, w2c, SIZE, SIZE)
    origin, dirs = pixel_grid_rays(K, w2c, SIZE, SIZE)
    t = ray_sphere(origin, dirs, (0, 0, 0.5), 0.5)
    points = origin + np.where(np.isfinite(t), t, 1.0)[..., None] * dirs  # misses: any point
    to_camera = (origin - points) / np.linalg.norm(origin - points, axis=-1, keepdims=True)
    zenith = np.arccos(np.clip(np.einsum("hwi,hwi->hw", (points - [0, 0, 0.5]) / 0.5, to_camera), -1, 1))
    rho_d, rho_s = fresnel_dolps(zenith)
    centre = project(K, w2c, [0, 0, 0.5])
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    radial = np.arctan2(-(v - centre[1]), u - centre[0]) % math.pi
    diffuse, specular = clean.diffuse.mean(0).numpy(), clean.specular.mean(0).numpy()
    aolp, dolp = clean_aolp_dolp(clean.stokes)
    on_sphere = clean.mask[0].numpy() & np.isfinite(t) & (zenith < np.radians(80)) & (dolp > 0.01)
    spec_dominant = on_sphere & (specular * rho_s > 3 * diffuse * rho_d)
    diff_dominant = on_sphere & (diffuse * rho_d > 3 * specular * rho_s)
    assert spec_dominant.sum() > 5 and diff_dominant.sum() > 20
    assert wrapped_diff(aolp, radial + math.pi / 2)[spec_dominant].max() < 0.05
    assert wrapped_diff(aolp, radial)[diff_dominant].max() < 0.05


# --- sensor ------------------------------------------------------------------------------------


def test_sensor_quantises_clips_and_recomputes_stokes():
    rng = np.random.default_rng(0)
    s0 = torch.rand(1, 3, 6, 7, dtype=torch.float64) * 2.5  # up to 1.25 per angle: some overexposed
    rho, phi = torch.rand(1, 3, 6, 7, dtype=torch.float64) * 0.8, torch.rand(1, 3, 6, 7, dtype=torch.float64) * math.pi
    stokes = torch.cat([s0, s0 * rho * torch.cos(2 * phi), s0 * rho * torch.sin(2 * phi)])
    angles, recomputed, over = apply_sensor(stokes, rng, noise_std=0.0, quantize_bits=8)
    beta = torch.tensor([0.0, 45.0, 90.0, 135.0], dtype=torch.float64).deg2rad().reshape(4, 1, 1, 1)
    malus = 0.5 * (s0 + stokes[1:2] * torch.cos(2 * beta) + stokes[2:3] * torch.sin(2 * beta))
    assert torch.allclose(angles.double(), (malus.clamp(0, 1) * 255).round() / 255, atol=1e-7)
    i0, i45, i90, i135 = angles
    assert torch.allclose(recomputed, torch.stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135]))
    assert torch.equal(over[0], (malus >= 1).any(0).any(0))
    saturated = (malus >= 1).all(0)  # every angle clipped: polarization is gone
    assert saturated.any()
    assert torch.all(recomputed[1:][:, saturated] == 0)


def test_sensor_rejects_bad_bits():
    with pytest.raises(ValueError, match="quantize_bits"):
        apply_sensor(torch.zeros(3, 3, 2, 2), np.random.default_rng(0), quantize_bits=12)


# --- generated scenes --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["glossy_plane_sphere", "shiny_torus", "bumpy_mixed"])
def test_named_scenes_have_object_highlights_and_consistent_fields(name):
    scene = generate_scene(name, num_views=4, width=48, height=40, seed=3)
    surface = generate_scene(name, num_views=4, width=48, height=40, seed=3, mask="surface")
    assert (scene.meta["mask"], surface.meta["mask"]) == ("object", "surface")
    assert len(scene.views) == len(scene.angle_images) == len(scene.highlight_masks) == 4
    assert scene.meta["azimuth_model"] == "perspective" and scene.meta["scene"] == name
    highlights = torch.stack(scene.highlight_masks)
    assert highlights.any(), "a glossy scene must show highlights"
    for i, view in enumerate(scene.views):
        assert view.stokes.shape == (3, 3, 40, 48) and view.stokes.dtype == torch.float32
        assert view.K.dtype == torch.float64 and view.world_to_camera.shape == (4, 4)
        assert 0.05 < view.mask.float().mean() < 0.95
        assert torch.all(scene.highlight_masks[i] <= view.mask)
        seen = surface.views[i].mask  # every surface: the object and, on glossy_plane_sphere, the floor
        assert torch.all(view.mask <= seen) and torch.all(scene.specular_gt[i][:, ~seen[0]] == 0)
        assert torch.equal(view.mask, seen) == (name != "glossy_plane_sphere")
        for gt_map in (view.depth_gt, view.normal_gt):  # the object's GT only: 0 outside the mask
            assert torch.all(gt_map[:, ~view.mask[0]] == 0)
        assert torch.all(view.depth_gt[view.mask] > 0) and torch.equal(surface.views[i].depth_gt[view.mask], view.depth_gt[view.mask])
        # Noise-free expectation of the training colour is diffuse + specular (clipped per angle).
        unclipped = ~scene.overexposed_masks[i][0]
        err = (view.image - (scene.diffuse_gt[i] + scene.specular_gt[i]))[:, unclipped]
        assert err.abs().mean() < 0.01
    if name == "bumpy_mixed":
        assert torch.stack(scene.overexposed_masks).float().mean() > 0.002


def test_same_seed_identical_different_seed_different_noise():
    a = generate_scene("bumpy_mixed", num_views=2, width=32, height=32, seed=7)
    b = generate_scene("bumpy_mixed", num_views=2, width=32, height=32, seed=7)
    c = generate_scene("bumpy_mixed", num_views=2, width=32, height=32, seed=8)
    for va, vb, vc, ia, ib, ic in zip(a.views, b.views, c.views, a.angle_images, b.angle_images, c.angle_images):
        assert torch.equal(ia, ib) and torch.equal(va.stokes, vb.stokes)
        assert not torch.equal(ia, ic)
        assert torch.equal(va.depth_gt, vc.depth_gt) and torch.equal(va.mask, vc.mask)
        # The difference is noise of the requested size (8-bit quantised).
        assert 0.002 < float((ia - ic).std()) < 0.02


def test_unknown_scene_name():
    with pytest.raises(ValueError, match="glossy_plane_sphere"):
        generate_scene("no_such_scene", num_views=1, width=8, height=8)
    assert len(SCENE_NAMES) >= 3


def test_object_mesh_excludes_the_floor():
    """glossy_plane_sphere: the evaluation GT is the sphere (floor = support); the other scenes
    are all object."""
    from polargs_plugin.data.scenes import build_scene
    from polargs_plugin.data.synthetic import object_submesh

    spec = build_scene("glossy_plane_sphere")
    vertices, triangles = object_submesh(spec.vertices, spec.triangles, spec.object_mask())
    assert np.abs(np.linalg.norm(vertices - [0.0, 0.0, 0.5], axis=1) - 0.5).max() < 1e-9
    assert triangles.max() < len(vertices) and len(triangles) == int((spec.triangle_material == 0).sum())
    for name in ("shiny_torus", "bumpy_mixed", "torus_knot"):
        assert build_scene(name).object_mask().all()
