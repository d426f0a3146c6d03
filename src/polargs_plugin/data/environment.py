"""Image-based lighting for the synthetic generator: surroundings fixed in the world, infinitely far.

An :class:`Environment` gives the radiance arriving along every world direction: a sky that runs
from a horizon colour to a zenith colour, a ground below the horizon, a texture over directions
(the surroundings' detail, what a mirror shows moving with the view) and bright discs
(:class:`Softbox`: windows, softboxes, the sun behind a diffuser) that may saturate the sensor.
Radiance is in training-colour units (s0 / 2): a white Lambertian surface lit from every side by
a constant environment of radiance L has colour L.

The renderer (:mod:`polargs_plugin.data.synthetic`) integrates it two ways:

- the diffuse irradiance by a fixed quadrature over the sphere (:func:`sphere_directions`, the
  same directions for every point, so the result is consistent between views) plus each softbox
  as a small area light at its centre;
- the specular reflection by a fixed set of directions inside the material's lobe around the
  mirror direction (:func:`lobe_directions`), plus each softbox convolved with the lobe in closed
  form (both Gaussian in angle), so that neither flickers as the view moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from polargs_plugin.data.textures import Texture, pattern_at

__all__ = ["Softbox", "Environment", "sphere_directions", "lobe_directions", "lobe_width"]

#: Lobe exponent from which a material reflects as a mirror (lobe narrower than about 1.5 deg).
MIRROR_SHININESS = 3000.0


@dataclass(frozen=True)
class Softbox:
    """A bright disc of the surroundings (a window, a softbox), fixed in the world.

    Attributes:
        direction: (3,) unit world direction from the scene towards the disc's centre.
        radius_deg: angular radius of the disc (degrees, in (0, 45]).
        color: (3,) RGB radiance of the disc (training-colour units; above about 1 / (k_s F) its
            reflection clips).
    """

    direction: tuple[float, float, float]
    radius_deg: float
    color: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not 0 < self.radius_deg <= 45:
            raise ValueError(f"softbox radius_deg must be in (0, 45], got {self.radius_deg}")
        if not abs(float(np.linalg.norm(self.direction)) - 1.0) < 1e-6:
            raise ValueError(f"softbox direction must be a unit vector, got {self.direction}")

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(N, 3) the disc's radiance along unit ``directions`` (N, 3); its edge is half a degree soft."""
        angle = np.arccos(np.clip(directions @ np.asarray(self.direction), -1.0, 1.0))
        inside = np.clip((math.radians(self.radius_deg) - angle) / math.radians(0.5) + 0.5, 0.0, 1.0)
        return inside[:, None] * np.asarray(self.color)

    @property
    def solid_angle(self) -> float:
        """The disc's solid angle (sr)."""
        return 2 * math.pi * (1 - math.cos(math.radians(self.radius_deg)))

    @property
    def angular_variance(self) -> float:
        """Variance (rad^2) of the angle from the centre over the disc, per axis: r^2 / 4."""
        return math.radians(self.radius_deg) ** 2 / 4


@dataclass(frozen=True)
class Environment:
    """Radiance arriving from infinitely far along each world direction (z up).

    Attributes:
        zenith: (3,) RGB sky radiance straight up.
        horizon: (3,) RGB sky radiance at the horizon (a coloured horizon gives coloured rims).
        ground: (3,) RGB radiance from below the horizon (where no floor of the scene hides it).
        texture_amplitude: relative modulation of sky and ground by a smooth noise over
            directions, in [0, 1).
        texture_scale: angular size of that noise's features (radians, > 0).
        softboxes: the bright discs.
        samples: directions of the diffuse-irradiance quadrature over the sphere (>= 16).
    """

    zenith: tuple[float, float, float] = (0.35, 0.45, 0.6)
    horizon: tuple[float, float, float] = (0.6, 0.6, 0.55)
    ground: tuple[float, float, float] = (0.15, 0.13, 0.1)
    texture_amplitude: float = 0.3
    texture_scale: float = 0.35
    softboxes: tuple[Softbox, ...] = field(default_factory=tuple)
    samples: int = 128

    def __post_init__(self) -> None:
        if not 0 <= self.texture_amplitude < 1:
            raise ValueError(f"environment texture_amplitude must be in [0, 1), got {self.texture_amplitude}")
        if not self.texture_scale > 0:
            raise ValueError(f"environment texture_scale must be > 0, got {self.texture_scale}")
        if self.samples < 16:
            raise ValueError(f"environment samples must be >= 16, got {self.samples}")
        for name in ("zenith", "horizon", "ground"):
            if min(getattr(self, name)) < 0:
                raise ValueError(f"environment {name} radiance must be >= 0, got {getattr(self, name)}")

    def background(self, directions: np.ndarray) -> np.ndarray:
        """(N, 3) radiance of sky, ground and texture along unit ``directions`` (N, 3), no softbox."""
        z = np.clip(directions[:, 2], -1.0, 1.0)
        up = np.sqrt(np.clip(z, 0.0, None))[:, None]
        sky = (1 - up) * np.asarray(self.horizon) + up * np.asarray(self.zenith)
        # A soft horizon (about 3 deg) keeps the sky-ground edge from aliasing in reflections.
        blend = np.clip(0.5 + z / 0.1, 0.0, 1.0)[:, None]
        colour = blend * sky + (1 - blend) * np.asarray(self.ground)
        if self.texture_amplitude > 0:
            noise = pattern_at(directions, Texture("speckle", self.texture_scale, 1.0))
            colour = colour * (1 + self.texture_amplitude * np.clip(noise, -1.0, 1.0))[:, None]
        return colour

    def softbox_radiance(self, directions: np.ndarray) -> np.ndarray:
        """(N, 3) radiance of all the softboxes along unit ``directions`` (N, 3)."""
        return sum((box.radiance(directions) for box in self.softboxes), np.zeros((directions.shape[0], 3)))

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(N, 3) radiance along unit ``directions`` (N, 3): what a camera sees there."""
        return self.background(directions) + self.softbox_radiance(directions)

    def mean_radiance(self) -> np.ndarray:
        """(3,) radiance averaged over the sphere, softboxes included (what an interreflection sees)."""
        dirs = sphere_directions(self.samples)
        boxes = sum((b.solid_angle * np.asarray(b.color) for b in self.softboxes), np.zeros(3))
        return self.background(dirs).mean(axis=0) + boxes / (4 * math.pi)


def sphere_directions(count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the sphere (a Fibonacci lattice), fixed.

    >>> d = sphere_directions(256)
    >>> bool(np.allclose(np.linalg.norm(d, axis=1), 1.0)), bool(np.abs(d.mean(axis=0)).max() < 0.01)
    (True, True)
    """
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    azimuth = math.pi * (1 + math.sqrt(5)) * k
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def lobe_width(shininess: float | np.ndarray) -> np.ndarray:
    """Angular standard deviation (rad, per axis) of a lobe cos^s around its axis: about 1 / sqrt(s + 1)."""
    return 1.0 / np.sqrt(np.asarray(shininess, dtype=np.float64) + 1.0)


def lobe_directions(axes: np.ndarray, shininess: np.ndarray, count: int) -> np.ndarray:
    """(N, count, 3) unit directions distributed as the lobe cos^s(angle to the axis).

    A fixed stratified pattern (the same for every axis, turned with it by a frame that varies
    smoothly with the axis), so that neighbouring pixels and views average nearly the same
    directions: the reflection does not sparkle. A lobe of exponent :data:`MIRROR_SHININESS` or
    more collapses onto its axis.

    Args:
        axes: (N, 3) unit lobe axes (mirror directions).
        shininess: (N,) lobe exponents s > 0.
        count: directions per lobe.
    """
    k = np.arange(count) + 0.5
    u = k / count  # stratified in cos^(s+1), the lobe's cumulative share
    spin = math.pi * (3 - math.sqrt(5)) * np.arange(count)  # golden-angle turns
    s = np.asarray(shininess, dtype=np.float64)[:, None]
    cos_a = np.where(s >= MIRROR_SHININESS, 1.0, u[None, :] ** (1.0 / (s + 1.0)))
    sin_a = np.sqrt(np.clip(1 - cos_a**2, 0.0, None))
    # A frame around each axis: the tangent from the world axis least aligned with it.
    helper = np.where(np.abs(axes[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    tangent = np.cross(helper, axes)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bitangent = np.cross(axes, tangent)
    return (cos_a[..., None] * axes[:, None, :]
            + (sin_a * np.cos(spin))[..., None] * tangent[:, None, :]
            + (sin_a * np.sin(spin))[..., None] * bitangent[:, None, :])
