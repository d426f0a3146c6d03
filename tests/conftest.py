"""Shared test set-up: single-threaded torch per pytest worker, deterministic seeds, synthetic
scenes generated once per worker (tests/scene_cache.py)."""

import os

import numpy as np
import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture(scope="session")
def synthetic_scene():
    """``synthetic_scene(name, num_views=..., width=..., height=..., **options)``: the scene
    ``generate_scene`` makes of these arguments, generated once per worker process and handed
    out as a deep copy on every call, so a test may change it in place (tests/scene_cache.py)."""
    import scene_cache

    return scene_cache.scene


@pytest.fixture(scope="session")
def synthetic_views():
    """``synthetic_views(name, ...)``: the views of ``synthetic_scene(name, ...)`` (a fresh copy)."""
    import scene_cache

    return scene_cache.views
