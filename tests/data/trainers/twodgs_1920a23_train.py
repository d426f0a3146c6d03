# Test fixture for the patch scripts: a placeholder trainer with the statement shape of the 2DGS
# (hbb1/2d-gaussian-splatting @ 1920a23) training loop: the total loss is named differently, the
# render package carries surfel outputs (rend_normal, surf_normal, rend_dist), and a second no_grad
# block (the viewer's) follows the one with the optimizer step. Written for these tests; the
# bodies do nothing useful and nothing here is upstream code.

import os
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


def training(dataset, opt, pipe, testing_iterations, saving_iterations, checkpoint_iterations, checkpoint):
    first_iter = 0
    gaussians = GaussianModel(dataset.sh_degree)
    scene = Scene(dataset, gaussians)
    gaussians.training_setup(opt)
    background = torch.zeros(3)
    viewpoint_stack = None
    first_iter += 1
    for iteration in range(first_iter, opt.iterations + 1):
        gaussians.update_learning_rate(iteration)
        if not viewpoint_stack:
            viewpoint_stack = scene.getTrainCameras().copy()
        viewpoint_cam = viewpoint_stack.pop(randint(0, len(viewpoint_stack) - 1))

        render_pkg = render(viewpoint_cam, gaussians, pipe, background)
        image, viewspace_point_tensor, visibility_filter, radii = render_pkg["render"], render_pkg["viewspace_points"], render_pkg["visibility_filter"], render_pkg["radii"]

        gt_image = viewpoint_cam.original_image
        loss = l1_loss(image, gt_image)

        lambda_normal = opt.lambda_normal if iteration > 7000 else 0.0
        lambda_dist = opt.lambda_dist if iteration > 3000 else 0.0
        rend_dist = render_pkg["rend_dist"]
        rend_normal = render_pkg['rend_normal']
        surf_normal = render_pkg['surf_normal']
        normal_loss = lambda_normal * (1 - (rend_normal * surf_normal).sum(dim=0)).mean()
        dist_loss = lambda_dist * rend_dist.mean()

        total_loss = loss + dist_loss + normal_loss
        total_loss.backward()

        with torch.no_grad():
            if iteration in saving_iterations:
                scene.save(iteration)

            if iteration < opt.densify_until_iter:
                gaussians.add_densification_stats(viewspace_point_tensor, visibility_filter)
                if iteration > opt.densify_from_iter and iteration % opt.densification_interval == 0:
                    gaussians.densify_and_prune(opt.densify_grad_threshold, opt.opacity_cull, scene.cameras_extent, None)

            if iteration < opt.iterations:
                gaussians.optimizer.step()
                gaussians.optimizer.zero_grad(set_to_none = True)

            if (iteration in checkpoint_iterations):
                torch.save((gaussians.capture(), iteration), scene.model_path + "/chkpnt.pth")

        with torch.no_grad():
            if network_gui.conn is None:
                network_gui.try_connect(dataset.render_items)
            while network_gui.conn is not None:
                custom_cam = network_gui.receive()
                if custom_cam is not None:
                    render_pkg = render(custom_cam, gaussians, pipe, background, 1.0)
                break


if __name__ == "__main__":
    parser = ArgumentParser()
    args = parser.parse_args(sys.argv[1:])
    training(args, args, args, [], [], [], None)
