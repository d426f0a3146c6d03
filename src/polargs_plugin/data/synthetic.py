"""Synthetic multi-view polarimetric scenes with exact ground truth (the project's default dataset).

Pipeline per view (docs/dataset-format.md describes the model and the files):

1. Ray casting (open3d ``RaycastingScene``) through pixel centres K^-1 (u + 0.5, v + 0.5, 1): hit
   mask, camera-z depth, interpolated shading normal (camera frame, facing the camera). The views'
   masks mark the pixels whose first hit is the object (``SceneSpec.object_triangles``; a floor
   is background) unless ``generate_scene(mask="surface")``.
2. Shading in training-colour units (the colour a trainer sees, s0 / 2): Lambertian diffuse
   c_d = albedo * (ambient + sum_l E_l max(n.l, 0) vis_l) and a Blinn-Phong highlight
   c_s = k_s tint sum_l E_l max(n.h, 0)^shininess [n.l > 0] vis_l (tint white for a dielectric,
   the metal's colour for a conductor), with lights fixed in the world. A scene with an
   environment (:class:`~polargs_plugin.data.environment.Environment`, surroundings fixed in the
   world) adds its irradiance over pi to the diffuse factor (sky and ground by a fixed sphere
   quadrature, softboxes as area lights, both shadowed) and its reflection to the specular
   colour: k_s F(theta) tint L_lobe, F the material's Fresnel reflectance (R_s + R_p) / 2
   (a conductor's by its complex index) and L_lobe the environment seen through the lobe
   cos^shininess around the mirror direction (where the scene blocks a direction, the blocking
   surface's albedo times the environment's mean radiance).
3. Polarization (Fresnel, unpolarized light, n = the material's ``refractive_index`` or else
   ``refractive_index``), per pixel
   s = 2 c_d [1, rho_d cos 2a, rho_d sin 2a] + 2 c_s [1, -rho_s cos 2a, -rho_s sin 2a],
   rho_d = dolp_diffuse(theta), rho_s = dolp_specular(theta) (a conductor: rho_d = 0 and rho_s
   = dolp_specular_conductor(theta, n, k)), theta the angle between the normal
   and the direction to the camera, a the perspective-phase-angle (PPA) azimuth of the normal:
   diffuse AoLP = a, specular AoLP = a + pi/2 (docs/conventions.md).
4. Sensor: four angle images I(beta) = (s0 + s1 cos 2beta + s2 sin 2beta) / 2, Gaussian noise,
   clipping to [0, 1] (an overexposed pixel clips in every angle and loses its polarization),
   quantisation to ``quantize_bits``; ``View.stokes`` is recomputed from these images.

The background (no hit) is the environment where the scene has one, else a dim unpolarized
backdrop weakly textured by the world ray direction.
Besides the views, the scene records which view sees which of the object's triangles
(``SyntheticScene.visibility``, exact ray casting: :func:`polargs_plugin.data.visibility.triangle_visibility`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
import torch
from torch import Tensor
from tqdm import tqdm

from polargs_plugin.data.environment import lobe_directions, lobe_width, sphere_directions
from polargs_plugin.data.scenes import (
    SCENE_BUILDERS,
    Light,
    Material,
    SceneSpec,
    Texture,
    build_scene,
    evaluate_albedo,
    intrinsics,
    same_arguments_as,
    scene_cameras,
    with_floor_texture,
)
from polargs_plugin.data.visibility import triangle_visibility
from polargs_plugin.optics.azimuth import normal_azimuth, pixel_rays
from polargs_plugin.optics.fresnel import (
    dolp_diffuse,
    dolp_specular,
    dolp_specular_conductor,
    fresnel_reflectance,
    fresnel_reflectance_conductor,
)
from polargs_plugin.optics.stokes import intensities_from_stokes, stokes_from_intensities
from polargs_plugin.types import View

__all__ = [
    "SCENE_NAMES",
    "AZIMUTH_MODEL",
    "QUANTIZE_BITS",
    "MASK_KINDS",
    "GENERATOR_VERSION",
    "SMALL_SETTINGS",
    "SyntheticScene",
    "RenderedView",
    "SceneRenderer",
    "apply_sensor",
    "generate_scene",
    "generate_scene_views",
    "assemble_scene",
    "object_submesh",
]

SCENE_NAMES: tuple[str, ...] = tuple(SCENE_BUILDERS)
#: Azimuth model used to render AoLP: the perspective phase angle, the physical model of an
#: on-sensor (division-of-focal-plane) polarizer grid (Chen et al. ECCV 2022).
AZIMUTH_MODEL = "perspective"
#: What a view's mask marks (``generate_scene(mask=...)``): ``"object"``, the pixels where the
#: object to reconstruct is seen (the scene format's object mask, as real object datasets ship
#: it); ``"surface"``, every pixel that sees some surface, a floor it stands on included.
MASK_KINDS = ("object", "surface")
#: Bumped whenever the same settings would generate different files, so that caches keyed by
#: settings (``polargs ablate --scene-cache``) never hand out an older generator's scene.
#: 2: masks mark the object only by default (was: every surface).
#: 3: per-view visibility of the object's triangles (visibility.npz); per-material optics
#: (refractive index, conductors, specular tint) in scene.json. The images did not change.
#: 4: a checker texture on a surface lying on a cell boundary (glossy_plane_sphere's floor) keeps
#: one colour per cell instead of flickering with the hit points' rounding.
#: 5: environment lighting (scene.json's ``environment``); scenes without one render as before.
GENERATOR_VERSION = 5
#: Supported sensor bit depths (angle images are always quantised, as a real sensor's are).
QUANTIZE_BITS = (8, 16)
#: A scene size for tests and smoke runs: ``generate_scene(name, **SMALL_SETTINGS)``.
SMALL_SETTINGS = {"num_views": 8, "width": 48, "height": 48}
# Backdrop texture: relative amplitude and angular scale of its pattern over ray directions.
_BACKDROP_TEXTURE = Texture("noise", scale=0.6, amplitude=0.25)
# Offset of shadow-ray origins along the geometric normal, against self-intersection.
_SHADOW_EPS = 1e-4
# Directions per specular lobe of an environment reflection, and rays per ray-casting call.
_LOBE_SAMPLES = 16
_RAY_CHUNK = 1 << 21


@dataclass
class RenderedView:
    """Noise-free render of one view, before the sensor (all float64 tensors, (.., H, W)).

    Attributes:
        mask: (1, H, W) bool, ray hit the mesh.
        object_mask: (1, H, W) bool, ray hit the object first (``SceneSpec.object_triangles``).
        depth: (1, H, W) camera-z depth (0 outside the mask).
        normal: (3, H, W) unit camera-frame shading normals facing the camera (0 outside).
        diffuse: (3, H, W) diffuse colour c_d (background level outside the mask).
        specular: (3, H, W) specular colour c_s (0 outside the mask).
        dolp_diffuse: (1, H, W) Fresnel diffuse DoLP rho_d (0 outside).
        dolp_specular: (1, H, W) Fresnel specular DoLP rho_s (0 outside).
        azimuth: (1, H, W) PPA image-plane azimuth of the normal in [0, 2 pi) (0 outside).
        stokes: (3, 3, H, W) clean Stokes (s0, s1, s2) of the RGB image.
    """

    mask: Tensor
    object_mask: Tensor
    depth: Tensor
    normal: Tensor
    diffuse: Tensor
    specular: Tensor
    dolp_diffuse: Tensor
    dolp_specular: Tensor
    azimuth: Tensor
    stokes: Tensor


@dataclass
class SyntheticScene:
    """A generated scene: sensor-like views plus the ground truth used by tests and benchmarks.

    Attributes:
        name: scene name.
        views: one :class:`View` per camera (stokes from the quantised angle images; mask (the
            object's pixels unless generated with ``mask="surface"``), normal_gt and depth_gt
            (0 outside the mask) filled).
        angle_images: per view (4, 3, H, W) float32 images at 0/45/90/135 deg, in [0, 1].
        diffuse_gt: per view (3, H, W) float32 true diffuse colour (s0 / 2 units; the backdrop
            where no surface is hit), before noise and clipping.
        specular_gt: per view (3, H, W) float32 true specular colour (0 where no surface is hit).
        highlight_masks: per view (1, H, W) bool, mask & mean_c specular_gt >= highlight threshold.
        overexposed_masks: per view (1, H, W) bool, some angle image of some channel clipped at 1.
        mesh_vertices: (V, 3) float64 ground-truth mesh vertices (world frame), the whole scene.
        mesh_triangles: (F, 3) int64 ground-truth mesh triangles, the whole scene.
        meta: JSON-serialisable description (generator settings, materials, lights, conventions).
        object_triangles: (F,) bool, the triangles of the object to reconstruct (the floor of
            ``glossy_plane_sphere`` is not); None = every triangle. :meth:`object_mesh` is the
            evaluation ground truth (docs/evaluation.md).
        visibility: (num_views, F') bool, view v sees the centroid of triangle f of
            :meth:`object_mesh` from its front side, unhidden (a floor hides too); None when not
            computed (a scene folder written before it existed).
    """

    name: str
    views: list[View]
    angle_images: list[Tensor]
    diffuse_gt: list[Tensor]
    specular_gt: list[Tensor]
    highlight_masks: list[Tensor]
    overexposed_masks: list[Tensor]
    mesh_vertices: np.ndarray
    mesh_triangles: np.ndarray
    meta: dict = field(default_factory=dict)
    object_triangles: np.ndarray | None = None
    visibility: np.ndarray | None = None

    def object_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (V', 3), triangles (F', 3)) of the object only, unused vertices dropped."""
        return object_submesh(self.mesh_vertices, self.mesh_triangles, self.object_triangles)


def object_submesh(
    vertices: np.ndarray, triangles: np.ndarray, object_triangles: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """The triangles selected by ``object_triangles`` (all if None), vertices re-indexed."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if object_triangles is None:
        return vertices, triangles
    keep = np.asarray(object_triangles, dtype=bool)
    if keep.shape != (len(triangles),):
        raise ValueError(f"object_triangles must have one entry per triangle ({len(triangles)}), got {keep.shape}")
    if not keep.any():
        raise ValueError("object_triangles selects no triangle")
    kept = triangles[keep]
    used, inverse = np.unique(kept.reshape(-1), return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3).astype(np.int64)


def triangle_ranges(mask: np.ndarray) -> list[list[int]]:
    """Run-length form [[start, end), ...] of a bool mask (for JSON)."""
    mask = np.asarray(mask, dtype=bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]


def mask_from_ranges(ranges: list, size: int) -> np.ndarray:
    """Inverse of :func:`triangle_ranges`."""
    mask = np.zeros(size, dtype=bool)
    for start, end in ranges:
        if not (0 <= int(start) <= int(end) <= size):
            raise ValueError(f"triangle range [{start}, {end}) outside 0..{size}")
        mask[int(start):int(end)] = True
    return mask


@dataclass
class _Hits:
    """Ray-mesh intersections: ``mask`` (N,) over all rays, the rest (M, ...) for the M hits."""

    mask: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    face: np.ndarray
    material: np.ndarray
    on_object: np.ndarray


class SceneRenderer:
    """Ray-casts and shades one :class:`~polargs_plugin.data.scenes.SceneSpec` for any camera.

    Args:
        spec: the scene.
        refractive_index: n of every material that does not give its own (Fresnel DoLP).
        shadows: cast shadow rays towards each light.
    """

    def __init__(self, spec: SceneSpec, refractive_index: float = 1.5, shadows: bool = True):
        if not refractive_index > 1.0:
            raise ValueError(f"refractive_index must be > 1, got {refractive_index}")
        self.spec = spec
        self.refractive_index = float(refractive_index)
        self.shadows = shadows
        self._on_object = spec.object_mask()
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(spec.vertices.astype(np.float32)), o3d.core.Tensor(spec.triangles.astype(np.uint32))
        )

    def render(self, K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int) -> RenderedView:
        """Render the noise-free components of one view.

        Args:
            K: (3, 3) intrinsics (pixel centres at +0.5).
            world_to_camera: (4, 4) OpenCV world-to-camera transform.
            width: image width W.
            height: image height H.

        Returns:
            the :class:`RenderedView`.
        """
        K_t = torch.as_tensor(K, dtype=torch.float64)
        rotation = np.asarray(world_to_camera, np.float64)[:3, :3]
        origin = -rotation.T @ np.asarray(world_to_camera, np.float64)[:3, 3]
        # World directions R^T K^-1 (u + 0.5, v + 0.5, 1): their camera z is 1, so t_hit = depth.
        dirs = pixel_rays(K_t, height, width).reshape(3, -1).T.numpy() @ rotation
        hits = self._intersect(origin, dirs)
        hit = hits.mask
        view = -dirs[hit] / np.linalg.norm(dirs[hit], axis=1, keepdims=True)
        diffuse, specular = self._shade(hits, view)
        theta = torch.from_numpy(np.arccos(np.clip(np.einsum("ni,ni->n", hits.normal, view), 0.0, 1.0)))
        rho_d, rho_s = self._dolp(theta, hits.material)

        def image(values: np.ndarray) -> Tensor:
            """Scatter per-hit values (M, C) into a (C, H, W) image, 0 where nothing was hit."""
            values = values.reshape(values.shape[0], -1)
            out = np.zeros((hit.size, values.shape[1]))
            out[hit] = values
            return torch.from_numpy(np.ascontiguousarray(out.T.reshape(-1, height, width)))

        backdrop = np.zeros((hit.size, 3))
        backdrop[~hit] = self._backdrop(dirs[~hit])
        mask = torch.from_numpy(hit.reshape(1, height, width))
        object_hit = np.zeros_like(hit)
        object_hit[hit] = hits.on_object
        diffuse_img = image(diffuse) + torch.from_numpy(np.ascontiguousarray(backdrop.T.reshape(3, height, width)))
        specular_img = image(specular)
        normal_img = image(hits.normal @ rotation.T)
        azimuth = torch.where(mask, normal_azimuth(normal_img, K_t, AZIMUTH_MODEL), 0.0)
        rho_d_img, rho_s_img = image(rho_d), image(rho_s)
        linear = 2.0 * (diffuse_img * rho_d_img - specular_img * rho_s_img)
        stokes = torch.stack(
            [2.0 * (diffuse_img + specular_img), linear * torch.cos(2 * azimuth), linear * torch.sin(2 * azimuth)]
        )
        return RenderedView(
            mask=mask,
            object_mask=torch.from_numpy(object_hit.reshape(1, height, width)),
            depth=image(hits.depth),
            normal=normal_img,
            diffuse=diffuse_img,
            specular=specular_img,
            dolp_diffuse=rho_d_img,
            dolp_specular=rho_s_img,
            azimuth=azimuth,
            stokes=stokes,
        )

    def _dolp(self, theta: Tensor, material: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(diffuse DoLP, specular DoLP), (M,) each, of hits at zenith ``theta`` (M,) on the materials
        ``material`` (M,): the renderer's index for every hit, then each material's own optics."""
        rho_d = dolp_diffuse(theta, self.refractive_index).numpy()
        rho_s = dolp_specular(theta, self.refractive_index).numpy()
        for index, item in enumerate(self.spec.materials):
            sel = material == index
            if not sel.any() or (item.refractive_index is None and not item.is_conductor):
                continue
            if item.is_conductor:
                rho_d[sel] = 0.0  # a metal re-emits no diffusely polarized light
                rho_s[sel] = dolp_specular_conductor(theta[sel], item.refractive_index, item.extinction).numpy()
            else:
                rho_d[sel] = dolp_diffuse(theta[sel], item.refractive_index).numpy()
                rho_s[sel] = dolp_specular(theta[sel], item.refractive_index).numpy()
        return rho_d, rho_s

    def visibility(self, cameras: list[np.ndarray], K: np.ndarray, width: int, height: int) -> np.ndarray:
        """(len(cameras), F') bool: which of the object's triangles each camera sees
        (:func:`~polargs_plugin.data.visibility.triangle_visibility`, the whole scene hiding them)."""
        vertices, triangles = object_submesh(self.spec.vertices, self.spec.triangles, self.spec.object_triangles)
        return triangle_visibility(vertices, triangles, [(K, w2c, width, height) for w2c in cameras], self._scene)

    def _intersect(self, origin: np.ndarray, dirs: np.ndarray) -> _Hits:
        """Cast rays from ``origin`` along ``dirs`` (N, 3); shading normals face the ray origin."""
        return self._intersect_rays(np.broadcast_to(origin, dirs.shape), dirs)

    def _intersect_rays(self, origins: np.ndarray, dirs: np.ndarray) -> _Hits:
        """Cast rays from ``origins`` (N, 3) along ``dirs`` (N, 3); shading normals face the origins."""
        spec = self.spec
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        result = self._scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = result["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t_hit)
        triangle = result["primitive_ids"].numpy()[hit].astype(np.int64)
        uv = result["primitive_uvs"].numpy()[hit].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        normal = np.einsum("nk,nki->ni", bary, spec.vertex_normals[spec.triangles[triangle]])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        face = result["primitive_normals"].numpy()[hit].astype(np.float64)
        backface = np.einsum("ni,ni->n", face, dirs[hit]) > 0  # e.g. a one-sided surface seen from behind
        normal[backface] *= -1
        face[backface] *= -1
        return _Hits(
            mask=hit,
            depth=t_hit[hit],
            points=origins[hit] + t_hit[hit, None] * dirs[hit],
            normal=normal,
            face=face,
            material=spec.triangle_material[triangle],
            on_object=self._on_object[triangle],
        )

    def _shade(self, hits: _Hits, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Diffuse and specular RGB (M, 3) of the hits seen along ``view`` (M, 3, towards the camera)."""
        spec, count = self.spec, hits.points.shape[0]
        albedo, specular_weight, shininess = np.zeros((count, 3)), np.zeros(count), np.ones(count)
        tint = np.ones((count, 3))
        for index, material in enumerate(spec.materials):
            sel = hits.material == index
            albedo[sel] = evaluate_albedo(hits.points[sel], material)
            specular_weight[sel] = material.specular
            shininess[sel] = material.shininess
            tint[sel] = material.specular_tint
        irradiance = np.full((count, 3), spec.ambient)
        highlight = np.zeros((count, 3))
        for light in spec.lights:
            to_light, strength = self._light_at(light, hits.points)
            cos_light = np.einsum("ni,ni->n", hits.normal, to_light)
            lit = (cos_light > 0).astype(np.float64)
            if self.shadows:
                lit *= self._visible(hits.points + _SHADOW_EPS * hits.face, light)
            half = to_light + view
            half /= np.linalg.norm(half, axis=1, keepdims=True)
            cos_half = np.clip(np.einsum("ni,ni->n", hits.normal, half), 0.0, 1.0)
            irradiance += strength * (np.clip(cos_light, 0.0, None) * lit)[:, None]
            highlight += strength * (specular_weight * cos_half**shininess * lit)[:, None]
        if spec.environment is not None:
            box_visible = self._softboxes_visible(hits)
            irradiance += self._environment_irradiance(hits, box_visible)
            theta = np.arccos(np.clip(np.einsum("ni,ni->n", hits.normal, view), 0.0, 1.0))
            reflectance = self._reflectance(torch.from_numpy(theta), hits.material)
            reflected = self._environment_reflection(hits, view, shininess, box_visible)
            highlight += (specular_weight * reflectance)[:, None] * reflected
        return albedo * irradiance, highlight * tint

    def _softboxes_visible(self, hits: _Hits) -> np.ndarray:
        """(M, B) 1 where nothing hides softbox b's centre from hit m (0 with shadows off: none)."""
        boxes = self.spec.environment.softboxes
        out = np.ones((hits.points.shape[0], len(boxes)))
        if self.shadows:
            for b, box in enumerate(boxes):
                out[:, b] = self._visible(hits.points + _SHADOW_EPS * hits.face, Light("directional", box.direction, box.color))
        return out

    def _environment_irradiance(self, hits: _Hits, box_visible: np.ndarray) -> np.ndarray:
        """(M, 3) the environment's irradiance over pi at the hits (a Lambertian albedo's factor):
        sky and ground by the fixed sphere quadrature, each softbox as an area light at its centre,
        both hidden where the scene blocks the way (with ``shadows``)."""
        env = self.spec.environment
        dirs = sphere_directions(env.samples)
        cosines = np.clip(hits.normal @ dirs.T, 0.0, None)  # (M, J)
        if self.shadows:
            cosines *= self._open_along(hits.points + _SHADOW_EPS * hits.face, dirs, cosines > 0)
        total = cosines @ env.background(dirs) * (4.0 / env.samples)  # E / pi = sum L cos (4 pi / J) / pi
        for b, box in enumerate(env.softboxes):
            facing = np.clip(hits.normal @ np.asarray(box.direction), 0.0, None) * box_visible[:, b]
            total += (box.solid_angle / math.pi) * facing[:, None] * np.asarray(box.color)[None, :]
        return total

    def _environment_reflection(self, hits: _Hits, view: np.ndarray, shininess: np.ndarray,
                                box_visible: np.ndarray) -> np.ndarray:
        """(M, 3) environment radiance reflected towards ``view`` through each hit's lobe, before
        k_s and Fresnel: the lobe's fixed directions (:func:`lobe_directions`) look up the sky and
        ground, or, where the scene blocks them (or they point into the surface), the blocking
        surface's albedo times the environment's mean radiance (one diffuse interreflection); a
        softbox wider than the lobe is among what the directions see, a narrower one is convolved
        with the lobe in closed form (both Gaussian in angle)."""
        env = self.spec.environment
        mirror = 2.0 * np.einsum("ni,ni->n", hits.normal, view)[:, None] * hits.normal - view
        mirror /= np.linalg.norm(mirror, axis=1, keepdims=True)
        dirs = lobe_directions(mirror, shininess, _LOBE_SAMPLES)  # (M, K, 3)
        width2 = lobe_width(shininess) ** 2
        sampled_box = np.stack([width2 < box.angular_variance for box in env.softboxes], axis=1) \
            if env.softboxes else np.zeros((len(shininess), 0), dtype=bool)
        flat = dirs.reshape(-1, 3)
        seen = env.background(flat)
        for b, box in enumerate(env.softboxes):
            seen += np.repeat(sampled_box[:, b], _LOBE_SAMPLES)[:, None] * box.radiance(flat)
        seen = seen.reshape(dirs.shape)
        above = np.einsum("nki,ni->nk", dirs, hits.face) > 0
        blocked = ~above
        if self.shadows:
            blocked_colour, hit_mask = self._first_albedo(hits.points + _SHADOW_EPS * hits.face, dirs, above)
            seen = np.where(hit_mask[..., None], blocked_colour * env.mean_radiance(), seen)
        seen = np.where(blocked[..., None], 0.0, seen)
        total = seen.mean(axis=1)
        for b, box in enumerate(env.softboxes):
            variance = box.angular_variance + width2
            angle = np.arccos(np.clip(mirror @ np.asarray(box.direction), -1.0, 1.0))
            weight = box.solid_angle / (2 * math.pi * variance) * np.exp(-(angle**2) / (2 * variance))
            weight *= (~sampled_box[:, b]) * box_visible[:, b]
            total += weight[:, None] * np.asarray(box.color)[None, :]
        return total

    def _open_along(self, origins: np.ndarray, dirs: np.ndarray, wanted: np.ndarray) -> np.ndarray:
        """(M, J) 1 where the ray from origin m along the fixed direction j leaves the scene, for
        the pairs ``wanted`` (M, J) (0 elsewhere)."""
        m, j = np.nonzero(wanted)
        out = np.zeros(wanted.shape)
        for start in range(0, len(m), _RAY_CHUNK):
            mm, jj = m[start:start + _RAY_CHUNK], j[start:start + _RAY_CHUNK]
            rays = np.concatenate([origins[mm], dirs[jj]], axis=1).astype(np.float32)
            out[mm, jj] = ~self._scene.test_occlusions(o3d.core.Tensor(rays)).numpy()
        return out

    def _first_albedo(self, origins: np.ndarray, dirs: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Albedo (M, K, 3) of the first surface along each ray from origin m along dirs[m, k]
        for the pairs ``wanted`` (M, K), and (M, K) bool where such a surface was hit."""
        m, k = np.nonzero(wanted)
        colour, hit = np.zeros(dirs.shape), np.zeros(wanted.shape, dtype=bool)
        for start in range(0, len(m), _RAY_CHUNK):
            mm, kk = m[start:start + _RAY_CHUNK], k[start:start + _RAY_CHUNK]
            found = self._intersect_rays(origins[mm], dirs[mm, kk])
            mm, kk = mm[found.mask], kk[found.mask]
            hit[mm, kk] = True
            for index, material in enumerate(self.spec.materials):
                sel = found.material == index
                colour[mm[sel], kk[sel]] = evaluate_albedo(found.points[sel], material)
        return colour, hit

    def _reflectance(self, theta: Tensor, material: np.ndarray) -> np.ndarray:
        """(M,) Fresnel reflectance of unpolarized light, (R_s + R_p) / 2, at zenith ``theta`` (M,)
        on the materials ``material`` (M,) (as :meth:`_dolp` chooses their optics)."""
        out = torch.stack(fresnel_reflectance(theta, self.refractive_index)).mean(dim=0).numpy()
        for index, item in enumerate(self.spec.materials):
            sel = material == index
            if not sel.any() or (item.refractive_index is None and not item.is_conductor):
                continue
            pair = (fresnel_reflectance_conductor(theta[sel], item.refractive_index, item.extinction) if item.is_conductor
                    else fresnel_reflectance(theta[sel], item.refractive_index))
            out[sel] = torch.stack(pair).mean(dim=0).numpy()
        return out

    @staticmethod
    def _light_at(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions towards the light (N, 3) and RGB irradiance scale (N, 3)."""
        color = np.asarray(light.color, dtype=np.float64)[None, :]
        vector = np.asarray(light.vector, dtype=np.float64)
        if light.kind == "directional":
            return np.broadcast_to(vector, points.shape), np.broadcast_to(color, points.shape)
        if light.kind == "point":
            offset = vector - points
            dist2 = np.einsum("ni,ni->n", offset, offset)
            return offset / np.sqrt(dist2)[:, None], color / dist2[:, None]
        raise ValueError(f"unknown light kind {light.kind!r}")

    def _visible(self, origins: np.ndarray, light: Light) -> np.ndarray:
        """(N,) 1 where nothing blocks the way from the points (N, 3) to the light."""
        if origins.shape[0] == 0:
            return np.ones(0)
        if light.kind == "point":
            # Unnormalised directions: t = 1 is the light itself, so tfar = 1 bounds the segment.
            directions, tfar = np.asarray(light.vector, np.float64) - origins, 1.0
        else:
            directions, tfar = np.broadcast_to(np.asarray(light.vector, np.float64), origins.shape), np.inf
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        occluded = self._scene.test_occlusions(o3d.core.Tensor(rays), tfar=tfar).numpy()
        return (~occluded).astype(np.float64)

    def _backdrop(self, dirs: np.ndarray) -> np.ndarray:
        """(N, 3) what a ray that hits nothing sees: the environment, or else a dim grey backdrop
        weakly textured by the world ray direction."""
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        if self.spec.environment is not None:
            return self.spec.environment.radiance(unit)
        backdrop = Material("backdrop", albedo=(self.spec.background,) * 3, texture=_BACKDROP_TEXTURE)
        return evaluate_albedo(unit, backdrop)


def apply_sensor(
    stokes: Tensor, rng: np.random.Generator, noise_std: float = 0.005, quantize_bits: int = 8
) -> tuple[Tensor, Tensor, Tensor]:
    """Turn clean Stokes into what a division-of-focal-plane sensor delivers.

    Args:
        stokes: (3, C, H, W) clean Stokes.
        rng: noise generator.
        noise_std: standard deviation of the additive Gaussian noise on each angle image.
        quantize_bits: 8 or 16.

    Returns:
        ``(angle_images (4, C, H, W) float32 in [0, 1], stokes (3, C, H, W) float32 recomputed
        from them, overexposed (1, H, W) bool where some clean angle image reached 1)``.
    """
    if quantize_bits not in QUANTIZE_BITS:
        raise ValueError(f"quantize_bits must be one of {QUANTIZE_BITS}, got {quantize_bits}")
    if not noise_std >= 0:
        raise ValueError(f"noise_std must be >= 0, got {noise_std}")
    clean = intensities_from_stokes(stokes.to(torch.float64))
    overexposed = (clean >= 1.0).flatten(0, 1).any(dim=0, keepdim=True)
    noisy = clean + torch.from_numpy(rng.normal(0.0, noise_std, size=tuple(clean.shape))) if noise_std > 0 else clean
    levels = 2**quantize_bits - 1
    angles = (torch.round(noisy.clamp(0.0, 1.0) * levels) / levels).to(torch.float32)
    return angles, stokes_from_intensities(angles), overexposed


def assemble_scene(parts: Iterable[SyntheticScene]) -> SyntheticScene:
    """One scene of the parts :func:`generate_scene_views` yields (their views in order)."""
    out = None
    for part in parts:
        out = part if out is None else _extend(out, part)
    if out is None:
        raise ValueError("no views to assemble")
    return out


def generate_scene_views(
    name: str | SceneSpec,
    num_views: int = 24,
    width: int = 128,
    height: int = 128,
    seed: int = 0,
    noise_std: float = 0.005,
    quantize_bits: int = 8,
    refractive_index: float = 1.5,
    *,
    shadows: bool = True,
    highlight_threshold: float = 0.1,
    mask: str = "object",
    progress: bool = False,
    floor_texture: str | None = None,
) -> Iterator[SyntheticScene]:
    """Render a named procedural scene from ``num_views`` cameras orbiting it, one view at a time.

    Each item is the scene (mesh, meta) holding only the next view, so a writer can store it
    before the next is rendered; :func:`generate_scene` assembles them into one scene. Geometry,
    texture and cameras depend on the scene only; ``seed`` drives the sensor noise (each view
    draws from its own stream spawned from ``seed``), so equal seeds give identical arrays.

    Args:
        name: one of :data:`SCENE_NAMES`, or a custom :class:`SceneSpec`.
        num_views: number of cameras (>= 1), placed by the scene's camera layout (three elevation rings
            for the bundled scenes).
        width: image width W (pixels).
        height: image height H (pixels).
        seed: noise seed.
        noise_std: Gaussian noise std per angle image ([0, 1] units).
        quantize_bits: sensor bit depth, 8 or 16.
        refractive_index: n for the Fresnel DoLP.
        shadows: cast shadows from the lights.
        highlight_threshold: channel-mean specular colour above which a pixel is a highlight.
        mask: what the views' masks mark, one of :data:`MASK_KINDS`: ``"object"`` (default), the
            pixels where the object itself is seen, so a floor it stands on is background as in
            real object datasets; ``"surface"``, every pixel that sees a surface, so the object's
            outline over the floor lies inside the mask (an occlusion edge no mask marks; see
            docs/evaluation.md "The mask's edge"). GT depth and normals are 0 outside the mask.
        progress: show a tqdm progress bar over views.
        floor_texture: a key of :data:`~polargs_plugin.data.scenes.FLOOR_TEXTURES` that replaces
            the floor's texture; None: the scene's own (ValueError for a scene without a floor).

    Yields:
        one :class:`SyntheticScene` per view, in order.
    """
    if num_views < 1 or width < 1 or height < 1:
        raise ValueError(f"need num_views, width, height >= 1, got {num_views}, {width}, {height}")
    if mask not in MASK_KINDS:
        raise ValueError(f"mask must be one of {', '.join(MASK_KINDS)}, got {mask!r}")
    spec = name if isinstance(name, SceneSpec) else build_scene(name)
    if floor_texture is not None:
        spec = with_floor_texture(spec, floor_texture)
    renderer = SceneRenderer(spec, refractive_index, shadows)
    # Field of view is horizontal; keep the object's pixel size independent of the aspect ratio.
    K = intrinsics(width, height, spec.fov_deg)
    cameras = scene_cameras(spec, num_views)
    streams = np.random.SeedSequence(seed).spawn(num_views)
    meta = _meta(spec, num_views, width, height, seed, noise_std, quantize_bits, refractive_index, shadows,
                 highlight_threshold, mask)
    for index in tqdm(range(num_views), desc=f"rendering {spec.name}", unit="view", disable=not progress):
        clean = renderer.render(K, cameras[index], width, height)
        sensed = apply_sensor(clean.stokes, np.random.default_rng(streams[index]), noise_std, quantize_bits)
        part = _empty_scene(spec)
        _append_view(part, index, K, cameras[index], clean, sensed, mask, highlight_threshold)
        part.visibility = renderer.visibility([cameras[index]], K, width, height)
        part.meta = dict(meta)
        yield part


@same_arguments_as(generate_scene_views)
def generate_scene(*args: Any, **kwargs: Any) -> SyntheticScene:
    """Render a named procedural scene, all its views at once: the parts
    :func:`generate_scene_views` yields (arguments exactly as there), assembled.

    Returns:
        the :class:`SyntheticScene`.

    Example:
        >>> scene = generate_scene("glossy_plane_sphere", num_views=2, width=32, height=32)
        >>> scene.views[0].stokes.shape, scene.angle_images[0].shape
        (torch.Size([3, 3, 32, 32]), torch.Size([4, 3, 32, 32]))
    """
    return assemble_scene(generate_scene_views(*args, **kwargs))


def _extend(scene: SyntheticScene, part: SyntheticScene) -> SyntheticScene:
    """``scene`` with the views of ``part`` appended (the per-view lists)."""
    for name in ("views", "angle_images", "diffuse_gt", "specular_gt", "highlight_masks", "overexposed_masks"):
        getattr(scene, name).extend(getattr(part, name))
    if scene.visibility is not None and part.visibility is not None:
        scene.visibility = np.concatenate([scene.visibility, part.visibility])
    return scene


def _empty_scene(spec: SceneSpec) -> SyntheticScene:
    """The scene of ``spec`` with its mesh and no views yet."""
    return SyntheticScene(
        name=spec.name,
        views=[],
        angle_images=[],
        diffuse_gt=[],
        specular_gt=[],
        highlight_masks=[],
        overexposed_masks=[],
        mesh_vertices=spec.vertices.copy(),
        mesh_triangles=spec.triangles.copy(),
        object_triangles=None if spec.object_triangles is None else spec.object_mask().copy(),
    )


def _append_view(
    scene: SyntheticScene,
    index: int,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    clean: RenderedView,
    sensed: tuple[Tensor, Tensor, Tensor],
    mask: str,
    highlight_threshold: float,
) -> None:
    """Add view ``index`` to ``scene``: its rendering ``clean`` and what the sensor made of it,
    ``sensed`` = (angle images, Stokes, overexposed) of :func:`apply_sensor`."""
    angles, stokes, overexposed = sensed
    view_mask = clean.object_mask if mask == "object" else clean.mask
    scene.views.append(
        View(
            name=f"view_{index:03d}",
            K=torch.from_numpy(K.copy()),
            world_to_camera=torch.from_numpy(world_to_camera.copy()),
            stokes=stokes,
            mask=view_mask,
            normal_gt=torch.where(view_mask, clean.normal, 0.0).to(torch.float32),
            depth_gt=torch.where(view_mask, clean.depth, 0.0).to(torch.float32),
            source=f"synthetic:{scene.name}",
        )
    )
    scene.angle_images.append(angles)
    scene.diffuse_gt.append(clean.diffuse.to(torch.float32))
    scene.specular_gt.append(clean.specular.to(torch.float32))
    scene.highlight_masks.append(view_mask & (clean.specular.mean(dim=0, keepdim=True) >= highlight_threshold))
    scene.overexposed_masks.append(overexposed)


def _meta(spec: SceneSpec, num_views, width, height, seed, noise_std, quantize_bits, refractive_index, shadows,
          highlight_threshold, mask) -> dict:
    return {
        "generator": "polargs_plugin.data.synthetic",
        "generator_version": GENERATOR_VERSION,
        "scene": spec.name,
        "description": spec.description,
        "num_views": num_views,
        "width": width,
        "height": height,
        "seed": seed,
        "noise_std": noise_std,
        "quantize_bits": quantize_bits,
        "refractive_index": refractive_index,
        "azimuth_model": AZIMUTH_MODEL,
        "aolp_convention": "0.5*atan2(s2,s1) mod pi, ccw from image +x towards image up; "
        "diffuse AoLP = azimuth, specular = azimuth + pi/2",
        "stokes": "s0=(I0+I45+I90+I135)/2, s1=I0-I90, s2=I45-I135; training colour s0/2",
        "shading": "Lambert diffuse + Blinn-Phong specular (white, a metal's tint), world-fixed lights"
        + (", environment lighting (diffuse irradiance; reflections k_s F(theta) through the lobe)"
           if spec.environment is not None else "")
        + (", shadow rays" if shadows else ", no shadows"),
        "environment": None if spec.environment is None else asdict(spec.environment),
        "specular_zenith": "angle between shading normal and view direction",
        "ambient": spec.ambient,
        "background": {"kind": "unpolarized backdrop textured by world ray direction", "level": spec.background,
                       "texture": asdict(_BACKDROP_TEXTURE)},
        "highlight_threshold": highlight_threshold,
        "mask": mask,
        "materials": [asdict(m) for m in spec.materials],
        "lights": [asdict(light) for light in spec.lights],
        "camera": {"target": list(spec.target), "distance": spec.camera_distance, "fov_deg": spec.fov_deg,
                   "elevations_deg": list(spec.elevations_deg), "layout": spec.camera_layout,
                   "azimuth_deg": spec.camera_azimuth_deg},
        # Evaluation ground truth: the object's triangles of the scene mesh, [start, end) ranges.
        "object_triangles": triangle_ranges(spec.object_mask()),
    }
