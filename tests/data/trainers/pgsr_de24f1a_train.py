# Test fixture for the patch scripts: a placeholder trainer with the statement shape of the PGSR
# (zju3dv/PGSR @ de24f1a) training loop: app_model render argument over two lines, a second render
# for the nearest view, a commented-out GUI block, the multi-view trim. Written for these tests;
# nothing here is upstream code.

import os
import torch
import random
from random import randint
from utils.loss_utils import l1_loss, ssim
from gaussian_renderer import render, network_gui
import sys, time
from scene import Scene, GaussianModel
from argparse import ArgumentParser
from scene.app_model import AppModel
try:
    from torch.utils.tensorboard import SummaryWriter
    HAVE_TB = True
except ImportError:
    HAVE_TB = False
import torch.nn.functional as F


def training(dataset, opt, pipe, testing_iterations, saving_iterations, checkpoint_iterations, checkpoint, debug_from):
    first_iter = 0
    gaussians = GaussianModel(dataset.sh_degree)
    scene = Scene(dataset, gaussians)
    gaussians.training_setup(opt)

    app_model = AppModel()
    app_model.train()
    background = torch.zeros(3)
    viewpoint_stack = None
    first_iter += 1

    for iteration in range(first_iter, opt.iterations + 1):
        # if network_gui.conn == None:
        #     net_image = render(custom_cam, gaussians, pipe, background, 1.0)["render"]

        gaussians.update_learning_rate(iteration)
        if not viewpoint_stack:
            viewpoint_stack = scene.getTrainCameras().copy()
        viewpoint_cam = viewpoint_stack.pop(randint(0, len(viewpoint_stack) - 1))
        gt_image, gt_image_gray = viewpoint_cam.get_image()

        bg = torch.rand(3) if opt.random_background else background
        render_pkg = render(viewpoint_cam, gaussians, pipe, bg, app_model=app_model,
                            return_plane=iteration>opt.single_view_weight_from_iter, return_depth_normal=iteration>opt.single_view_weight_from_iter)
        image, viewspace_point_tensor, visibility_filter, radii = \
            render_pkg["render"], render_pkg["viewspace_points"], render_pkg["visibility_filter"], render_pkg["radii"]

        Ll1 = l1_loss(image, gt_image)
        image_loss = (1.0 - opt.lambda_dssim) * Ll1 + opt.lambda_dssim * (1.0 - ssim(image, gt_image))
        loss = image_loss.clone()

        if iteration > opt.multi_view_weight_from_iter:
            nearest_cam = scene.getTrainCameras()[random.sample(viewpoint_cam.nearest_id, 1)[0]]
            nearest_render_pkg = render(nearest_cam, gaussians, pipe, bg, app_model=app_model,
                                        return_plane=True, return_depth_normal=False)
            with torch.no_grad():
                weights = nearest_render_pkg["plane_depth"].detach()
            loss += (weights * 0).mean()

        loss.backward()

        with torch.no_grad():
            if iteration in saving_iterations:
                scene.save(iteration)

            if iteration < opt.densify_until_iter:
                gaussians.add_densification_stats(viewspace_point_tensor, render_pkg["viewspace_points_abs"], visibility_filter)
                if iteration > opt.densify_from_iter and iteration % opt.densification_interval == 0:
                    gaussians.densify_and_prune(opt.densify_grad_threshold, opt.densify_abs_grad_threshold,
                                                opt.opacity_cull_threshold, scene.cameras_extent, None)

            if opt.use_multi_view_trim and iteration % 1000 == 0 and iteration < opt.densify_until_iter:
                for view in scene.getTrainCameras():
                    render_pkg_tmp = render(view, gaussians, pipe, bg, app_model=app_model, return_plane=False, return_depth_normal=False)

            if iteration < opt.iterations:
                gaussians.optimizer.step()
                app_model.optimizer.step()
                gaussians.optimizer.zero_grad(set_to_none = True)
                app_model.optimizer.zero_grad(set_to_none = True)

            if (iteration in checkpoint_iterations):
                torch.save((gaussians.capture(), iteration), scene.model_path + "/chkpnt.pth")
                app_model.save_weights(scene.model_path, iteration)

    app_model.save_weights(scene.model_path, opt.iterations)


if __name__ == "__main__":
    parser = ArgumentParser()
    args = parser.parse_args(sys.argv[1:])
    training(args, args, args, [], [], [], None, -1)
