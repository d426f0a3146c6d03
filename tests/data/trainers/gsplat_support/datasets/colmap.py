"""Placeholder Parser / Dataset: reads ``<data_dir>/sparse/0`` (COLMAP) and ``<data_dir>/images``."""

import os

import numpy as np
import torch

from polargs_plugin.data.colmap import read_colmap_model
from polargs_plugin.data.imageio_utils import read_image


class Parser:
    def __init__(self, data_dir, factor=1, normalize=False, test_every=8):
        model = os.path.join(data_dir, "sparse", "0")
        cameras = sorted(read_colmap_model(model).items())
        self.data_dir = data_dir
        self.image_names = [name for name, _ in cameras]
        self.image_paths = [os.path.join(data_dir, "images", name) for name in self.image_names]
        self.camera_ids = list(range(1, len(cameras) + 1))
        self.camtoworlds = np.stack([np.linalg.inv(cam.world_to_camera) for _, cam in cameras])
        self.Ks_dict = {i: cam.K for i, (_, cam) in zip(self.camera_ids, cameras)}
        self.imsize_dict = {i: (cam.width, cam.height) for i, (_, cam) in zip(self.camera_ids, cameras)}
        rows = [line.split() for line in open(os.path.join(model, "points3D.txt")) if line.strip() and not line.startswith("#")]
        self.points = np.array([[float(v) for v in row[1:4]] for row in rows], dtype=np.float32)
        self.points_rgb = np.array([[int(v) for v in row[4:7]] for row in rows], dtype=np.uint8)
        centres = self.camtoworlds[:, :3, 3]
        self.scene_scale = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
        self.test_every = test_every


class Dataset:
    def __init__(self, parser, split="train"):
        self.parser = parser
        self.indices = np.arange(len(parser.image_names))

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, item):
        index = self.indices[item]
        camera_id = self.parser.camera_ids[index]
        image = read_image(self.parser.image_paths[index])[..., :3]
        return {
            "K": torch.from_numpy(self.parser.Ks_dict[camera_id]).float(),
            "camtoworld": torch.from_numpy(self.parser.camtoworlds[index]).float(),
            "image": torch.from_numpy(image.astype(np.float32)),
            "image_id": item,
        }
