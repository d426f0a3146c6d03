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


def run_sfm(pictures: dict[str, np.ndarray] | Path, model_dir: str | os.PathLike,
            max_image_size: int | None = None) -> Path:
    """Structure from motion with pycolmap (the ``sfm`` extra) on 8-bit pictures.

    Args:
        pictures: {name: (H, W, 3) or (H, W, 1) uint8 RGB picture}, or a folder of such pictures
            as ``<name>.png``; all share one pinhole camera.
        model_dir: where the largest reconstruction is written as a text model.
        max_image_size: features are found on pictures scaled down to at most this width and
            height (the model is still for the pictures' own size); None: COLMAP's default.

    Returns:
        ``model_dir``.
    """
    model_dir = Path(model_dir)
    advice = (
        f"it needs at least {SFM_MIN_VIEWS} overlapping views of the object (textured surfaces, neighbouring "
        "views sharing most of what they see); add views, or give a COLMAP model in sparse/0"
    )
    count = len(pictures) if isinstance(pictures, dict) else len(list(Path(pictures).glob("*.png")))
    if count < SFM_MIN_VIEWS:
        raise PolarInputError(
            model_dir.parent.parent if model_dir.name == "0" else model_dir,
            f"SfM got {count} image(s) ({', '.join(sorted(_names(pictures))) or 'none'}); {advice}",
        )
    try:
        import pycolmap  # optional dependency, only needed here
    except ImportError:
        raise PolarInputError(
            model_dir, "SfM needs pycolmap (pip install 'polargs_plugin[sfm]'), or give a COLMAP model in sparse/0"
        ) from None

    options = {} if max_image_size is None else _extraction_options(pycolmap, int(max_image_size))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        images = tmp / "images" if isinstance(pictures, dict) else Path(pictures)
        if isinstance(pictures, dict):
            for name, picture in pictures.items():
                write_png(images / f"{name}.png", picture, 8)
        database = tmp / "database.db"
        pycolmap.extract_features(
            database,
            images,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=pycolmap.ImageReaderOptions(camera_model="SIMPLE_PINHOLE"),
            **options,
            device=pycolmap.Device.cpu,
        )
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        reconstructions = pycolmap.incremental_mapping(database, images, tmp / "sparse")
        best = max(reconstructions.values(), key=lambda r: r.num_reg_images()) if reconstructions else None
        registered = 0 if best is None else int(best.num_reg_images())
        if registered < SFM_MIN_VIEWS:
            raise PolarInputError(model_dir, f"SfM registered {registered} of {count} images; {advice}")
        staging = tmp / "model"
        staging.mkdir()
        best.write_text(str(staging))
        model_dir.parent.mkdir(parents=True, exist_ok=True)
        if model_dir.exists():
            raise PolarInputError(model_dir, "already exists; refusing to overwrite a COLMAP model")
        shutil.move(str(staging), str(model_dir))  # a whole directory appears at once
    return model_dir


def _names(pictures: dict[str, np.ndarray] | Path) -> list[str]:
    return list(pictures) if isinstance(pictures, dict) else [p.stem for p in Path(pictures).glob("*.png")]


def _extraction_options(pycolmap, max_image_size: int) -> dict:
    """``extract_features`` keyword arguments that cap the picture size (pycolmap >= 3.12 names
    them ``extraction_options``, older ones ``sift_options``)."""
    if hasattr(pycolmap, "FeatureExtractionOptions"):
        options = pycolmap.FeatureExtractionOptions()
        options.max_image_size = max_image_size
        return {"extraction_options": options}
    return {"sift_options": pycolmap.SiftExtractionOptions(max_image_size=max_image_size)}
