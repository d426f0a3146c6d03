# Test fixture for the patch scripts: a placeholder trainer with the statement shape of the GOF
# (autonomousvision/gaussian-opacity-fields @ 5245b20) training loop: kernel_size render argument,
# 3D filter recomputation, an image-saving no_grad block before the main one. Written for these
# tests; nothing here is upstream code.

import os
import random
import torch
from random import randint
from utils.loss_utils import l1_loss, ssim
from gaussian_renderer import render, network_gui
import sys
from scene import Scene, GaussianModel
from argparse import ArgumentParser
try:
    from torch.utils.tensorboard import SummaryWriter
    HAVE_TB = True
except ImportError:
    HAVE_TB = False

from utils.depth_utils import depth_to_normal


@torch.no_grad()
def helper(image):
    return image


def training(dataset, opt, pipe, testing_iterations, saving_iterations, checkpoint_iterations, checkpoint, debug_from):
    first_iter = 0
    gaussians = GaussianModel(dataset.sh_degree)
    scene = Scene(dataset, gaussians)
    gaussians.training_setup(opt)
    background = torch.zeros(3)
    trainCameras = scene.getTrainCameras().copy()
    gaussians.compute_3D_filter(cameras=trainCameras)
    viewpoint_stack = None
    first_iter += 1
    for iteration in range(first_iter, opt.iterations + 1):        

        gaussians.update_learning_rate(iteration)
        if not viewpoint_stack:
            viewpoint_stack = scene.getTrainCameras().copy()
        viewpoint_cam = viewpoint_stack.pop(randint(0, len(viewpoint_stack) - 1))

        render_pkg = render(viewpoint_cam, gaussians, pipe, background, kernel_size=dataset.kernel_size)
        rendering, viewspace_point_tensor, visibility_filter, radii = render_pkg["render"], render_pkg["viewspace_points"], render_pkg["visibility_filter"], render_pkg["radii"]
        image = rendering[:3]

        gt_image = viewpoint_cam.original_image
        Ll1 = l1_loss(image, gt_image)
        rgb_loss = (1.0 - opt.lambda_dssim) * Ll1 + opt.lambda_dssim * (1.0 - ssim(image, gt_image))
        distortion_loss = rendering[8].mean()
        depth_normal, _ = depth_to_normal(viewpoint_cam, rendering[6][None])
        depth_normal_loss = (1 - (rendering[3:6] * depth_normal).sum(dim=0)).mean()

        # Final loss
        loss = rgb_loss + depth_normal_loss * opt.lambda_depth_normal + distortion_loss * opt.lambda_distortion
        loss.backward()

        save_pictures = False
        if save_pictures and iteration % 100 == 0:
            with torch.no_grad():
                eval_cam = trainCameras[random.randint(0, len(trainCameras) - 1)]
                rendering = render(eval_cam, gaussians, pipe, background, kernel_size=dataset.kernel_size)["render"]

        with torch.no_grad():
            if iteration in saving_iterations:
                scene.save(iteration)

            if iteration < opt.densify_until_iter:
                gaussians.add_densification_stats(viewspace_point_tensor, visibility_filter)
                if iteration > opt.densify_from_iter and iteration % opt.densification_interval == 0:
                    gaussians.densify_and_prune(opt.densify_grad_threshold, 0.05, scene.cameras_extent, None)
                    gaussians.compute_3D_filter(cameras=trainCameras)

            if iteration % 100 == 0 and iteration > opt.densify_until_iter:
                if iteration < opt.iterations - 100:
                    gaussians.compute_3D_filter(cameras=trainCameras)

            if iteration < opt.iterations:
                gaussians.optimizer.step()
                gaussians.optimizer.zero_grad(set_to_none = True)

            if (iteration in checkpoint_iterations):
                torch.save((gaussians.capture(), iteration), scene.model_path + "/chkpnt.pth")


if __name__ == "__main__":
    parser = ArgumentParser()
    args = parser.parse_args(sys.argv[1:])
    training(args, args, args, [], [], [], None, -1)
