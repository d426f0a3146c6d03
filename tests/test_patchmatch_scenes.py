"""Analytic textured scenes rendered by exact ray casting (shared by the densify tests).

A plane ``z = 0`` or a unit sphere at the origin, a solid procedural texture (sum of sinusoids
of world position), OpenCV cameras on a ring looking at the origin. Everything is computed in
float64 from closed-form ray intersections, so depths and normals are ground truth.
"""

from __future__ import annotations

import math

import torch

from polargs_plugin.types import View


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """(4, 4) float64 OpenCV world-to-camera (x right, y down, z forward)."""
    eye = torch.tensor(eye, dtype=torch.float64)
    fwd = torch.nn.functional.normalize(torch.tensor(target, dtype=torch.float64) - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor(up, dtype=torch.float64)), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def intrinsics(focal: float, width: int, height: int) -> torch.Tensor:
    return torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64)


def texture(points: torch.Tensor, seed: int = 3, scale: float = 1.0) -> torch.Tensor:
    """(3, ...) RGB in [0, 1] of a solid texture at world points (3, ...)."""
    g = torch.Generator().manual_seed(seed)
    out = torch.full((3,) + points.shape[1:], 0.5, dtype=torch.float64)
    for _ in range(8):
        direction = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        wavelength = scale * (0.25 + 0.35 * torch.rand(1, generator=g, dtype=torch.float64))
        phase = 2 * math.pi * torch.rand(3, generator=g, dtype=torch.float64)
        arg = torch.einsum("i,i...->...", direction, points) * (2 * math.pi / wavelength)
        out = out + 0.08 * torch.sin(arg.unsqueeze(0) + phase.reshape(3, *([1] * arg.ndim)))
    return out.clamp(0, 1)


def ray_cast(kind: str, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, textured: bool = True,
             texture_scale: float = 1.0):
    """Render (image (3,H,W), depth (1,H,W), normal (3,H,W) camera frame, mask (1,H,W)) exactly."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    eye = -R.T @ t
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                          torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    rays_cam = torch.linalg.inv(K) @ torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    rays = R.T @ rays_cam  # world directions with unit camera z
    if kind == "plane":
        s = -eye[2] / rays[2]
        hit = s > 0
        normal_w = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)[:, None].expand(3, s.numel())
    elif kind == "sphere":
        a = (rays**2).sum(0)
        bq = 2 * (rays * eye[:, None]).sum(0)
        c = (eye**2).sum() - 1.0
        disc = bq**2 - 4 * a * c
        hit = disc > 0
        s = (-bq - torch.sqrt(disc.clamp_min(0))) / (2 * a)
        hit = hit & (s > 0)
        normal_w = None
    else:
        raise ValueError(kind)
    s = torch.where(hit, s, torch.zeros_like(s))
    points = eye[:, None] + s * rays
    if normal_w is None:
        normal_w = torch.nn.functional.normalize(points, dim=0)
    normal_c = R @ normal_w
    normal_c = torch.where((normal_c * rays_cam).sum(0) > 0, -normal_c, normal_c)
    colour = texture(points, scale=texture_scale) if textured else torch.full_like(points, 0.6)
    m = hit.float()
    img = (colour * m).reshape(3, height, width).float()
    depth = (s * m).reshape(1, height, width).float()
    normal = (normal_c * m).reshape(3, height, width).float()
    return img, depth, normal, hit.reshape(1, height, width)


def make_scene(kind: str, size: int = 64, num_sources: int = 4, textured: bool = True,
               tilt_deg: float = 30.0, baseline_deg: float = 12.0, distance: float = 4.0,
               focal_ratio: float = 1.1, texture_scale: float = 1.0):
    """Reference camera ``v0`` plus ``num_sources`` cameras on a ring around it.

    Returns (views, renders) with renders[i] = (image, depth, normal, mask) of view i.
    """
    focal = size * focal_ratio
    K = intrinsics(focal, size, size)
    views, renders = [], []
    angles = [(0.0, 0.0)] + [(baseline_deg * math.cos(2 * math.pi * k / num_sources),
                               baseline_deg * math.sin(2 * math.pi * k / num_sources))
                              for k in range(num_sources)]
    for i, (da, db) in enumerate(angles):
        elev = math.radians(90.0 - tilt_deg + db)
        azim = math.radians(-90.0 + da)
        eye = (distance * math.cos(elev) * math.cos(azim), distance * math.cos(elev) * math.sin(azim),
               distance * math.sin(elev))
        w2c = look_at(eye)
        img, depth, normal, mask = ray_cast(kind, K, w2c, size, size, textured, texture_scale)
        stokes = torch.stack([2 * img, torch.zeros_like(img), torch.zeros_like(img)])
        views.append(View(f"v{i}", K.clone(), w2c, stokes, mask=mask, normal_gt=normal, depth_gt=depth))
        renders.append((img, depth, normal, mask))
    return views, renders


def test_plane_depth_is_camera_z_of_the_world_plane():
    views, renders = make_scene("plane", size=32, num_sources=1)
    for view, (_, depth, _, mask) in zip(views, renders):
        rays = torch.linalg.inv(view.K) @ torch.stack(torch.meshgrid(
            torch.arange(32, dtype=torch.float64) + 0.5, torch.arange(32, dtype=torch.float64) + 0.5,
            indexing="xy") + (torch.ones(32, 32, dtype=torch.float64),)).reshape(3, -1)
        cam = rays * depth.reshape(1, -1).double()
        world = view.R.T @ (cam - view.t[:, None])
        assert mask.all()
        assert torch.allclose(world[2], torch.zeros_like(world[2]), atol=1e-4)


def test_sphere_normals_are_radial_and_face_the_camera():
    views, renders = make_scene("sphere", size=32, num_sources=1)
    view, (_, depth, normal, mask) = views[0], renders[0]
    m = mask[0]
    assert m.float().mean() > 0.2
    assert (normal[2][m] < 0).all()
    n_world = view.R.T @ normal.reshape(3, -1).double()
    rays = torch.linalg.inv(view.K) @ torch.stack(torch.meshgrid(
        torch.arange(32, dtype=torch.float64) + 0.5, torch.arange(32, dtype=torch.float64) + 0.5,
        indexing="xy") + (torch.ones(32, 32, dtype=torch.float64),)).reshape(3, -1)
    world = view.R.T @ (rays * depth.reshape(1, -1).double() - view.t[:, None])
    sel = m.reshape(-1)
    assert torch.allclose(world[:, sel].norm(dim=0), torch.ones(int(sel.sum()), dtype=torch.float64), atol=1e-4)
    assert torch.allclose(n_world[:, sel], world[:, sel], atol=1e-4)
