"""A stand-in for zju3dv/PGSR's training objects (de24f1a), written for these tests on top of
:mod:`standins.inria`; it renders with the bundled reference rasterizer (PGSR's
diff-plane-rasterization is CUDA only). What it mimics, and where it simplifies:

- ``Camera``: the Inria camera plus PGSR's extras ``Fx``, ``Fy``, ``Cx = W / 2``, ``Cy = H / 2``,
  ``uid``, ``nearest_id``, ``camera_center``, ``get_image()`` -> (rgb, gray), ``get_k``,
  ``get_inv_k`` and ``get_rays`` (rays through INTEGER pixel coordinates, as PGSR).
- ``GaussianModel``: the Inria model plus ``_knn_f`` (N, 6) with its own Adam group ``knn_f``
  (second group, lr 0.01, as PGSR), ``max_all_points``, ``use_app``, the extra statistics
  ``xyz_gradient_accum_abs``, ``denom_abs``, ``max_weight``; ``densification_postfix(new_xyz,
  new_knn_f, new_features_dc, new_features_rest, new_opacities, new_scaling, new_rotation)``
  (PGSR's order) resets all six statistics; ``add_densification_stats(vs, vs_abs, mask)``;
  ``get_normal(camera)`` = world shortest axis flipped towards the camera centre.
- ``AppModel``: per-image exposure ``appear_ab`` (n, 2) and its optimizer.
- ``render(viewpoint_camera, pc, pipe, bg_color, scaling_modifier=1.0, override_color=None,
  app_model=None, return_plane=True, return_depth_normal=True)`` with PGSR's keys: ``render``
  (background added, not clamped), ``viewspace_points``, ``viewspace_points_abs``,
  ``visibility_filter`` (bool), ``radii``, ``out_observe``; with ``return_plane``:
  ``rendered_normal`` (camera frame, alpha-weighted), ``rendered_distance`` (alpha-weighted
  |n . p_cam|), ``plane_depth`` = distance / -(normal . ray) with rays through integer pixels
  ((px - Cx) / Fx, (py - Cy) / Fy, 1), i.e. half a pixel off the +0.5 centres, as PGSR; with
  ``return_depth_normal`` also ``depth_normal`` (finite-difference normal of ``plane_depth``,
  camera frame, times alpha detached); ``app_image`` = exp(a) I + b when ``pc.use_app``.
  No alpha is returned (as PGSR). Simplifications: ``viewspace_points_abs`` is the same tensor
  as ``viewspace_points`` (the reference rasterizer has no absolute-gradient output) and
  ``out_observe`` is 1 for every visible Gaussian (not a pixel count).
- ``image_loss`` / ``scale_loss`` / ``single_view_loss``: the shape of PGSR's train.py terms.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.ssim import ssim_map
from polargs_plugin.types import View
from standins import inria
from standins.inria import SH_C0, Scene  # noqa: F401  (re-exported)

__all__ = ["Camera", "Scene", "GaussianModel", "AppModel", "make_model", "render", "image_loss", "scale_loss",
           "single_view_loss", "SH_C0"]


class Camera(inria.Camera):
    def __init__(self, view: View, uid: int = 0):
        super().__init__(view)
        self.uid = uid
        self.nearest_id: list[int] = []
        self.Fx = self.image_width / (2 * math.tan(self.FoVx / 2))
        self.Fy = self.image_height / (2 * math.tan(self.FoVy / 2))
        self.Cx = 0.5 * self.image_width
        self.Cy = 0.5 * self.image_height
        self.camera_center = torch.linalg.inv(self.world_view_transform)[3, :3]
        image = self.original_image
        self.original_image_gray = (0.299 * image[0] + 0.587 * image[1] + 0.114 * image[2])[None]

    def get_image(self):
        return self.original_image, self.original_image_gray

    def get_k(self, scale: float = 1.0) -> torch.Tensor:
        return torch.tensor([[self.Fx / scale, 0, self.Cx / scale], [0, self.Fy / scale, self.Cy / scale], [0, 0, 1]])

    def get_inv_k(self, scale: float = 1.0) -> torch.Tensor:
        return torch.linalg.inv(self.get_k(scale))

    def get_rays(self, scale: float = 1.0) -> torch.Tensor:
        """(H, W, 3) camera-frame rays through integer pixel coordinates (PGSR's convention)."""
        w, h = int(self.image_width / scale), int(self.image_height / scale)
        py, px = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                                indexing="ij")
        return torch.stack([(px - self.Cx / scale) / self.Fx * scale, (py - self.Cy / scale) / self.Fy * scale,
                            torch.ones_like(px)], dim=-1)


def _rotation_matrices(quats: torch.Tensor) -> torch.Tensor:
    w, x, y, z = nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


class GaussianModel(inria.GaussianModel):
    names = ("xyz", "knn_f", "f_dc", "f_rest", "opacity", "scaling", "rotation")

    def __init__(self, points: torch.Tensor, colors: torch.Tensor, sh_degree: int = 1, max_all_points: int = 6_000_000):
        super().__init__(points, colors, sh_degree, postfix_arguments=6)
        n = points.shape[0]
        self._knn_f = nn.Parameter(torch.randn(n, 6))
        self.max_all_points = max_all_points
        self.use_app = False
        lrs = {"xyz": 1.6e-3, "knn_f": 0.01, "f_dc": 0.0025, "f_rest": 0.0025 / 20, "opacity": 0.05, "scaling": 0.005,
               "rotation": 0.001}
        self.optimizer = torch.optim.Adam(
            [{"params": [getattr(self, self._attr(k))], "lr": lr, "name": k} for k, lr in lrs.items()], lr=0.0, eps=1e-15
        )

    @staticmethod
    def _attr(name: str) -> str:
        return "_knn_f" if name == "knn_f" else inria.GaussianModel._attr(name)

    def reset_statistics(self) -> None:
        super().reset_statistics()
        n = self._xyz.shape[0]
        self.xyz_gradient_accum_abs = torch.zeros(n, 1)
        self.denom_abs = torch.zeros(n, 1)
        self.max_weight = torch.zeros(n)

    def get_normal(self, camera) -> torch.Tensor:
        """World-frame shortest axis, flipped to point towards the camera centre (PGSR)."""
        rotations = _rotation_matrices(self._rotation)
        index = self.get_scaling.min(dim=-1).indices
        axis = rotations[torch.arange(rotations.shape[0]), :, index]
        towards = camera.camera_center.to(axis) - self._xyz
        flip = (axis * towards).sum(-1) < 0
        return torch.where(flip[:, None], -axis, axis)

    def add_densification_stats(self, viewspace_points, viewspace_points_abs, update_filter):
        self.xyz_gradient_accum[update_filter] += viewspace_points.grad[update_filter, :2].norm(dim=-1, keepdim=True)
        self.xyz_gradient_accum_abs[update_filter] += viewspace_points_abs.grad[update_filter, :2].norm(dim=-1, keepdim=True)
        self.denom[update_filter] += 1
        self.denom_abs[update_filter] += 1

    def densification_postfix(self, new_xyz, new_knn_f, new_features_dc, new_features_rest, new_opacities,
                              new_scaling, new_rotation):
        self._cat_tensors_to_optimizer(dict(xyz=new_xyz, knn_f=new_knn_f, f_dc=new_features_dc,
                                            f_rest=new_features_rest, opacity=new_opacities, scaling=new_scaling,
                                            rotation=new_rotation))
        self.reset_statistics()


def make_model(points, colors, sh_degree: int = 1, max_all_points: int = 6_000_000) -> GaussianModel:
    return GaussianModel(points, colors, sh_degree, max_all_points)


class AppModel(nn.Module):
    def __init__(self, num_images: int = 16):
        super().__init__()
        self.appear_ab = nn.Parameter(torch.zeros(num_images, 2))
        self.optimizer = torch.optim.Adam([{"params": self.appear_ab, "lr": 0.001, "name": "appear_ab"}], betas=(0.9, 0.99))


def _depth_normal(plane_depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(3, H, W) camera-frame normal of the points plane_depth x integer-pixel rays (central
    differences, facing the camera, zero on the border)."""
    points = camera.get_rays().to(plane_depth) * plane_depth[0, :, :, None]
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    normal = nn.functional.normalize(torch.cross(dx, dy, dim=-1), dim=-1)
    flip = (normal * points[1:-1, 1:-1]).sum(-1, keepdim=True) > 0
    normal = torch.where(flip, -normal, normal)
    return nn.functional.pad(normal.permute(2, 0, 1), (1, 1, 1, 1))


def render(viewpoint_camera, pc, pipe, bg_color, scaling_modifier=1.0, override_color=None, app_model=None,
           return_plane=True, return_depth_normal=True):
    """PGSR's render() on the bundled rasterizer (see the module docstring)."""
    cam = viewpoint_camera
    K = cam.intrinsics()
    w2c = cam.world_view_transform.T
    width, height = cam.image_width, cam.image_height
    scales = pc.get_scaling * scaling_modifier
    opacity = pc.get_opacity[:, 0]
    colors = override_color if override_color is not None else pc.get_features[:, : (pc.active_sh_degree + 1) ** 2]
    out = rasterize(pc.get_xyz, pc.get_rotation, scales, opacity, colors, K, w2c, width, height, background=bg_color)
    visible = out.radii > 0
    result = {
        "render": out.color,
        "viewspace_points": out.means2d,
        "viewspace_points_abs": out.means2d,
        "visibility_filter": visible,
        "radii": out.radii,
        "out_observe": visible.int(),
    }
    if app_model is not None and pc.use_app:
        a, b = app_model.appear_ab[cam.uid]
        result["app_image"] = torch.exp(a) * out.color + b
    if not return_plane:
        return result
    # per-Gaussian plane inputs, as PGSR's input_all_map: camera normal, 1, |n . p_cam|
    normal_cam = pc.get_normal(cam) @ w2c[:3, :3].T
    points_cam = pc.get_xyz @ w2c[:3, :3].T + w2c[:3, 3]
    distance = (normal_cam * points_cam).sum(-1).abs()
    plane = rasterize(pc.get_xyz, pc.get_rotation, scales, opacity,
                      torch.stack([distance, torch.zeros_like(distance), torch.zeros_like(distance)], -1),
                      K, w2c, width, height)
    rendered_normal = out.normal  # composited with the same weights; camera frame, facing the camera
    rendered_distance = plane.color[:1]
    rays = cam.get_rays().to(rendered_normal).permute(2, 0, 1)  # integer pixels, as PGSR's kernel
    plane_depth = rendered_distance / -((rendered_normal * rays).sum(0, keepdim=True) + 1.0e-8)
    result.update(rendered_normal=rendered_normal, rendered_distance=rendered_distance, plane_depth=plane_depth)
    if return_depth_normal:
        result["depth_normal"] = _depth_normal(plane_depth, cam) * out.alpha.detach()
    return result


def image_loss(render_pkg, gt_image, lambda_dssim: float = 0.2):
    """PGSR's image loss: L1 of ``app_image`` when present and the SSIM loss < 0.5, else of
    ``render``; SSIM always of ``render``."""
    image = render_pkg["render"]
    ssim_loss = 1.0 - ssim_map(image, gt_image).mean()
    if "app_image" in render_pkg and ssim_loss < 0.5:
        l1 = (render_pkg["app_image"] - gt_image).abs().mean()
    else:
        l1 = (image - gt_image).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * ssim_loss


def scale_loss(pc, visibility_filter, weight: float = 100.0):
    """PGSR's flattening term: the smallest scale of the visible Gaussians, x100."""
    if visibility_filter.sum() == 0:
        return pc.get_scaling.new_zeros(())
    return weight * pc.get_scaling[visibility_filter].min(dim=-1).values.mean()


def single_view_loss(render_pkg, weight: float = 0.015):
    """PGSR's depth-normal term (without the image-gradient weight)."""
    return weight * (render_pkg["depth_normal"] - render_pkg["rendered_normal"]).abs().sum(0).mean()

