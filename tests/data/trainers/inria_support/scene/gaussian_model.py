"""Placeholder GaussianModel with the upstream attribute surface: raw parameters, activated
getters, one Adam with a named group per parameter, densification statistics, clone-and-prune
densification through ``densification_postfix`` / ``prune_points`` (which keep the Adam state in
step), ``capture`` / ``restore``. The ``densification_postfix`` form follows the rasterizer: seven
arguments with ``tmp_radii`` (set only inside ``densify_and_prune``) for the 2024 form."""

import torch
from diff_gaussian_rasterization import GaussianRasterizationSettings
from simple_knn._C import distCUDA2
from torch import nn

from utils.general_utils import get_expon_lr_func

FORM_2024 = "antialiasing" in GaussianRasterizationSettings._fields
SH_C0 = 0.28209479177387814
GROUPS = ("xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation")


def _logit(x):
    return torch.log(x / (1 - x))


class GaussianModel:
    def __init__(self, sh_degree, optimizer_type="default"):
        self.active_sh_degree, self.max_sh_degree = 0, sh_degree
        self.optimizer_type = optimizer_type
        self.optimizer = None
        self.tmp_radii = None
        self.spatial_lr_scale = 0.0
        for name in ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity"):
            setattr(self, name, torch.empty(0))
        self.max_radii2D = self.xyz_gradient_accum = self.denom = torch.empty(0)

    # ------------------------------------------------------------------ getters
    @property
    def get_xyz(self):
        return self._xyz

    @property
    def get_features(self):
        return torch.cat((self._features_dc, self._features_rest), dim=1)

    @property
    def get_scaling(self):
        return torch.exp(self._scaling)

    @property
    def get_rotation(self):
        return torch.nn.functional.normalize(self._rotation)

    @property
    def get_opacity(self):
        return torch.sigmoid(self._opacity)

    # ---------------------------------------------------------------- set-up
    def create_from_pcd(self, xyz, rgb, spatial_lr_scale):
        self.spatial_lr_scale = spatial_lr_scale
        points = torch.tensor(xyz, dtype=torch.float32).cuda()
        n, rest = points.shape[0], (self.max_sh_degree + 1) ** 2 - 1
        dist2 = torch.clamp_min(distCUDA2(points), 1e-7)
        rotation = torch.zeros((n, 4), device="cuda")
        rotation[:, 0] = 1
        self._xyz = nn.Parameter(points.requires_grad_(True))
        self._features_dc = nn.Parameter(((torch.tensor(rgb, dtype=torch.float32) - 0.5) / SH_C0)[:, None].cuda())
        self._features_rest = nn.Parameter(torch.zeros((n, rest, 3), device="cuda"))
        self._scaling = nn.Parameter(torch.log(torch.sqrt(dist2))[:, None].repeat(1, 3))
        self._rotation = nn.Parameter(rotation)
        self._opacity = nn.Parameter(_logit(0.1 * torch.ones((n, 1), device="cuda")))
        self.max_radii2D = torch.zeros(n, device="cuda")

    def training_setup(self, training_args):
        n = self._xyz.shape[0]
        self.xyz_gradient_accum = torch.zeros((n, 1), device="cuda")
        self.denom = torch.zeros((n, 1), device="cuda")
        rates = (training_args.position_lr_init * self.spatial_lr_scale, training_args.feature_lr,
                 training_args.feature_lr / 20.0, training_args.opacity_lr, training_args.scaling_lr,
                 training_args.rotation_lr)
        params = (self._xyz, self._features_dc, self._features_rest, self._opacity, self._scaling, self._rotation)
        groups = [{"params": [p], "lr": lr, "name": name} for p, lr, name in zip(params, rates, GROUPS)]
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        self.exposure_optimizer = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=0.0)
        self.xyz_scheduler_args = get_expon_lr_func(training_args.position_lr_init * self.spatial_lr_scale,
                                                    training_args.position_lr_final * self.spatial_lr_scale,
                                                    max_steps=training_args.position_lr_max_steps)

    def update_learning_rate(self, iteration):
        for group in self.optimizer.param_groups:
            if group["name"] == "xyz":
                group["lr"] = self.xyz_scheduler_args(iteration)

    def oneupSHdegree(self):
        self.active_sh_degree = min(self.active_sh_degree + 1, self.max_sh_degree)

    # ------------------------------------------------------------ checkpoints
    def capture(self):
        return (self.active_sh_degree, self._xyz, self._features_dc, self._features_rest, self._scaling,
                self._rotation, self._opacity, self.max_radii2D, self.xyz_gradient_accum, self.denom,
                self.optimizer.state_dict(), float(self.spatial_lr_scale))

    def restore(self, model_args, training_args):
        (self.active_sh_degree, xyz, dc, rest, scaling, rotation, opacity, self.max_radii2D, accum, denom,
         opt_dict, self.spatial_lr_scale) = model_args
        self._xyz, self._features_dc, self._features_rest = nn.Parameter(xyz), nn.Parameter(dc), nn.Parameter(rest)
        self._scaling, self._rotation, self._opacity = nn.Parameter(scaling), nn.Parameter(rotation), nn.Parameter(opacity)
        self.training_setup(training_args)
        self.xyz_gradient_accum, self.denom = accum, denom
        self.optimizer.load_state_dict(opt_dict)

    # ---------------------------------------------------------- densification
    def _replace_rows(self, make):
        """Every group's parameter and Adam moments through ``make(name, tensor, is_moment)``."""
        out = {}
        for group in self.optimizer.param_groups:
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            new = nn.Parameter(make(group["name"], old.detach(), False).requires_grad_(True))
            if state is not None:
                state["exp_avg"] = make(group["name"], state["exp_avg"], True)
                state["exp_avg_sq"] = make(group["name"], state["exp_avg_sq"], True)
                self.optimizer.state[new] = state
            group["params"][0] = new
            out[group["name"]] = new
        self._xyz, self._features_dc, self._features_rest = out["xyz"], out["f_dc"], out["f_rest"]
        self._opacity, self._scaling, self._rotation = out["opacity"], out["scaling"], out["rotation"]

    def _postfix_rows(self, rows):
        def make(name, tensor, is_moment):
            extra = torch.zeros_like(rows[name]) if is_moment else rows[name]
            return torch.cat([tensor, extra])
        self._replace_rows(make)
        n = self._xyz.shape[0]
        self.xyz_gradient_accum = torch.zeros((n, 1), device="cuda")
        self.denom = torch.zeros((n, 1), device="cuda")
        self.max_radii2D = torch.zeros(n, device="cuda")

    if FORM_2024:
        def densification_postfix(self, new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                                  new_rotation, new_tmp_radii):
            self._postfix_rows(dict(xyz=new_xyz, f_dc=new_features_dc, f_rest=new_features_rest,
                                    opacity=new_opacities, scaling=new_scaling, rotation=new_rotation))
            self.tmp_radii = torch.cat((self.tmp_radii, new_tmp_radii))
    else:
        def densification_postfix(self, new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                                  new_rotation):
            self._postfix_rows(dict(xyz=new_xyz, f_dc=new_features_dc, f_rest=new_features_rest,
                                    opacity=new_opacities, scaling=new_scaling, rotation=new_rotation))

    def prune_points(self, mask):
        keep = ~mask
        self._replace_rows(lambda name, tensor, is_moment: tensor[keep])
        self.xyz_gradient_accum, self.denom = self.xyz_gradient_accum[keep], self.denom[keep]
        self.max_radii2D = self.max_radii2D[keep]
        if self.tmp_radii is not None:
            self.tmp_radii = self.tmp_radii[keep]

    def add_densification_stats(self, viewspace_point_tensor, update_filter):
        self.xyz_gradient_accum[update_filter] += torch.norm(viewspace_point_tensor.grad[update_filter, :2], dim=-1, keepdim=True)
        self.denom[update_filter] += 1

    def densify_and_prune(self, max_grad, min_opacity, extent, max_screen_size, radii=None):
        grads = (self.xyz_gradient_accum / self.denom).nan_to_num(0.0)[:, 0]
        self.tmp_radii = radii if radii is not None else None
        chosen = grads >= max(max_grad, float(torch.quantile(grads, 0.9)))  # at most a tenth more a pass
        rows = dict(new_xyz=self._xyz[chosen], new_features_dc=self._features_dc[chosen],
                    new_features_rest=self._features_rest[chosen], new_opacities=self._opacity[chosen],
                    new_scaling=self._scaling[chosen], new_rotation=self._rotation[chosen])
        if FORM_2024:
            rows["new_tmp_radii"] = self.tmp_radii[chosen]
        self.densification_postfix(**{k: v.detach() for k, v in rows.items()})
        self.prune_points((self.get_opacity < min_opacity).squeeze(-1))
        self.tmp_radii = None
