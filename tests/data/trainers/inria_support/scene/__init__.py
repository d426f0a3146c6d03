"""Placeholder Scene: reads ``<source>/sparse/0`` (COLMAP text) and ``<source>/images``."""

import math
import os

import numpy as np
import torch

from polargs_plugin.data.colmap import read_colmap_model
from polargs_plugin.data.imageio_utils import read_image
from scene.cameras import Camera
from scene.gaussian_model import GaussianModel  # noqa: F401  (the upstream module layout)


def _points(path):
    rows = [line.split() for line in open(path) if line.strip() and not line.startswith("#")]
    xyz = np.array([[float(v) for v in row[1:4]] for row in rows])
    rgb = np.array([[float(v) for v in row[4:7]] for row in rows]) / 255.0
    return xyz, rgb


class Scene:
    def __init__(self, args, gaussians):
        self.model_path = args.model_path
        self.gaussians = gaussians
        os.makedirs(self.model_path, exist_ok=True)
        model = os.path.join(args.source_path, "sparse", "0")
        self.train_cameras = []
        for uid, (name, cam) in enumerate(sorted(read_colmap_model(model).items())):
            image = torch.tensor(read_image(os.path.join(args.source_path, "images", name)), dtype=torch.float32)
            image = image.permute(2, 0, 1)[:3]
            fovx = 2 * math.atan(cam.width / (2 * cam.K[0, 0]))
            fovy = 2 * math.atan(cam.height / (2 * cam.K[1, 1]))
            R = cam.world_to_camera[:3, :3].T
            self.train_cameras.append(Camera(uid, R, cam.world_to_camera[:3, 3], fovx, fovy, image, os.path.splitext(name)[0]))
        centres = np.stack([c.camera_center.cpu().numpy() for c in self.train_cameras])
        self.cameras_extent = 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
        xyz, rgb = _points(os.path.join(model, "points3D.txt"))
        gaussians.create_from_pcd(xyz, rgb, self.cameras_extent)

    def getTrainCameras(self):
        return self.train_cameras

    def getTestCameras(self):
        return []

    def save(self, iteration):
        folder = os.path.join(self.model_path, "point_cloud", f"iteration_{iteration}")
        os.makedirs(folder, exist_ok=True)
        _write_ply(self.gaussians, os.path.join(folder, "point_cloud.ply"))


def _write_ply(gaussians, path):
    """The upstream PLY layout: x y z, nx ny nz, f_dc_*, f_rest_* (channel-major), opacity, scale_*, rot_*."""
    g = gaussians
    rest = g._features_rest.detach().transpose(1, 2).flatten(start_dim=1)
    columns = [g._xyz.detach(), torch.zeros_like(g._xyz), g._features_dc.detach()[:, 0], rest, g._opacity.detach(),
               g._scaling.detach(), g._rotation.detach()]
    values = torch.cat(columns, dim=1).cpu().numpy().astype("<f4")
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
             *[f"f_rest_{i}" for i in range(rest.shape[1])], "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(values)}",
              *[f"property float {name}" for name in names], "end_header"]
    with open(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode())
        handle.write(np.ascontiguousarray(values).tobytes())
