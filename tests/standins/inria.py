"""A stand-in for the graphdeco (Inria 3DGS) family's training objects, written for these tests.

It has the upstream attribute surface and conventions that the adapters translate, and renders
with the bundled reference rasterizer (the upstream CUDA rasterizers are not available here):

- ``Camera``: ``R`` = world-to-camera rotation transposed (numpy), ``T``, ``FoVx``/``FoVy``,
  ``image_width``/``image_height``, ``image_name``, ``original_image`` (3, H, W) and
  ``world_view_transform`` (the transposed 4x4, a tensor); no K (centred principal point).
- ``GaussianModel``: raw ``_xyz``, ``_features_dc`` (N, 1, 3), ``_features_rest`` (N, K-1, 3),
  ``_opacity`` (N, 1) logits, ``_scaling`` log, ``_rotation`` wxyz; getters; one Adam with named
  groups; ``densification_postfix`` concatenating rows with zero Adam moments and resetting the
  statistics (the seven-argument 2024 form needs ``tmp_radii`` set, as upstream).
- ``render(camera, pc, pipe, bg_color, scaling_modifier=1.0, separate_sh=False, override_color=None,
  use_trained_exp=False)`` -> dict with ``render`` (background added, clamped), ``viewspace_points``,
  ``visibility_filter`` (index tensor), ``radii`` and ``depth`` = accumulated inverse depth sum w / z.
- ``Scene`` with ``getTrainCameras()``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from polargs_plugin.backends.reference.rasterizer import rasterize
from polargs_plugin.types import View

SH_C0 = 0.28209479177387814


class Camera:
    def __init__(self, view: View):
        w2c = view.world_to_camera.double().numpy()
        K = view.K.double().numpy()
        self.R = w2c[:3, :3].T.copy()
        self.T = w2c[:3, 3].copy()
        self.image_width, self.image_height = view.width, view.height
        self.FoVx = 2 * math.atan(view.width / (2 * K[0, 0]))
        self.FoVy = 2 * math.atan(view.height / (2 * K[1, 1]))
        self.image_name = view.name
        self.original_image = view.image.float().clamp(0, 1)
        M = np.eye(4)
        M[:3, :3] = self.R.T
        M[:3, 3] = self.T
        self.world_view_transform = torch.tensor(M.T, dtype=torch.float32)

    def intrinsics(self) -> torch.Tensor:
        fx = self.image_width / (2 * math.tan(self.FoVx / 2))
        fy = self.image_height / (2 * math.tan(self.FoVy / 2))
        return torch.tensor([[fx, 0, self.image_width / 2], [0, fy, self.image_height / 2], [0, 0, 1]])


class Scene:
    def __init__(self, cameras: list[Camera]):
        self.cameras = cameras

    def getTrainCameras(self) -> list[Camera]:
        return self.cameras


class GaussianModel:
    """Vanilla-3DGS-shaped model (``postfix_arguments`` 6 = 2023 form, 7 = 2024 form)."""

    names = ("xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation")

    def __init__(self, points: torch.Tensor, colors: torch.Tensor, sh_degree: int = 1, postfix_arguments: int = 7):
        n = points.shape[0]
        self.max_sh_degree = sh_degree
        self.active_sh_degree = 0
        self.postfix_arguments = postfix_arguments
        self.tmp_radii = None
        dist = torch.cdist(points, points) + torch.eye(n) * 1e9
        knn = dist.topk(3, largest=False).values.square().mean(1).sqrt().clamp_min(1e-4)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1
        self._xyz = nn.Parameter(points.clone())
        self._features_dc = nn.Parameter(((colors - 0.5) / SH_C0)[:, None, :].clone())
        self._features_rest = nn.Parameter(torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3))
        self._opacity = nn.Parameter(torch.logit(torch.full((n, 1), 0.1)))
        self._scaling = nn.Parameter(knn.log()[:, None].repeat(1, 3))
        self._rotation = nn.Parameter(quats)
        lrs = {"xyz": 1.6e-3, "f_dc": 0.025, "f_rest": 0.025 / 20, "opacity": 0.05, "scaling": 0.01, "rotation": 0.002}
        self.optimizer = torch.optim.Adam(
            [{"params": [getattr(self, self._attr(k))], "lr": lr, "name": k} for k, lr in lrs.items()], lr=0.0, eps=1e-15
        )
        self.reset_statistics()

    @staticmethod
    def _attr(name: str) -> str:
        return {"xyz": "_xyz", "f_dc": "_features_dc", "f_rest": "_features_rest", "opacity": "_opacity",
                "scaling": "_scaling", "rotation": "_rotation"}[name]

    def reset_statistics(self) -> None:
        n = self._xyz.shape[0]
        self.xyz_gradient_accum = torch.zeros(n, 1)
        self.denom = torch.zeros(n, 1)
        self.max_radii2D = torch.zeros(n)

    @property
    def get_xyz(self):
        return self._xyz

    @property
    def get_features(self):
        return torch.cat([self._features_dc, self._features_rest], dim=1)

    @property
    def get_scaling(self):
        return torch.exp(self._scaling)

    @property
    def get_rotation(self):
        return nn.functional.normalize(self._rotation, dim=-1)

    @property
    def get_opacity(self):
        return torch.sigmoid(self._opacity)

    def add_densification_stats(self, viewspace_points, visibility_filter):
        grad = viewspace_points.grad[visibility_filter[:, 0]]
        self.xyz_gradient_accum[visibility_filter[:, 0]] += grad[:, :2].norm(dim=-1, keepdim=True)
        self.denom[visibility_filter[:, 0]] += 1

    def _cat_tensors_to_optimizer(self, tensors: dict) -> None:
        for group in self.optimizer.param_groups:
            extension = tensors[group["name"]]
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            new = nn.Parameter(torch.cat([old.detach(), extension], dim=0))
            if state is not None:
                state["exp_avg"] = torch.cat([state["exp_avg"], torch.zeros_like(extension)], dim=0)
                state["exp_avg_sq"] = torch.cat([state["exp_avg_sq"], torch.zeros_like(extension)], dim=0)
                self.optimizer.state[new] = state
            group["params"][0] = new
            setattr(self, self._attr(group["name"]), new)

    def densification_postfix(self, new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                              new_rotation, *extra):
        if len(extra) != self.postfix_arguments - 6:
            raise TypeError(f"densification_postfix takes {self.postfix_arguments} arguments")
        if extra and self.tmp_radii is None:
            raise TypeError("unsupported operand: tmp_radii is None")  # as upstream outside densify_and_prune
        self._cat_tensors_to_optimizer(dict(xyz=new_xyz, f_dc=new_features_dc, f_rest=new_features_rest,
                                            opacity=new_opacities, scaling=new_scaling, rotation=new_rotation))
        if extra:
            self.tmp_radii = torch.cat([self.tmp_radii, extra[0]])
        self.reset_statistics()


def postfix_2023(model: GaussianModel):
    """The six-argument signature (what inspect sees) of the 2023 form, bound to ``model``."""

    def densification_postfix(new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling, new_rotation):
        GaussianModel.densification_postfix(model, new_xyz, new_features_dc, new_features_rest, new_opacities,
                                            new_scaling, new_rotation)

    return densification_postfix


def postfix_2024(model: GaussianModel):
    def densification_postfix(new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling, new_rotation,
                              new_tmp_radii):
        GaussianModel.densification_postfix(model, new_xyz, new_features_dc, new_features_rest, new_opacities,
                                            new_scaling, new_rotation, new_tmp_radii)

    return densification_postfix


def make_model(points, colors, sh_degree: int = 1, version: int = 2024) -> GaussianModel:
    model = GaussianModel(points, colors, sh_degree, postfix_arguments=7 if version == 2024 else 6)
    model.densification_postfix = (postfix_2024 if version == 2024 else postfix_2023)(model)
    return model


def render(camera, pc, pipe, bg_color, scaling_modifier=1.0, separate_sh=False, override_color=None,
           use_trained_exp=False):
    """graphdeco's render() on the bundled rasterizer: clamped image, inverse accumulated depth."""
    K = camera.intrinsics()
    w2c = camera.world_view_transform.T
    scales = pc.get_scaling * scaling_modifier
    colors = override_color if override_color is not None else pc.get_features[:, : (pc.active_sh_degree + 1) ** 2]
    out = rasterize(pc.get_xyz, pc.get_rotation, scales, pc.get_opacity[:, 0], colors, K, w2c,
                    camera.image_width, camera.image_height, background=bg_color)
    # graphdeco's invdepth: per-Gaussian 1 / z of the mean, composited with the colour weights
    z = pc.get_xyz @ w2c[2, :3] + w2c[2, 3]
    inv = (1.0 / z.clamp_min(1e-6))[:, None].expand(-1, 3)
    inv_depth = rasterize(pc.get_xyz, pc.get_rotation, scales, pc.get_opacity[:, 0], inv, K, w2c,
                          camera.image_width, camera.image_height).color[:1]
    return {
        "render": out.color.clamp(0, 1),
        "viewspace_points": out.means2d,
        "visibility_filter": (out.radii > 0).nonzero(),
        "radii": out.radii,
        "depth": inv_depth,
    }


def l1_ssim_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """The vanilla 3DGS colour loss (1 - w) L1 + w (1 - SSIM)."""
    from polargs_plugin.losses import photometric_loss

    return photometric_loss(image, target, ssim_weight=ssim_weight)
