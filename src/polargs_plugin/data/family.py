"""A procedural family of synthetic scenes: one scene per seed, none tuned to.

``family_scene(seed)`` draws, from its own random stream, everything a scene is made of:

- **a shape**: a main body, a superquadric (boxy to round to pinched) with, on some seeds, ripples,
  bumps or a dent (a concavity), and up to three attached parts that intersect it: a torus ring
  through it (a handle, sometimes thin), a rod sticking out of it, a thin plate (a fin) or a
  smaller blob. The union is one mesh: triangles inside another part are left out;
- **materials**: dielectrics of refractive index 1.3-1.8, albedo from uniform to strongly
  textured, specular strength and sharpness over wide ranges; some metals (a conductor's complex
  index, tinted highlights, no diffuse polarization; :mod:`polargs_plugin.optics.fresnel`);
- **lights and exposure**: a key light, sometimes a fill and a point light, ambient light, an
  exposure that clips the highlights on some seeds; sensor noise. From :data:`LIT_SEED_START` on,
  a seed draws its **lighting**: lights, surroundings the object mirrors (an
  :class:`~polargs_plugin.data.environment.Environment`: a sky, a coloured horizon, a textured
  ground, one to three softboxes bright enough to clip on some seeds), or both; under
  surroundings, the dielectrics are glossier (k_s 0.5-1, lobes from near-mirror to broad);
- **a camera layout**: the upper hemisphere, a full orbit, 12 sparse views, or low elevations
  only (surfaces facing up are then seen at grazing angles only); 24-36 views (12 for the sparse
  layout) of 128-160 px;
- sometimes **a floor** the object stands on (support: not in the masks, not in the evaluation's
  ground truth); from :data:`LIT_SEED_START` on, the ``stand`` layout raises the object on a thin
  rod above the floor and looks from -15 to 60 deg, so its underside is seen by a few low views.

The same seed gives the same scene on every machine (numpy's PCG64 stream of ``seed``). The seeds
come in two blocks: below :data:`LIT_SEED_START`, lights only (the first family); from it on,
drawn lighting and the stand layout. In each block the first 10000 seeds are for development and
the rest are test seeds, reported and never used to choose a rule or a default (docs/results.md,
"Protocol"): development 0-9999 and 20000-29999, test 10000-19999 and 30000 on
(:func:`is_test_seed`). The scene's name is
``family-<seed>`` (:func:`family_name`); ``polargs generate --scene family:K``, ``polargs demo
--scene family:K`` and ``polargs ablate --scenes family:K`` render it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import open3d as o3d

from polargs_plugin.data.environment import Environment, Softbox
from polargs_plugin.data.scenes import (
    Light,
    Material,
    Mesh,
    SceneSpec,
    Texture,
    plane,
    same_arguments_as,
    tube,
)

if TYPE_CHECKING:
    from polargs_plugin.data.synthetic import SyntheticScene

__all__ = [
    "FAMILY",
    "TEST_SEED_START",
    "LIT_SEED_START",
    "LIGHTINGS",
    "LAYOUTS",
    "FamilyScene",
    "FamilySettings",
    "family_scene",
    "family_settings",
    "generate_family_scene",
    "generate_family_scene_views",
    "family_name",
    "parse_family",
    "is_test_seed",
]

#: The family's name on the command line (``family:K``; ``polargs generate --scene family --seed K`` too).
FAMILY = "family"
#: Seeds from here on, in each block, are test seeds: reported only, never used to choose
#: (docs/results.md).
TEST_SEED_START = 10_000
#: The second block of seeds starts here: drawn lighting and the stand layout.
LIT_SEED_START = 20_000
#: Camera layouts a seed draws from, with their probabilities (first block).
LAYOUTS: dict[str, float] = {"hemisphere": 0.35, "orbit": 0.25, "sparse": 0.2, "low": 0.2}
#: Camera layouts of the second block: the first block's and ``stand``.
LIT_LAYOUTS: dict[str, float] = {"hemisphere": 0.3, "orbit": 0.15, "sparse": 0.15, "low": 0.15, "stand": 0.25}
#: Lightings a second-block seed draws from, with their probabilities (the first block: lights).
LIGHTINGS: dict[str, float] = {"lights": 0.2, "environment": 0.5, "both": 0.3}
# How high the stand raises the object's lowest point above the floor, and the rod's radius.
_STAND_HEIGHT = 0.35
_STAND_RADIUS = 0.035
_STAND_MATERIAL = Material("stand", (0.25, 0.25, 0.25), specular=0.05, shininess=8.0)
#: Views of the sparse layout.
SPARSE_VIEWS = 12
#: Image sizes a seed draws from (square images).
SIZES = (128, 144, 160)
#: (name, n, k, tint) of the metals a seed may draw: complex index at 550 nm (Johnson & Christy;
#: Rakic for aluminium) and the colour of their reflection.
METALS: tuple[tuple[str, float, float, tuple[float, float, float]], ...] = (
    ("gold", 0.43, 2.46, (1.00, 0.78, 0.34)),
    ("copper", 1.02, 2.58, (0.95, 0.64, 0.54)),
    ("aluminium", 0.96, 6.69, (0.91, 0.92, 0.92)),
    ("iron", 2.9, 3.0, (0.56, 0.57, 0.58)),
)
_NAME_RE = re.compile(rf"^{FAMILY}[:-](\d+)$")
# The object's bounding radius after scaling, and the mesh resolution of the parts.
_OBJECT_RADIUS = 0.88
_BODY_GRID = (160, 320)
_PART_GRID = (96, 192)


def family_name(seed: int) -> str:
    """The scene name of a seed: ``family-<seed>``."""
    return f"{FAMILY}-{int(seed)}"


def parse_family(text: str) -> int | None:
    """The seed of ``family:K`` or ``family-K``; None for any other name."""
    match = _NAME_RE.match(text.strip())
    return int(match.group(1)) if match else None


def is_test_seed(seed: int) -> bool:
    """Whether ``seed`` is a test seed (10000-19999 or from 30000 on): reported, never chosen on."""
    seed = int(seed)
    return seed >= LIT_SEED_START + TEST_SEED_START or TEST_SEED_START <= seed < LIT_SEED_START


def is_lit_seed(seed: int) -> bool:
    """Whether ``seed`` is of the second block (>= :data:`LIT_SEED_START`): drawn lighting, stand layout."""
    return int(seed) >= LIT_SEED_START


@dataclass
class FamilyScene:
    """What one seed drew: the scene and how to render it.

    Attributes:
        seed: the seed.
        spec: the scene (mesh, materials, lights, cameras).
        settings: its cameras, image size, noise and floor (:func:`family_settings`).
        parts: one description per part of the shape (kind and parameters).
        exposure: factor on every light (above about 1.3, highlights clip).
        lighting: one of :data:`LIGHTINGS` (``"lights"`` for every first-block seed).
    """

    seed: int
    spec: SceneSpec
    settings: "FamilySettings"
    parts: list[dict[str, Any]] = field(default_factory=list)
    exposure: float = 1.0
    lighting: str = "lights"

    def describe(self) -> dict[str, Any]:
        """JSON-ready record of the draw (for scene.json)."""
        s = self.settings
        return {"seed": self.seed, "test_seed": is_test_seed(self.seed), "layout": s.layout, "floor": s.floor,
                "num_views": s.num_views, "size": s.size, "noise_std": s.noise_std, "exposure": self.exposure,
                "lighting": self.lighting, "parts": self.parts}


# ---------------------------------------------------------------------------------------------
# Parts: a mesh and an inside test in the part's own frame, placed by a rotation and a centre.


@dataclass(frozen=True)
class _Displacement:
    """Radial displacement of a star-shaped part: the surface point along the unit direction u
    moves to (1 + d(u)) times its distance, d(u) = sum of ripples A sin(k . u + phase) and
    bumps h exp(-(1 - u . c) / w^2) (a negative h is a dent)."""

    ripples: tuple[tuple[float, tuple[float, float, float], float], ...] = ()
    bumps: tuple[tuple[float, tuple[float, float, float], float], ...] = ()

    def __call__(self, directions: np.ndarray) -> np.ndarray:
        out = np.zeros(len(directions))
        for amplitude, wave, phase in self.ripples:
            out += amplitude * np.sin(directions @ np.asarray(wave) + phase)
        for height, centre, width in self.bumps:
            out += height * np.exp(-(1.0 - directions @ np.asarray(centre)) / width**2)
        return out


def _spow(x: np.ndarray, exponent: float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** exponent


@dataclass(frozen=True)
class _Superquadric:
    """Superellipsoid |x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1) + |z/c|^(2/e1) = 1 with a radial
    displacement, rotated by ``rotation`` and moved to ``centre``."""

    axes: tuple[float, float, float]
    exponents: tuple[float, float]
    rotation: np.ndarray
    centre: np.ndarray
    displacement: _Displacement = _Displacement()
    grid: tuple[int, int] = _PART_GRID

    def _implicit(self, local: np.ndarray) -> np.ndarray:
        (a, b, c), (e1, e2) = self.axes, self.exponents
        xy = (np.abs(local[:, 0] / a) ** (2 / e2) + np.abs(local[:, 1] / b) ** (2 / e2)) ** (e2 / e1)
        return xy + np.abs(local[:, 2] / c) ** (2 / e1)

    def mesh(self) -> Mesh:
        (a, b, c), (e1, e2) = self.axes, self.exponents
        rows, cols = self.grid
        eta = np.linspace(-np.pi / 2, np.pi / 2, rows + 1)[1:-1]
        omega = np.linspace(-np.pi, np.pi, cols, endpoint=False)
        eta_g, omega_g = np.meshgrid(eta, omega, indexing="ij")
        ring = np.stack([a * _spow(np.cos(eta_g), e1) * _spow(np.cos(omega_g), e2),
                         b * _spow(np.cos(eta_g), e1) * _spow(np.sin(omega_g), e2),
                         c * _spow(np.sin(eta_g), e1)], -1).reshape(-1, 3)
        local = np.concatenate([[[0.0, 0.0, -c]], ring, [[0.0, 0.0, c]]])
        length = np.linalg.norm(local, axis=1, keepdims=True)
        local = local * (1.0 + self.displacement(local / length))[:, None]
        return _finish(local @ self.rotation.T + self.centre, _uv_sphere_triangles(rows - 1, cols), self.centre)

    def inside(self, points: np.ndarray) -> np.ndarray:
        local = (points - self.centre) @ self.rotation
        length = np.maximum(np.linalg.norm(local, axis=1), 1e-12)
        scale = 1.0 + self.displacement(local / length[:, None])
        # the implicit function is homogeneous of degree 2 / e1: inside the displaced surface iff
        # f(p)^(e1 / 2) < 1 + d(p / |p|)
        return self._implicit(local) ** (self.exponents[0] / 2) < scale


@dataclass(frozen=True)
class _Torus:
    """Torus of ring radius ``major`` and tube radius ``minor`` about its local z axis."""

    major: float
    minor: float
    rotation: np.ndarray
    centre: np.ndarray

    def mesh(self) -> Mesh:
        def circle(t: np.ndarray) -> np.ndarray:
            return np.stack([self.major * np.cos(2 * np.pi * t), self.major * np.sin(2 * np.pi * t), 0 * t], 1)

        vertices, triangles, normals = tube(circle, self.minor, 192, max(24, int(96 * self.minor / 0.1)))
        return vertices @ self.rotation.T + self.centre, triangles, normals @ self.rotation.T

    def inside(self, points: np.ndarray) -> np.ndarray:
        local = (points - self.centre) @ self.rotation
        ring = np.hypot(local[:, 0], local[:, 1]) - self.major
        return ring**2 + local[:, 2] ** 2 < self.minor**2


def _uv_sphere_triangles(rings: int, cols: int) -> np.ndarray:
    """Triangles of a latitude-longitude grid: vertex 0 the south pole, ``rings`` rings of ``cols``
    vertices from south to north, then the north pole (orientation left to :func:`_finish`)."""
    south, north = 0, 1 + rings * cols
    j = np.arange(cols)
    j1 = (j + 1) % cols
    faces = [np.stack([np.full(cols, south), 1 + j, 1 + j1], 1)]
    for i in range(rings - 1):
        a, b = 1 + i * cols + j, 1 + i * cols + j1
        c, d = a + cols, b + cols
        faces += [np.stack([a, b, d], 1), np.stack([a, d, c], 1)]
    top = 1 + (rings - 1) * cols
    faces.append(np.stack([top + j, top + j1, np.full(cols, north)], 1))
    return np.concatenate(faces).astype(np.int64)


def _finish(vertices: np.ndarray, triangles: np.ndarray, centre: np.ndarray) -> Mesh:
    """(vertices, triangles, smooth vertex normals) of a closed star-shaped part about ``centre``,
    each triangle turned to face away from it (outwards)."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3 - centre) < 0
    triangles = triangles.copy()
    triangles[inward] = triangles[inward][:, [0, 2, 1]]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_vertex_normals()
    return vertices, triangles, np.asarray(mesh.vertex_normals, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# Drawing a scene.


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _frame_along(direction: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A rotation whose third column is ``direction`` (unit), turned randomly about it."""
    z = direction / np.linalg.norm(direction)
    helper = np.eye(3)[np.argmin(np.abs(z))]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    angle = rng.uniform(0, 2 * np.pi)
    x, y = math.cos(angle) * x + math.sin(angle) * y, -math.sin(angle) * x + math.cos(angle) * y
    return np.stack([x, y, z], 1)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _displacement(rng: np.random.Generator, record: dict[str, Any]) -> _Displacement:
    """Ripples, bumps and a dent, each on some seeds."""
    ripples, bumps = [], []
    if rng.random() < 0.35:
        for _ in range(int(rng.integers(1, 4))):
            ripples.append((float(rng.uniform(0.01, 0.04)), tuple(_unit(rng) * rng.uniform(6.0, 16.0)),
                            float(rng.uniform(0, 2 * np.pi))))
    if rng.random() < 0.35:
        for _ in range(int(rng.integers(3, 9))):
            bumps.append((float(rng.uniform(0.03, 0.1)) * (1 if rng.random() < 0.7 else -1), tuple(_unit(rng)),
                          float(rng.uniform(0.12, 0.3))))
    if rng.random() < 0.3:
        bumps.append((-float(rng.uniform(0.25, 0.45)), tuple(_unit(rng)), float(rng.uniform(0.3, 0.5))))
        record["dent"] = True
    record.update(ripples=len(ripples), bumps=sum(1 for h, _, _ in bumps if abs(h) < 0.2))
    return _Displacement(tuple(ripples), tuple(bumps))


def _body(rng: np.random.Generator, upright: bool) -> tuple[_Superquadric, dict[str, Any]]:
    axes = tuple(float(v) for v in rng.uniform(0.35, 0.75, size=3))
    exponents = (float(rng.uniform(0.35, 1.6)), float(rng.uniform(0.35, 1.6)))
    record: dict[str, Any] = {"kind": "superquadric", "axes": axes, "exponents": exponents}
    displacement = _displacement(rng, record)
    rotation = _random_rotation(rng)
    if upright:  # turned about the vertical only: a boxy body stands on its flat base, its top faces up
        rotation = _frame_along(np.array([0.0, 0.0, 1.0]), rng)
    return _Superquadric(axes, exponents, rotation, np.zeros(3), displacement, _BODY_GRID), record


def _surface_point(body: _Superquadric, direction: np.ndarray) -> np.ndarray:
    """Where the ray from the body's centre along ``direction`` (world, unit) leaves it (bisection)."""
    low, high = 0.0, 3.0
    for _ in range(40):
        mid = (low + high) / 2
        low, high = (mid, high) if body.inside(body.centre[None] + mid * direction[None])[0] else (low, mid)
    return body.centre + low * direction


def _attachment(rng: np.random.Generator, body: _Superquadric) -> tuple[Any, dict[str, Any]]:
    """A part that intersects the body: a ring, a rod, a fin or a blob."""
    direction = _unit(rng)
    anchor = _surface_point(body, direction)
    kind = str(rng.choice(["ring", "rod", "fin", "blob"]))
    if kind == "ring":
        major, minor = float(rng.uniform(0.22, 0.4)), float(rng.uniform(0.03, 0.1))
        # the ring's axis across the direction, its centre outside: it goes through the body's surface
        frame = _frame_along(np.cross(direction, _unit(rng)), rng)
        part = _Torus(major, minor, frame, anchor + direction * major * rng.uniform(0.3, 0.7))
        return part, {"kind": "ring", "major": major, "minor": minor, "thin": minor < 0.05}
    if kind == "rod":
        radius, length = float(rng.uniform(0.025, 0.06)), float(rng.uniform(0.3, 0.55))
        part = _Superquadric((radius, radius, length), (float(rng.uniform(0.3, 0.8)), 1.0), _frame_along(direction, rng),
                             anchor + direction * length * 0.6)
        return part, {"kind": "rod", "radius": radius, "length": length}
    if kind == "fin":
        size, thickness = float(rng.uniform(0.25, 0.45)), float(rng.uniform(0.018, 0.035))
        frame = _frame_along(np.cross(direction, _unit(rng)), rng)  # the fin's normal across the direction
        part = _Superquadric((size, size * rng.uniform(0.5, 1.0), thickness), (0.4, 1.0), frame, anchor + direction * size * 0.55)
        return part, {"kind": "fin", "size": size, "thickness": thickness}
    radius = float(rng.uniform(0.15, 0.3))
    part = _Superquadric((radius, radius * rng.uniform(0.7, 1.0), radius * rng.uniform(0.7, 1.0)),
                         (float(rng.uniform(0.5, 1.2)), float(rng.uniform(0.5, 1.2))), _random_rotation(rng), anchor)
    return part, {"kind": "blob", "radius": radius}


def _union(parts: list[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, normals, part index per triangle) of the parts' union: a triangle whose
    three vertices lie inside another part is left out (it could never be seen)."""
    vertices, triangles, normals, owner, offset = [], [], [], [], 0
    for index, part in enumerate(parts):
        v, f, n = part.mesh()
        inside = np.zeros(len(v), dtype=bool)
        for other_index, other in enumerate(parts):
            if other_index != index:
                inside |= other.inside(v)
        keep = ~inside[f].all(axis=1)
        vertices.append(v)
        normals.append(n)
        triangles.append(f[keep] + offset)
        owner.append(np.full(int(keep.sum()), index))
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(normals), np.concatenate(owner)


def _dielectric(rng: np.random.Generator, name: str, mirrored: bool) -> Material:
    """A dielectric; ``mirrored`` (surroundings light the scene): a glossy one whose reflection
    k_s F(theta) runs from near-mirror to broad (under point lights, a Blinn-Phong highlight)."""
    hue, saturation, value = rng.uniform(0, 1), rng.uniform(0.0, 0.8), rng.uniform(0.2, 0.8)
    albedo = tuple(float(c) for c in _hsv_to_rgb(hue, saturation, value))
    texture_kind = str(rng.choice(["uniform", "noise", "checker"], p=[0.35, 0.4, 0.25]))
    texture = Texture() if texture_kind == "uniform" else Texture(
        texture_kind, float(rng.uniform(0.1, 0.4)), float(rng.uniform(0.1, 0.6)))
    specular, shininess = ((float(rng.uniform(0.5, 1.0)), _log_uniform(rng, 30.0, 20000.0)) if mirrored
                           else (_log_uniform(rng, 0.02, 2.5), _log_uniform(rng, 5.0, 300.0)))
    return Material(name, albedo, texture, specular=specular, shininess=shininess,
                    refractive_index=float(rng.uniform(1.3, 1.8)))


def _metal(rng: np.random.Generator, name: str, mirrored: bool) -> Material:
    metal, n, k, tint = METALS[int(rng.integers(len(METALS)))]
    diffuse = rng.uniform(0.1, 0.25)  # rough-surface scattering; the highlight is the metal's reflection
    specular = float(rng.uniform(0.7, 1.0)) if mirrored else float(rng.uniform(0.5, 2.0))
    shininess = _log_uniform(rng, 50.0, 5000.0) if mirrored else _log_uniform(rng, 10.0, 150.0)
    return Material(f"{name}_{metal}", tuple(float(diffuse * c) for c in tint), Texture(), specular=specular,
                    shininess=shininess, refractive_index=n, extinction=k, specular_tint=tint)


def _hsv_to_rgb(hue: float, saturation: float, value: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    return value - value * saturation * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _lights(rng: np.random.Generator, exposure: float) -> tuple[Light, ...]:
    def direction(elevation_deg: tuple[float, float]) -> tuple[float, float, float]:
        elevation, azimuth = math.radians(rng.uniform(*elevation_deg)), rng.uniform(0, 2 * np.pi)
        return (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))

    def colour(level: float) -> tuple[float, float, float]:
        return tuple(float(exposure * level * c) for c in rng.uniform(0.9, 1.0, size=3))

    lights = [Light("directional", direction((25.0, 75.0)), colour(rng.uniform(0.6, 1.0)))]
    if rng.random() < 0.7:
        lights.append(Light("directional", direction((-10.0, 50.0)), colour(rng.uniform(0.15, 0.4))))
    if rng.random() < 0.4:
        position = np.asarray(direction((10.0, 60.0))) * rng.uniform(1.5, 2.2)
        lights.append(Light("point", tuple(float(v) for v in position), colour(rng.uniform(0.6, 1.4))))
    return tuple(lights)


@dataclass(frozen=True)
class FamilySettings:
    """How a seed is seen: drawn from its own stream, without building the shape (cheap).

    Attributes:
        seed: the seed.
        layout: the camera layout, one of :data:`LAYOUTS` (:data:`LIT_LAYOUTS` from
            :data:`LIT_SEED_START` on; ``stand``: the object raised on a thin rod above a floor).
        floor: whether the object stands on a floor (never with the full orbit, which looks from
            below; always with the stand).
        elevations_deg: the band of camera elevations (degrees).
        num_views: views (24-36; 12 for the sparse layout).
        size: image width = height (pixels).
        noise_std: sensor noise std per angle image.
        camera_distance: cameras' distance from the object's centre.
        azimuth_deg: azimuth of the first camera.
    """

    seed: int
    layout: str
    floor: bool
    elevations_deg: tuple[float, float]
    num_views: int
    size: int
    noise_std: float
    camera_distance: float
    azimuth_deg: float


def family_settings(seed: int) -> FamilySettings:
    """The cameras, image size, noise and floor of ``seed`` (its settings stream only)."""
    rng = _streams(seed)["settings"]
    layouts = LIT_LAYOUTS if is_lit_seed(seed) else LAYOUTS
    layout = str(rng.choice(list(layouts), p=list(layouts.values())))
    floor = (bool(rng.random() < 0.4) and layout != "orbit") or layout == "stand"
    band = {"hemisphere": (8.0, 75.0), "orbit": (-60.0, 70.0), "sparse": (5.0 if floor else -30.0, 65.0),
            "low": (1.0 if floor else -8.0, 15.0), "stand": (-15.0, 60.0)}[layout]
    views = SPARSE_VIEWS if layout == "sparse" else int(rng.integers(24, 37))
    return FamilySettings(int(seed), layout, floor, band, views, int(rng.choice(SIZES)),
                          _log_uniform(rng, 0.002, 0.012), float(rng.uniform(2.8, 3.3)), float(rng.uniform(0.0, 360.0)))


def _streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent random streams of a seed, one per aspect, so that each is drawn the same way
    whatever the others draw."""
    if int(seed) < 0:
        raise ValueError(f"family seeds are >= 0, got {seed}")
    names = ("settings", "shape", "materials", "lights")
    return {name: np.random.default_rng(child) for name, child in zip(names, np.random.SeedSequence(int(seed)).spawn(len(names)))}


def _shape(rng: np.random.Generator, upright: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """(vertices, triangles, normals, part index per triangle, part records) of the object,
    centred and scaled to the bounding radius; ``upright``: the body's axes along the world's
    (an object standing on a floor rests on its base)."""
    body, body_record = _body(rng, upright)
    parts, records = [body], [body_record]
    for _ in range(int(rng.choice([0, 1, 2, 3], p=[0.25, 0.35, 0.25, 0.15]))):
        part, record = _attachment(rng, body)
        parts.append(part)
        records.append(record)
    vertices, triangles, normals, owner = _union(parts)
    used = np.unique(triangles)
    centre = (vertices[used].max(0) + vertices[used].min(0)) / 2
    scale = _OBJECT_RADIUS / np.linalg.norm(vertices[used] - centre, axis=1).max()
    return (vertices - centre) * scale, triangles, normals, owner, [_plain(r) for r in records]


def _materials(rng: np.random.Generator, vertices: np.ndarray, triangles: np.ndarray, owner: np.ndarray,
               num_parts: int, mirrored: bool = False) -> tuple[list[Material], np.ndarray]:
    """The object's materials and each triangle's: the body's, each attached part's (the body's
    or its own), and on some seeds a second material over part of the body; ``mirrored``: the
    glossy materials of a scene lit by surroundings."""
    materials = [_metal(rng, "metal", mirrored) if rng.random() < 0.2 else _dielectric(rng, "body", mirrored)]
    part_material = [0]
    for index in range(1, num_parts):
        if rng.random() < 0.5:
            part_material.append(0)
        else:
            materials.append(_metal(rng, f"part{index}", mirrored) if rng.random() < 0.2
                             else _dielectric(rng, f"part{index}", mirrored))
            part_material.append(len(materials) - 1)
    triangle_material = np.asarray(part_material)[owner]
    if rng.random() < 0.3:  # the body in two materials, split by a smooth pattern over its surface
        materials.append(_dielectric(rng, "body_second", mirrored))
        centroid = vertices[triangles].mean(axis=1)
        wave = _unit(rng) * rng.uniform(3.0, 6.0)
        second = (owner == 0) & (np.sin(centroid @ wave + rng.uniform(0, 2 * np.pi)) > rng.uniform(-0.3, 0.3))
        triangle_material = np.where(second, len(materials) - 1, triangle_material)
    return materials, triangle_material


def _environment(rng: np.random.Generator, exposure: float) -> Environment:
    """Surroundings of a second-block seed: a sky from a coloured horizon to a bluish zenith, a
    dim ground, a texture over directions and one to three softboxes, all times ``exposure``."""

    def colour(hue: tuple[float, float], saturation: tuple[float, float], value: tuple[float, float]) -> tuple:
        return tuple(float(exposure * c) for c in _hsv_to_rgb(rng.uniform(*hue), rng.uniform(*saturation), rng.uniform(*value)))

    zenith, horizon, ground = colour((0.5, 0.7), (0.2, 0.6), (0.12, 0.3)), colour((0, 1), (0.2, 0.7), (0.15, 0.4)), \
        colour((0, 1), (0.1, 0.5), (0.03, 0.15))
    amplitude, scale = float(rng.uniform(0.15, 0.5)), float(rng.uniform(0.2, 0.5))
    boxes = []
    for _ in range(int(rng.choice([1, 2, 3], p=[0.35, 0.4, 0.25]))):
        elevation, azimuth = math.radians(rng.uniform(10.0, 70.0)), rng.uniform(0, 2 * np.pi)
        direction = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))
        radius = float(rng.uniform(4.0, 20.0))
        # Each box adds ``share`` (times the albedo) to the colour of a surface facing it: a small
        # box is bright (its reflection clips), a large one dim, as a lamp and a window are.
        share = exposure * float(rng.uniform(0.08, 0.3))
        level = share * math.pi / (2 * math.pi * (1 - math.cos(math.radians(radius))))
        boxes.append(Softbox(direction, radius, tuple(float(level * c) for c in rng.uniform(0.9, 1.0, 3))))
    return Environment(zenith, horizon, ground, amplitude, scale, tuple(boxes))


def _rod(bottom: np.ndarray, top_z: float, radius: float, sides: int = 24, rings: int = 8) -> Mesh:
    """An open vertical cylinder of ``radius`` from the point ``bottom`` (3,) up to height ``top_z``."""
    phi = 2 * np.pi * np.arange(sides) / sides
    z = np.linspace(bottom[2], top_z, rings + 1)
    radial = np.stack([np.cos(phi), np.sin(phi), np.zeros(sides)], axis=1)
    vertices = np.concatenate([np.column_stack([bottom[0] + radius * radial[:, 0], bottom[1] + radius * radial[:, 1],
                                                np.full(sides, height)]) for height in z])
    normals = np.tile(radial, (rings + 1, 1))
    i, j = np.meshgrid(np.arange(rings), np.arange(sides), indexing="ij")
    a, b = i * sides + j, i * sides + (j + 1) % sides
    c, d = a + sides, b + sides
    triangles = np.concatenate([np.stack([a.ravel(), b.ravel(), d.ravel()], 1), np.stack([a.ravel(), d.ravel(), c.ravel()], 1)])
    return vertices, triangles.astype(np.int64), normals


def _floor_material(rng: np.random.Generator) -> Material:
    level = rng.uniform(0.3, 0.5) * rng.uniform(0.85, 1.0, 3)
    texture = Texture(str(rng.choice(["checker", "noise"])), float(rng.uniform(0.2, 0.4)), float(rng.uniform(0.1, 0.3)))
    return Material("floor", tuple(float(c) for c in level), texture, specular=float(rng.uniform(0.01, 0.1)), shininess=8.0)


def family_scene(seed: int) -> FamilyScene:
    """The scene of ``seed`` (module docstring); deterministic.

    Raises:
        ValueError: a negative seed.
    """
    settings = family_settings(seed)
    streams = _streams(seed)
    lighting_rng = streams["lights"]
    lighting = str(lighting_rng.choice(list(LIGHTINGS), p=list(LIGHTINGS.values()))) if is_lit_seed(seed) else "lights"
    vertices, triangles, normals, owner, records = _shape(streams["shape"], upright=settings.floor)
    materials, triangle_material = _materials(streams["materials"], vertices, triangles, owner, len(records),
                                              mirrored=lighting != "lights")
    num_object_materials = len(materials)
    object_triangles = None
    if settings.floor:
        lowest = vertices[np.unique(triangles)][np.argmin(vertices[np.unique(triangles), 2])]
        raised = _STAND_HEIGHT if settings.layout == "stand" else 0.0
        support = [plane(5.0, height=float(lowest[2]) - 1e-3 - raised, segments=10)]
        materials.append(_floor_material(streams["materials"]))
        support_material = [len(materials) - 1]
        if raised:  # a thin rod from the floor up into the object's lowest point
            support.append(_rod(lowest - np.array([0.0, 0.0, raised]), float(lowest[2]) + 0.05, _STAND_RADIUS))
            materials.append(_STAND_MATERIAL)
            support_material.append(len(materials) - 1)
        object_triangles = np.concatenate([np.ones(len(triangles), dtype=bool)]
                                          + [np.zeros(len(mesh[1]), dtype=bool) for mesh in support])
        for mesh, material in zip(support, support_material):
            triangles = np.concatenate([triangles, mesh[1] + len(vertices)])
            vertices = np.concatenate([vertices, mesh[0]])
            normals = np.concatenate([normals, mesh[2]])
            triangle_material = np.concatenate([triangle_material, np.full(len(mesh[1]), material)])
    exposure = _log_uniform(lighting_rng, 0.7, 2.0)
    lights = _lights(lighting_rng, exposure) if lighting != "environment" else ()
    # Under lights and surroundings together, the surroundings at half the exposure keep the sum in range.
    environment = _environment(lighting_rng, exposure * (0.5 if lighting == "both" else 1.0)) if lighting != "lights" else None
    ambient = float(lighting_rng.uniform(0.05, 0.18)) if lighting != "environment" else 0.0
    spec = SceneSpec(
        name=family_name(seed),
        description=f"family scene {seed}: " + " + ".join(r["kind"] for r in records)
        + f", {num_object_materials} material(s){' on a floor' if settings.floor else ''}, {settings.layout} cameras"
        + ("" if lighting == "lights" else f", lit by {'surroundings' if lighting == 'environment' else 'lights and surroundings'}"),
        vertices=vertices,
        triangles=triangles,
        vertex_normals=normals,
        triangle_material=triangle_material.astype(np.int64),
        materials=tuple(materials),
        lights=lights,
        ambient=ambient,
        target=(0.0, 0.0, 0.0),
        camera_distance=settings.camera_distance,
        fov_deg=40.0,
        elevations_deg=settings.elevations_deg,
        background=float(lighting_rng.uniform(0.02, 0.08)),
        object_triangles=object_triangles,
        camera_layout="spiral",
        camera_azimuth_deg=settings.azimuth_deg,
        environment=environment,
    )
    return FamilyScene(seed=int(seed), spec=spec, settings=settings, parts=records, exposure=exposure, lighting=lighting)


def _plain(record: dict[str, Any]) -> dict[str, Any]:
    """A part record with plain floats and lists (for JSON)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in record.items()}


def generate_family_scene_views(
    seed: int,
    num_views: int | None = None,
    size: tuple[int, int] | None = None,
    noise_std: float | None = None,
    **options: Any,
) -> Iterator[SyntheticScene]:
    """Render the scene of ``seed`` with its own views, size and noise (or the ones given), one
    view at a time (as :func:`~polargs_plugin.data.synthetic.generate_scene_views`).

    Args:
        seed: the family seed; it is also the sensor-noise seed.
        num_views: None: the layout's (24-36, 12 for the sparse layout).
        size: (width, height); None: the seed's square size (128-160 px).
        noise_std: None: the seed's.
        **options: any other argument of
            :func:`~polargs_plugin.data.synthetic.generate_scene_views` (``quantize_bits``,
            ``mask``, ``progress``, ``floor_texture``, ...), with its default there.

    Yields:
        one :class:`~polargs_plugin.data.synthetic.SyntheticScene` per view, its meta with a
        ``family`` entry (:meth:`FamilyScene.describe`).
    """
    from polargs_plugin.data.synthetic import generate_scene_views

    drawn = family_scene(seed)
    settings = drawn.settings
    width, height = size if size is not None else (settings.size, settings.size)
    described = drawn.describe()
    for part in generate_scene_views(drawn.spec, num_views=num_views or settings.num_views, width=width, height=height,
                                     seed=int(seed), noise_std=settings.noise_std if noise_std is None else noise_std,
                                     **options):
        part.meta["family"] = described
        yield part


@same_arguments_as(generate_family_scene_views)
def generate_family_scene(*args: Any, **kwargs: Any) -> SyntheticScene:
    """The family scene of ``seed``, all its views at once: the parts
    :func:`generate_family_scene_views` yields (arguments exactly as there), assembled."""
    from polargs_plugin.data.synthetic import assemble_scene

    return assemble_scene(generate_family_scene_views(*args, **kwargs))
