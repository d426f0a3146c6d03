"""Placeholder camera with the upstream attributes (R = world-to-camera rotation transposed, T,
FoVs, the transposed 4x4 matrices, ``camera_center``, ``original_image``)."""

import math

import numpy as np
import torch


def _projection(znear, zfar, fovx, fovy):
    """Transposed symmetric perspective matrix (NDC z in 0..1), row-vector convention."""
    tx, ty = math.tan(fovx / 2), math.tan(fovy / 2)
    P = torch.zeros(4, 4)
    P[0, 0], P[1, 1] = 1 / tx, 1 / ty
    P[3, 2], P[2, 2], P[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
    return P.T


class Camera:
    def __init__(self, uid, R, T, FoVx, FoVy, image, image_name):
        self.uid, self.R, self.T, self.FoVx, self.FoVy = uid, R, T, FoVx, FoVy
        self.image_name = image_name
        self.original_image = image.clamp(0, 1).to("cuda")
        self.image_height, self.image_width = image.shape[1], image.shape[2]
        self.depth_reliable, self.invdepthmap = False, None
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R.T, T
        self.world_view_transform = torch.tensor(w2c, dtype=torch.float32).T.cuda()
        self.projection_matrix = _projection(0.01, 100.0, FoVx, FoVy).cuda()
        self.full_proj_transform = self.world_view_transform @ self.projection_matrix
        self.camera_center = torch.linalg.inv(self.world_view_transform)[3, :3]
