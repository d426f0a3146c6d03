"""Procedural scenes for the synthetic polarimetric generator: meshes, materials, lights, cameras.

Everything here is plain numpy (float64) and deterministic: a scene depends on its name only,
never on the noise seed. World frame: z up, metres-like units, objects within ~1 of the origin.
The renderer lives in :mod:`polargs_plugin.data.synthetic`.

Scenes (each chosen to be hard for photometric 3D Gaussian Splatting, as targeted by PolarGS):

- ``glossy_plane_sphere``: a glossy, textureless red sphere resting on a weakly textured matte
  plane; highlights move with the view and nothing but shading constrains the sphere. The plane
  is support (``object_triangles``): not in the masks, not in the evaluation's GT.
- ``shiny_torus``: a tilted shiny torus with a weak procedural texture, lit by three lights,
  giving small sharp highlights on a concave/convex surface.
- ``bumpy_mixed``: a displaced icosphere of two materials (glossy ceramic and textured matte
  clay) under a strong light, so that the glossy highlights overexpose (clip) and lose their
  polarization as on a real sensor.
- ``torus_knot``: a glossy (2, 3) torus knot with self-occlusions and thin parts.
- ``glazed_pot``: a glazed, light-coloured rippled pot with an aluminium knob on a floor, lit by
  surroundings it mirrors (:class:`~polargs_plugin.data.environment.Environment`: a sky, a
  coloured horizon, two softboxes whose reflections clip), no point lights: the reflections move
  with the view over much of the surface, the failure photometric correction exists for.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import open3d as o3d

from polargs_plugin.data.cameras import look_at
from polargs_plugin.data.environment import Environment, Softbox
from polargs_plugin.data.textures import Texture, pattern_at

__all__ = [
    "Texture",
    "Material",
    "Light",
    "SceneSpec",
    "SCENE_BUILDERS",
    "build_scene",
    "icosphere",
    "plane",
    "tube",
    "look_at",
    "orbit_cameras",
    "spiral_cameras",
    "scene_cameras",
    "CAMERA_LAYOUTS",
    "intrinsics",
    "evaluate_albedo",
    "pattern_at",
    "FLOOR_TEXTURES",
    "with_floor_texture",
    "same_arguments_as",
]


@dataclass(frozen=True)
class Material:
    """A dielectric (or a conductor) with a Lambertian diffuse lobe and a Blinn-Phong specular lobe.

    Attributes:
        name: material name (recorded in the scene meta).
        albedo: (3,) RGB diffuse albedo.
        texture: procedural modulation of ``albedo``.
        specular: specular weight k_s.
        shininess: Blinn-Phong exponent (higher = smaller, sharper highlights).
        refractive_index: n of this material's Fresnel polarization; None: the renderer's
            (``generate_scene(refractive_index=...)``).
        extinction: k of a conductor's complex index n + i k (0: a dielectric). A conductor (a
            metal) polarizes its reflection by the conductor Fresnel equations and its diffuse
            lobe (rough-surface scattering) not at all; ``refractive_index`` must then be given.
        specular_tint: (3,) RGB colour of the specular lobe: white for a dielectric (highlights
            take the light's colour), the metal's colour for a conductor.
    """

    name: str
    albedo: tuple[float, float, float]
    texture: Texture = field(default_factory=Texture)
    specular: float = 0.0
    shininess: float = 32.0
    refractive_index: float | None = None
    extinction: float = 0.0
    specular_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        if self.extinction < 0:
            raise ValueError(f"material {self.name!r}: extinction must be >= 0, got {self.extinction}")
        if self.extinction > 0 and not (self.refractive_index or 0) > 0:
            raise ValueError(f"material {self.name!r}: a conductor (extinction > 0) needs refractive_index > 0")
        if self.extinction == 0 and self.refractive_index is not None and not self.refractive_index > 1:
            raise ValueError(f"material {self.name!r}: a dielectric's refractive_index must be > 1, got {self.refractive_index}")

    @property
    def is_conductor(self) -> bool:
        """A metal: complex index with extinction k > 0."""
        return self.extinction > 0


@dataclass(frozen=True)
class Light:
    """A light fixed in the world (highlights therefore move with the camera).

    Attributes:
        kind: ``"directional"`` (``vector`` = unit direction towards the light) or ``"point"``
            (``vector`` = position; irradiance falls off as 1/d^2 relative to distance 1).
        vector: (3,) direction or position, world frame.
        color: (3,) RGB intensity.
    """

    kind: str
    vector: tuple[float, float, float]
    color: tuple[float, float, float]


@dataclass
class SceneSpec:
    """A renderable procedural scene.

    Attributes:
        name: scene name.
        description: one sentence for the meta file.
        vertices: (V, 3) float64 world positions.
        triangles: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        vertex_normals: (V, 3) float64 unit shading normals (analytic where the surface is).
        triangle_material: (F,) int64 index into ``materials``.
        materials: the materials.
        lights: the lights.
        ambient: uniform ambient irradiance added to the diffuse term.
        target: (3,) point the cameras look at.
        camera_distance: distance of the cameras from ``target``.
        fov_deg: horizontal field of view of the cameras.
        elevations_deg: (min, max) camera elevation above the target's horizontal plane.
        background: mean level of the dim unpolarized backdrop (training-colour units).
        object_triangles: (F,) bool, True for the triangles of the object being reconstructed,
            False for supporting geometry (floor, backdrop); None means every triangle is object.
            The evaluation ground truth (``gt_mesh.ply``, docs/evaluation.md) is the object part.
        camera_layout: where the cameras sit between the elevations (:func:`scene_cameras`):
            ``"rings"`` (three elevation rings, :func:`orbit_cameras`) or ``"spiral"`` (evenly
            spread over the band of elevations, :func:`spiral_cameras`).
        camera_azimuth_deg: azimuth of the first camera (turns the whole layout about the z axis).
        environment: surroundings that light the scene and that its glossy surfaces mirror
            (:class:`~polargs_plugin.data.environment.Environment`), besides ``lights`` and
            ``ambient``; None: lights and ambient only.
    """

    name: str
    description: str
    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray
    triangle_material: np.ndarray
    materials: tuple[Material, ...]
    lights: tuple[Light, ...]
    ambient: float
    target: tuple[float, float, float]
    camera_distance: float
    fov_deg: float
    elevations_deg: tuple[float, float]
    background: float = 0.04
    object_triangles: np.ndarray | None = None
    camera_layout: str = "rings"
    camera_azimuth_deg: float = 0.0
    environment: Environment | None = None

    def object_mask(self) -> np.ndarray:
        """(F,) bool: which triangles belong to the object (all of them when not specified)."""
        if self.object_triangles is None:
            return np.ones(len(self.triangles), dtype=bool)
        mask = np.asarray(self.object_triangles, dtype=bool)
        if mask.shape != (len(self.triangles),):
            raise ValueError(f"object_triangles must have one entry per triangle ({len(self.triangles)}), got {mask.shape}")
        return mask


# ---------------------------------------------------------------------------------------------
# Meshes: each returns (vertices (V,3), triangles (F,3), normals (V,3)).

Mesh = tuple[np.ndarray, np.ndarray, np.ndarray]


def _orient_outward(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Reorder each triangle so that its geometric normal agrees with its vertex normals."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    flip = np.einsum("fi,fi->f", face, normals[triangles].sum(axis=1)) < 0
    out = triangles.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def icosphere(radius: float, center=(0.0, 0.0, 0.0), subdivisions: int = 5) -> Mesh:
    """Geodesic sphere: an icosahedron subdivided ``subdivisions`` times and projected.

    Normals are the analytic sphere normals (p - center) / radius.
    """
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(subdivisions)
    unit = np.asarray(mesh.vertices, dtype=np.float64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    vertices = radius * unit + np.asarray(center, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    return vertices, _orient_outward(vertices, triangles, unit), unit


def plane(size: float, height: float = 0.0, segments: int = 8) -> Mesh:
    """Square ``size`` x ``size`` horizontal plane z = ``height`` centred on the z axis, normal +z."""
    ticks = np.linspace(-size / 2, size / 2, segments + 1)
    x, y = np.meshgrid(ticks, ticks, indexing="xy")
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, height)], axis=1)
    idx = np.arange(x.size).reshape(segments + 1, segments + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int64)
    normals = np.tile([0.0, 0.0, 1.0], (vertices.shape[0], 1))
    return vertices, _orient_outward(vertices, triangles, normals), normals


def tube(curve: Callable[[np.ndarray], np.ndarray], radius: float, segments: int = 256, sides: int = 48) -> Mesh:
    """Tube of constant ``radius`` around a closed curve.

    Args:
        curve: maps parameters t in [0, 1) of shape (S,) to points (S, 3); curve(0) = curve(1).
        radius: tube radius (smaller than the curve's radius of curvature).
        segments: samples along the curve.
        sides: samples around the tube.

    Frames are parallel-transported along the curve and the closing twist is spread evenly, so the
    mesh closes without a seam. Normals are the analytic tube normals (radial from the curve).
    """
    t = np.arange(segments) / segments
    centre = curve(t)
    tangent = np.roll(centre, -1, axis=0) - np.roll(centre, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    seed = np.eye(3)[np.argmin(np.abs(tangent[0]))]
    normal = np.empty_like(centre)
    normal[0] = seed - seed @ tangent[0] * tangent[0]
    normal[0] /= np.linalg.norm(normal[0])
    for i in range(1, segments + 1):
        k = i % segments
        prev = normal[i - 1]
        n = prev - prev @ tangent[k] * tangent[k]
        n /= np.linalg.norm(n)
        if k == 0:
            closing = n
        else:
            normal[k] = n
    twist = math.atan2(np.cross(closing, normal[0]) @ tangent[0], closing @ normal[0])
    binormal = np.cross(tangent, normal)
    angle = twist * t
    normal, binormal = (
        np.cos(angle)[:, None] * normal + np.sin(angle)[:, None] * binormal,
        -np.sin(angle)[:, None] * normal + np.cos(angle)[:, None] * binormal,
    )
    phi = 2 * np.pi * np.arange(sides) / sides
    radial = np.cos(phi)[None, :, None] * normal[:, None] + np.sin(phi)[None, :, None] * binormal[:, None]
    vertices = (centre[:, None] + radius * radial).reshape(-1, 3)
    normals = radial.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    i1, j1 = (i + 1) % segments, (j + 1) % sides
    a, b, c, d = i * sides + j, i1 * sides + j, i1 * sides + j1, i * sides + j1
    quads = [np.stack([a.ravel(), b.ravel(), c.ravel()], 1), np.stack([a.ravel(), c.ravel(), d.ravel()], 1)]
    triangles = np.concatenate(quads).astype(np.int64)
    return vertices, _orient_outward(vertices, triangles, normals), normals


def _rotation_x(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _transform(mesh: Mesh, rotation: np.ndarray, translation=(0.0, 0.0, 0.0)) -> Mesh:
    vertices, triangles, normals = mesh
    return vertices @ rotation.T + np.asarray(translation), triangles, normals @ rotation.T


def _merge(parts: list[tuple[Mesh, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate meshes; each part comes with its per-triangle material ids."""
    vertices, triangles, normals, materials, offset = [], [], [], [], 0
    for (v, f, n), mat in parts:
        vertices.append(v)
        triangles.append(f + offset)
        normals.append(n)
        materials.append(np.broadcast_to(np.asarray(mat, dtype=np.int64), (f.shape[0],)))
        offset += v.shape[0]
    return (np.concatenate(vertices), np.concatenate(triangles), np.concatenate(normals), np.concatenate(materials))


def evaluate_albedo(points: np.ndarray, material: Material) -> np.ndarray:
    """(N, 3) albedo of ``material`` at world points (N, 3)."""
    pattern = np.clip(pattern_at(points, material.texture), -1.0, 1.0)
    factor = 1.0 + material.texture.amplitude * pattern
    return np.asarray(material.albedo)[None, :] * factor[:, None]


#: What ``with_floor_texture`` (``polargs generate --floor-texture``) puts on a scene's floor:
#: ``uniform`` (textureless), ``checker`` (glossy_plane_sphere's own: 0.3-unit cells, 15 %
#: contrast) or ``speckle`` (a granite-like mat: 0.08-unit blobs and two finer octaves at 60 %
#: contrast, enough corners for SfM to register views that see the floor).
FLOOR_TEXTURES: dict[str, Texture] = {
    "uniform": Texture(),
    "checker": Texture("checker", 0.3, 0.15),
    "speckle": Texture("speckle", 0.08, 0.6),
}


def with_floor_texture(spec: SceneSpec, kind: str) -> SceneSpec:
    """``spec`` with :data:`FLOOR_TEXTURES` ``[kind]`` on its floor: every material that only
    supporting triangles (``object_triangles`` False) use.

    Raises:
        ValueError: an unknown ``kind``, or a scene without a floor.
    """
    if kind not in FLOOR_TEXTURES:
        raise ValueError(f"floor texture must be one of {', '.join(FLOOR_TEXTURES)}, got {kind!r}")
    support = np.zeros(len(spec.triangle_material), bool) if spec.object_triangles is None else ~spec.object_triangles
    floor = set(np.unique(spec.triangle_material[support]).tolist()) - set(
        np.unique(spec.triangle_material[~support]).tolist())
    if not floor:
        raise ValueError(f"scene {spec.name} has no floor to texture")
    materials = tuple(replace(m, texture=FLOOR_TEXTURES[kind]) if i in floor else m for i, m in enumerate(spec.materials))
    return replace(spec, materials=materials, description=f"{spec.description}; {kind} floor")


# ---------------------------------------------------------------------------------------------
# Cameras (OpenCV frame, world_to_camera 4x4).


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(3, 3) float64 pinhole K, square pixels, principal point at the image centre (+0.5 convention)."""
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


#: Camera layouts of :attr:`SceneSpec.camera_layout`.
CAMERA_LAYOUTS = ("rings", "spiral")


def orbit_cameras(
    num_views: int, target, distance: float, elevations_deg: tuple[float, float], rings: int = 3,
    azimuth_deg: float = 0.0,
) -> list[np.ndarray]:
    """World_to_camera matrices on ``rings`` elevation rings around ``target``.

    View i sits on ring i % rings (elevations evenly spread over ``elevations_deg``) at azimuth
    2 pi i / num_views (+ a per-ring offset, + ``azimuth_deg``), so any prefix of views covers
    the whole circle.

    Returns:
        ``num_views`` (4, 4) float64 arrays.
    """
    rings = max(1, min(rings, num_views))
    elevations = np.radians(np.linspace(*elevations_deg, rings)) if rings > 1 else np.radians([np.mean(elevations_deg)])
    target = np.asarray(target, float)
    out = []
    for i in range(num_views):
        elev = elevations[i % rings]
        azim = 2 * np.pi * i / num_views + 0.5 * np.pi * (i % rings) / rings
        if azimuth_deg:
            azim += math.radians(azimuth_deg)
        out.append(look_at(_orbit_eye(target, distance, elev, azim), target))
    return out


def spiral_cameras(
    num_views: int, target, distance: float, elevations_deg: tuple[float, float], azimuth_deg: float = 0.0
) -> list[np.ndarray]:
    """World_to_camera matrices spread evenly over the band of elevations ``elevations_deg``.

    A golden-angle spiral: view i sits at the sine of its elevation (i + 1/2) / num_views of the way
    through the band (equal areas of the band per view) and at azimuth i x 137.5 deg (+
    ``azimuth_deg``), so the views cover the band without rings or gaps.

    Returns:
        ``num_views`` (4, 4) float64 arrays.
    """
    low, high = (math.sin(math.radians(e)) for e in elevations_deg)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    target = np.asarray(target, float)
    out = []
    for i in range(num_views):
        elev = math.asin(low + (i + 0.5) / num_views * (high - low))
        azim = i * golden + math.radians(azimuth_deg)
        out.append(look_at(_orbit_eye(target, distance, elev, azim), target))
    return out


def _orbit_eye(target: np.ndarray, distance: float, elevation: float, azimuth: float) -> np.ndarray:
    """Camera centre at ``distance`` from ``target`` seen at ``elevation`` / ``azimuth`` (radians)."""
    return target + distance * np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])


def scene_cameras(spec: "SceneSpec", num_views: int) -> list[np.ndarray]:
    """The ``num_views`` world_to_camera matrices of ``spec`` (its :attr:`~SceneSpec.camera_layout`)."""
    if spec.camera_layout == "rings":
        return orbit_cameras(num_views, spec.target, spec.camera_distance, spec.elevations_deg,
                             azimuth_deg=spec.camera_azimuth_deg)
    if spec.camera_layout == "spiral":
        return spiral_cameras(num_views, spec.target, spec.camera_distance, spec.elevations_deg, spec.camera_azimuth_deg)
    raise ValueError(f"unknown camera layout {spec.camera_layout!r} (known: {', '.join(CAMERA_LAYOUTS)})")


# ---------------------------------------------------------------------------------------------
# The scenes.


def _glossy_plane_sphere() -> SceneSpec:
    sphere = icosphere(0.5, center=(0.0, 0.0, 0.5), subdivisions=5)
    ground = plane(3.0, height=0.0, segments=8)
    vertices, triangles, normals, mats = _merge([(sphere, 0), (ground, 1)])
    return SceneSpec(
        name="glossy_plane_sphere",
        description="glossy textureless red sphere (r=0.5) resting on a weakly textured matte plane",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=mats,
        materials=(
            Material("glossy_red", albedo=(0.55, 0.12, 0.10), specular=0.9, shininess=80.0),
            Material("matte_floor", albedo=(0.42, 0.40, 0.36), texture=FLOOR_TEXTURES["checker"], specular=0.03, shininess=8.0),
        ),
        lights=(
            Light("directional", _unit((0.5, -0.4, 0.75)), (0.75, 0.75, 0.72)),
            Light("directional", _unit((-0.6, 0.5, 0.6)), (0.30, 0.32, 0.36)),
        ),
        ambient=0.12,
        target=(0.0, 0.0, 0.35),
        camera_distance=3.0,
        fov_deg=40.0,
        elevations_deg=(20.0, 50.0),
        object_triangles=mats == 0,  # the sphere; the floor plane is support, not evaluated
    )


def _shiny_torus() -> SceneSpec:
    ring = tube(lambda t: np.stack([0.62 * np.cos(2 * np.pi * t), 0.62 * np.sin(2 * np.pi * t), 0 * t], 1), 0.24, 192, 64)
    torus = _transform(ring, _rotation_x(35.0))
    vertices, triangles, normals, mats = _merge([(torus, 0)])
    return SceneSpec(
        name="shiny_torus",
        description="tilted shiny torus (R=0.62, r=0.24) with a weak procedural texture under three lights",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=mats,
        materials=(
            Material("shiny_teal", albedo=(0.12, 0.38, 0.42), texture=Texture("noise", 0.35, 0.12), specular=1.2, shininess=150.0),
        ),
        lights=(
            Light("directional", _unit((0.3, -0.5, 0.8)), (0.7, 0.7, 0.7)),
            Light("directional", _unit((-0.7, -0.2, 0.3)), (0.35, 0.33, 0.30)),
            Light("point", (0.2, 1.6, 0.9), (1.2, 1.2, 1.25)),
        ),
        ambient=0.10,
        target=(0.0, 0.0, 0.0),
        camera_distance=3.0,
        fov_deg=40.0,
        elevations_deg=(-25.0, 55.0),
    )


def _bumpy_sphere() -> Mesh:
    vertices, triangles, unit = icosphere(1.0, subdivisions=5)
    bumps = 0.07 * np.sin(7.0 * unit[:, 0] + 1.0) * np.sin(6.0 * unit[:, 1] + 0.5) * np.sin(5.0 * unit[:, 2] + 2.0)
    bumps += 0.04 * np.sin(11.0 * unit[:, 2] + 3.0 * unit[:, 0])
    vertices = 0.62 * (1.0 + bumps)[:, None] * unit
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_vertex_normals()
    return vertices, triangles, np.asarray(mesh.vertex_normals, dtype=np.float64)


def _bumpy_mixed() -> SceneSpec:
    bumpy = _bumpy_sphere()
    vertices, triangles, normals = bumpy
    centroid = vertices[triangles].mean(axis=1)
    ceramic = np.sin(4.0 * centroid[:, 2] + 2.5 * centroid[:, 0]) > -0.2
    mats = np.where(ceramic, 0, 1)
    vertices, triangles, normals, mats = _merge([(bumpy, mats)])
    return SceneSpec(
        name="bumpy_mixed",
        description="bumpy displaced icosphere of glossy ceramic and textured matte clay; strong light overexposes highlights",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=mats,
        materials=(
            Material("glossy_ceramic", albedo=(0.70, 0.66, 0.58), specular=2.5, shininess=60.0),
            Material("matte_clay", albedo=(0.55, 0.30, 0.18), texture=Texture("noise", 0.25, 0.3), specular=0.05, shininess=6.0),
        ),
        lights=(
            Light("directional", _unit((0.4, -0.6, 0.7)), (1.0, 0.97, 0.92)),
            Light("directional", _unit((-0.5, 0.6, 0.2)), (0.35, 0.38, 0.45)),
        ),
        ambient=0.12,
        target=(0.0, 0.0, 0.0),
        camera_distance=3.0,
        fov_deg=40.0,
        elevations_deg=(-20.0, 50.0),
    )


def _torus_knot() -> SceneSpec:
    def knot(t: np.ndarray) -> np.ndarray:
        p, q, s = 2, 3, 2 * np.pi * t
        r = 0.5 + 0.22 * np.cos(q * s)
        return np.stack([r * np.cos(p * s), r * np.sin(p * s), 0.22 * np.sin(q * s)], 1)

    vertices, triangles, normals, mats = _merge([(tube(knot, 0.12, 384, 32), 0)])
    return SceneSpec(
        name="torus_knot",
        description="glossy (2,3) torus knot with thin parts and self-occlusions, weak texture",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=mats,
        materials=(
            Material("glossy_gold", albedo=(0.60, 0.45, 0.15), texture=Texture("noise", 0.3, 0.1), specular=1.0, shininess=100.0),
        ),
        lights=(
            Light("directional", _unit((0.3, -0.4, 0.85)), (0.8, 0.8, 0.78)),
            Light("directional", _unit((-0.6, 0.6, -0.2)), (0.3, 0.3, 0.35)),
        ),
        ambient=0.12,
        target=(0.0, 0.0, 0.0),
        camera_distance=2.6,
        fov_deg=40.0,
        elevations_deg=(-30.0, 60.0),
    )


def _rippled_body() -> Mesh:
    """A glazed pot's body: a squat ellipsoid with gentle vertical ripples, resting on z = 0."""
    _, triangles, unit = icosphere(1.0, subdivisions=5)
    azimuth = np.arctan2(unit[:, 1], unit[:, 0])
    ripple = 1.0 + 0.035 * np.cos(8.0 * azimuth) * (1.0 - unit[:, 2] ** 2)
    vertices = unit * np.array([0.58, 0.58, 0.48]) * ripple[:, None] + np.array([0.0, 0.0, 0.48])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_vertex_normals()
    return vertices, triangles, np.asarray(mesh.vertex_normals, dtype=np.float64)


def _glazed_pot() -> SceneSpec:
    knob = icosphere(0.1, center=(0.0, 0.0, 1.04), subdivisions=3)
    ground = plane(3.0, height=0.0, segments=8)
    vertices, triangles, normals, mats = _merge([(_rippled_body(), 0), (knob, 1), (ground, 2)])
    return SceneSpec(
        name="glazed_pot",
        description="glazed light-coloured rippled pot with an aluminium knob on a textured floor, mirroring "
        "a sky, a coloured horizon and two softboxes (environment lighting; its brightest reflections clip)",
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=mats,
        materials=(
            Material("cream_glaze", albedo=(0.72, 0.66, 0.55), texture=Texture("noise", 0.3, 0.08), specular=1.0,
                     shininess=2000.0),
            Material("aluminium", albedo=(0.09, 0.09, 0.09), specular=1.0, shininess=400.0, refractive_index=0.96,
                     extinction=6.69, specular_tint=(0.91, 0.92, 0.92)),
            Material("matte_floor", albedo=(0.40, 0.38, 0.35), texture=FLOOR_TEXTURES["checker"], specular=0.03,
                     shininess=8.0),
        ),
        lights=(),
        ambient=0.0,
        target=(0.0, 0.0, 0.45),
        camera_distance=3.0,
        fov_deg=40.0,
        elevations_deg=(15.0, 55.0),
        object_triangles=mats < 2,  # the pot and its knob; the floor is support, not evaluated
        environment=Environment(
            zenith=(0.26, 0.33, 0.46), horizon=(0.50, 0.38, 0.25), ground=(0.12, 0.10, 0.08),
            texture_amplitude=0.4, texture_scale=0.3,
            softboxes=(Softbox(_unit((0.6, -0.5, 0.62)), 18.0, (6.0, 6.0, 5.7)),
                       Softbox(_unit((-0.75, 0.45, 0.3)), 11.0, (5.0, 5.3, 5.8))),
        ),
    )


def _unit(v) -> tuple[float, float, float]:
    v = np.asarray(v, dtype=np.float64)
    return tuple(float(x) for x in v / np.linalg.norm(v))


SCENE_BUILDERS: dict[str, Callable[[], SceneSpec]] = {
    "glossy_plane_sphere": _glossy_plane_sphere,
    "shiny_torus": _shiny_torus,
    "bumpy_mixed": _bumpy_mixed,
    "torus_knot": _torus_knot,
    "glazed_pot": _glazed_pot,
}


def build_scene(name: str) -> SceneSpec:
    """The :class:`SceneSpec` of a named scene (see :data:`SCENE_BUILDERS`)."""
    if name not in SCENE_BUILDERS:
        raise ValueError(f"unknown synthetic scene {name!r}; choose one of {', '.join(SCENE_BUILDERS)}")
    return SCENE_BUILDERS[name]()


def same_arguments_as(generate_views: Callable) -> Callable[[Callable], Callable]:
    """Decorator of a whole-scene generator that forwards every argument to its view-at-a-time
    twin ``generate_views`` (:func:`~polargs_plugin.data.synthetic.generate_scene` of
    :func:`~polargs_plugin.data.synthetic.generate_scene_views`, the family's pair likewise): each
    argument is declared once, on ``generate_views``, and ``help()`` and ``inspect.signature`` show
    it on the decorated function too, with the decorated function's own return annotation."""

    def decorate(generate: Callable) -> Callable:
        returns = inspect.signature(generate).return_annotation
        generate.__signature__ = inspect.signature(generate_views).replace(return_annotation=returns)
        return generate

    return decorate
