"""Placeholder renderer: ``render(camera, pc, pipe, bg, scaling_modifier=1.0, separate_sh=False,
override_color=None, use_trained_exp=False)`` through ``diff_gaussian_rasterization`` (2023 form:
colour and radii; 2024 form: also inverse depth, then ``depth`` in the package)."""

import math

import torch
from diff_gaussian_rasterization import GaussianRasterizationSettings, GaussianRasterizer

from gaussian_renderer import network_gui  # noqa: F401  (the upstream module layout)

FORM_2024 = "antialiasing" in GaussianRasterizationSettings._fields


def render(viewpoint_camera, pc, pipe, bg_color, scaling_modifier=1.0, separate_sh=False, override_color=None,
           use_trained_exp=False):
    screenspace_points = torch.zeros_like(pc.get_xyz, requires_grad=True, device="cuda") + 0
    if screenspace_points.requires_grad:  # not under no_grad
        screenspace_points.retain_grad()
    fields = dict(
        image_height=int(viewpoint_camera.image_height), image_width=int(viewpoint_camera.image_width),
        tanfovx=math.tan(viewpoint_camera.FoVx * 0.5), tanfovy=math.tan(viewpoint_camera.FoVy * 0.5),
        bg=bg_color, scale_modifier=scaling_modifier, viewmatrix=viewpoint_camera.world_view_transform,
        projmatrix=viewpoint_camera.full_proj_transform, sh_degree=pc.active_sh_degree,
        campos=viewpoint_camera.camera_center, prefiltered=False, debug=pipe.debug,
    )
    if FORM_2024:
        fields["antialiasing"] = False
    rasterizer = GaussianRasterizer(raster_settings=GaussianRasterizationSettings(**fields))
    colors = dict(colors_precomp=override_color) if override_color is not None else dict(shs=pc.get_features)
    out = rasterizer(means3D=pc.get_xyz, means2D=screenspace_points, opacities=pc.get_opacity,
                     scales=pc.get_scaling, rotations=pc.get_rotation, **colors)
    package = {"render": out[0].clamp(0, 1), "viewspace_points": screenspace_points,
               "visibility_filter": (out[1] > 0).nonzero(), "radii": out[1]}
    if FORM_2024:
        package["depth"] = out[2]
    return package
