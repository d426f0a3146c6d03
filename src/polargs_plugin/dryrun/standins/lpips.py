"""Stand-in for ``torchmetrics.image.lpip`` in a dry run: ``LearnedPerceptualImagePatchSimilarity``
needs pretrained network weights, which torchmetrics downloads on first use; a dry run neither
has them nor evaluates (the trainer's evaluation steps lie after the run). The stand-in builds
without weights and refuses to be called."""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

__all__ = ["LearnedPerceptualImagePatchSimilarity"]


class LearnedPerceptualImagePatchSimilarity(nn.Module):
    """torchmetrics' LPIPS metric without its network: constructing it works, computing it raises."""

    def __init__(self, net_type: str = "alex", reduction: str = "mean", normalize: bool = False, **kwargs: Any) -> None:
        super().__init__()
        self.net_type = net_type

    def forward(self, img1: Tensor, img2: Tensor) -> Tensor:
        raise RuntimeError("LPIPS is not available in a dry run (no pretrained weights): keep the trainer's "
                           "evaluation steps after the run")
