"""Stand-in for ``simple_knn._C``: ``distCUDA2(points)``, the mean squared distance of each point
to its three nearest other points ((N,) float32), which the graphdeco-family ``create_from_pcd``
turns into each Gaussian's initial scale. Exact nearest neighbours (a k-d tree); the CUDA
version searches approximately, inside Morton-code boxes."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["distCUDA2"]


def distCUDA2(points: Tensor) -> Tensor:  # noqa: N802 (the upstream name)
    """(N,) mean squared distance to the 3 nearest other points (fewer when N < 4; 0 for N = 1)."""
    xyz = points.detach().cpu().double().numpy()
    k = min(4, xyz.shape[0])
    if k < 2:
        return torch.zeros(xyz.shape[0], dtype=torch.float32, device=points.device)
    distances, _ = cKDTree(xyz).query(xyz, k=k)
    mean_sq = np.mean(np.square(distances[:, 1:]), axis=1)
    return torch.from_numpy(mean_sq).float().to(points.device)
