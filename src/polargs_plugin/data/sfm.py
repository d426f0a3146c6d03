"""Structure from motion for a capture folder without a COLMAP model (the ``sfm`` extra, pycolmap)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from polargs_plugin.data.imageio_utils import write_png
from polargs_plugin.io import PolarInputError

__all__ = ["SFM_MIN_VIEWS", "run_sfm"]

SFM_MIN_VIEWS = 3
"""Fewest overlapping views SfM can build a model from (two to initialise, one more to check it)."""


def run_sfm(pictures: dict[str, np.ndarray], model_dir: str | os.PathLike) -> Path:
    """Structure from motion with pycolmap (the ``sfm`` extra) on 8-bit pictures.

    Args:
        pictures: {name: (H, W, 3) or (H, W, 1) uint8 RGB picture}; all share one pinhole camera.
        model_dir: where the largest reconstruction is written as a text model.

    Returns:
        ``model_dir``.
    """
    model_dir = Path(model_dir)
    advice = (
        f"it needs at least {SFM_MIN_VIEWS} overlapping views of the object (textured surfaces, neighbouring "
        "views sharing most of what they see); add views, or give a COLMAP model in sparse/0"
    )
    if len(pictures) < SFM_MIN_VIEWS:
        raise PolarInputError(
            model_dir.parent.parent if model_dir.name == "0" else model_dir,
            f"SfM got {len(pictures)} image(s) ({', '.join(sorted(pictures)) or 'none'}); {advice}",
        )
    try:
        import pycolmap  # optional dependency, only needed here
    except ImportError:
        raise PolarInputError(
            model_dir, "SfM needs pycolmap (pip install 'polargs_plugin[sfm]'), or give a COLMAP model in sparse/0"
        ) from None

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, picture in pictures.items():
            write_png(tmp / "images" / f"{name}.png", picture, 8)
        database = tmp / "database.db"
        pycolmap.extract_features(
            database,
            tmp / "images",
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=pycolmap.ImageReaderOptions(camera_model="SIMPLE_PINHOLE"),
            device=pycolmap.Device.cpu,
        )
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        reconstructions = pycolmap.incremental_mapping(database, tmp / "images", tmp / "sparse")
        best = max(reconstructions.values(), key=lambda r: r.num_reg_images()) if reconstructions else None
        registered = 0 if best is None else int(best.num_reg_images())
        if registered < SFM_MIN_VIEWS:
            raise PolarInputError(model_dir, f"SfM registered {registered} of {len(pictures)} images; {advice}")
        staging = tmp / "model"
        staging.mkdir()
        best.write_text(str(staging))
        model_dir.parent.mkdir(parents=True, exist_ok=True)
        if model_dir.exists():
            raise PolarInputError(model_dir, "already exists; refusing to overwrite a COLMAP model")
        shutil.move(str(staging), str(model_dir))  # a whole directory appears at once
    return model_dir
