"""Procedural textures of the synthetic generator: patterns over 3D points (or directions).

A pattern is a function of the world point, so a texture looks the same from every view; the
environment (:mod:`polargs_plugin.data.environment`) evaluates it over directions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Texture", "pattern_at"]


@dataclass(frozen=True)
class Texture:
    """Procedural albedo modulation evaluated at the 3D hit point (so it is multi-view consistent).

    Attributes:
        kind: ``"uniform"`` (textureless), ``"checker"`` (3D checkerboard of cell ``scale``),
            ``"noise"`` (sum of fixed 3D sinusoids with wavelength about ``scale``) or
            ``"speckle"`` (3D value noise of cell ``scale`` plus two finer octaves: irregular blobs
            with corners at several scales, what feature matchers such as SfM's need).
        scale: spatial period in world units.
        amplitude: relative albedo variation in [0, 1]; albedo * (1 + amplitude * pattern), with
            pattern in [-1, 1].
    """

    kind: str = "uniform"
    scale: float = 0.25
    amplitude: float = 0.0


# ---------------------------------------------------------------------------------------------
# Procedural texture.

# Fixed wave vectors (cycles per wavelength) and phases of the "noise" pattern; fixed so that the
# texture never depends on the noise seed.
_WAVES = np.array(
    [[1.0, 0.31, -0.52], [-0.27, 0.93, 0.41], [0.48, -0.36, 0.88], [0.77, 0.69, -0.14], [-0.62, 0.18, 0.71]]
)
_PHASES = np.array([0.3, 1.7, 4.1, 2.6, 5.2])


# Odd multipliers of the lattice hash of the "speckle" pattern (large primes, as in spatial hashing).
_HASH = np.array([73856093, 19349663, 83492791], dtype=np.int64)
_SPECKLE_OCTAVES = 3


def _lattice_values(cells: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random value in [-1, 1) for each integer lattice point (..., 3)."""
    h = np.bitwise_xor.reduce(cells * _HASH, axis=-1) & 0xFFFFFFFF
    h = (h * 2654435761) & 0xFFFFFFFF  # Knuth's multiplicative mix spreads nearby cells apart
    h ^= h >> 15
    return h.astype(np.float64) / 2**31 - 1.0


def _value_noise(points: np.ndarray, scale: float) -> np.ndarray:
    """(N,) trilinearly interpolated lattice values of cell ``scale`` with a smoothstep fade."""
    grid = points / scale
    base = np.floor(grid)
    t = grid - base
    t = t * t * (3.0 - 2.0 * t)
    cells = base.astype(np.int64)
    total = np.zeros(points.shape[0])
    for corner in np.ndindex(2, 2, 2):
        offset = np.array(corner)
        weight = np.prod(np.where(offset == 1, t, 1.0 - t), axis=1)
        total += weight * _lattice_values(cells + offset)
    return total


def pattern_at(points: np.ndarray, texture: Texture) -> np.ndarray:
    """(N,) pattern in [-1, 1] at world points (N, 3)."""
    if texture.kind == "uniform":
        return np.zeros(points.shape[0])
    if texture.kind == "checker":
        # A surface lying on a cell boundary (a floor at height 0) gets hit points a rounding error
        # above or below it; the small shift puts them all in one cell, so its parity does not
        # flicker from pixel to pixel and from view to view.
        cells = np.floor(points / texture.scale + 1e-4).astype(np.int64).sum(axis=1)
        return np.where(cells % 2 == 0, 1.0, -1.0)
    if texture.kind == "noise":
        waves = 2 * np.pi * _WAVES / texture.scale
        return np.sin(points @ waves.T + _PHASES).mean(axis=1) * (5 / 3)  # roughly unit range
    if texture.kind == "speckle":
        octaves = [0.5**k * _value_noise(points, texture.scale * 0.5**k) for k in range(_SPECKLE_OCTAVES)]
        return np.sum(octaves, axis=0)  # std about 0.45; evaluate_albedo clips the rare |values| > 1
    raise ValueError(f"unknown texture kind {texture.kind!r}")
