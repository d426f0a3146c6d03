"""What a run is trained on: a per-view fingerprint of cameras and image content, and its check."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from polargs_plugin.io import PolarInputError

if TYPE_CHECKING:
    from polargs_plugin.types import View

__all__ = ["FINGERPRINT_FORMAT", "fingerprint", "compare_fingerprints", "read_fingerprint"]

FINGERPRINT_FORMAT = "polargs-data-fingerprint-v1"
# Cameras must agree to this relative tolerance, the 8x8 thumbnails of s0 to this one.
_CAMERA_TOLERANCE = 1e-6
_THUMBNAIL_TOLERANCE = 1e-3
_LISTED = 5  # names listed in a message before "..."


def fingerprint(views: Sequence[View]) -> dict[str, Any]:
    """What a run is trained on, per view: name, size, camera (K, world_to_camera) and image
    content (SHA-256 of the Stokes and mask, and an 8x8 thumbnail of s0 for a tolerant check).

    Returns:
        ``{"format": FINGERPRINT_FORMAT, "views": [...]}``, plain JSON data.
    """
    import torch.nn.functional as F

    from polargs_plugin.types import content_digest

    entries = []
    for view in views:
        s0 = view.stokes[0].detach().cpu().float()
        thumb = F.adaptive_avg_pool2d(s0.mean(0, keepdim=True)[None], (8, 8))[0, 0]
        entries.append({
            "name": view.name,
            "size": [int(view.width), int(view.height)],
            "K": view.K.detach().cpu().double().reshape(-1).tolist(),
            "world_to_camera": view.world_to_camera.detach().cpu().double().reshape(-1).tolist(),
            "image_sha256": content_digest(view),
            "thumbnail": [round(float(v), 6) for v in thumb.reshape(-1)],
        })
    return {"format": FINGERPRINT_FORMAT, "views": entries}


def _names(names: list, total: int | None = None) -> str:
    total = len(names) if total is None else total
    return ", ".join(map(str, names[:_LISTED])) + (", ..." if total > _LISTED else "")


def _close(a: list, b: list, tolerance: float) -> bool:
    if len(a) != len(b):
        return False
    scale = max([abs(x) for x in a + b] + [1e-12])
    return all(abs(x - y) <= tolerance * scale for x, y in zip(a, b))


def compare_fingerprints(stored: dict[str, Any], current: dict[str, Any]) -> str | None:
    """None when ``current`` is the data of ``stored`` (tolerant to float noise), else the problem
    in one sentence (which views' cameras or images differ)."""
    old, new = stored.get("views", []), current["views"]
    old_names, new_names = [v.get("name") for v in old], [v["name"] for v in new]
    if old_names != new_names:
        return (
            f"this run was trained on {len(old_names)} views ({_names(old_names)}), "
            f"the dataset has {len(new_names)} ({_names(new_names)})"
        )
    cameras, images = [], []
    for a, b in zip(old, new):
        if a.get("size") != b["size"] or not _close(a.get("K", []), b["K"], _CAMERA_TOLERANCE) or not _close(
            a.get("world_to_camera", []), b["world_to_camera"], _CAMERA_TOLERANCE
        ):
            cameras.append(b["name"])
        if a.get("image_sha256") != b["image_sha256"] and not _close(a.get("thumbnail", []), b["thumbnail"], _THUMBNAIL_TOLERANCE):
            images.append(b["name"])
    if not cameras and not images:
        return None
    parts = [f"the {what} of {len(names)} of {len(new)} views ({_names(names)})"
             for what, names in (("cameras", cameras), ("images", images)) if names]
    return " and ".join(parts) + " differ from those this run was trained on"


def read_fingerprint(path: Path) -> dict[str, Any] | None:
    """A run's ``fingerprint.json``; None when it is missing (a run from before fingerprints).

    Raises:
        PolarInputError: naming the file when it cannot be read as a fingerprint.
    """
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise PolarInputError(path, f"unreadable ({err}); delete it to go on without the data check") from None
    if not isinstance(stored, dict) or not isinstance(stored.get("views"), list):
        raise PolarInputError(path, "not a data fingerprint; delete it to go on without the data check")
    return stored
