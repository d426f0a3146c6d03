"""Checks of a dataset's polarization conventions against its own images (``polargs check``).

Silhouette check (:func:`check_views`). At an occluding contour the surface normal is
perpendicular to the viewing ray, so its image projection is the outward normal of the mask
edge. Diffuse polarization is parallel to the projected normal (AoLP = edge-normal angle) and
specular polarization perpendicular to it (AoLP = edge-normal angle + 90 degrees). Along the
mask boundary (a band 1-3 pixels inside the mask, away from the image border) we take the
angle beta of the outward edge normal, counter-clockwise from image +x towards image up (the
package's AoLP convention, docs/conventions.md), and the AoLP A and DoLP rho of the
channel-mean Stokes, and form two DoLP-weighted circular means of the fourfold angle (fourfold
so that diffuse, 0, and specular, 90 degrees, count alike):

    z_ccw    = sum rho exp(4i (A - beta)) / sum rho      AoLP as the reader delivers it
    z_mirror = sum rho exp(4i (-A - beta)) / sum rho     AoLP mirrored (A -> c - A)

With the right convention |z_ccw| is large and its phase near 0 while z_mirror averages over
the contour's directions (exp(-8i beta)) to near 0; with a mirrored convention it is the other
way round. Verdicts: "consistent" (|z_ccw| >= |z_mirror| + margin and phase within
``max_offset_deg``), "rotated" (same but a constant offset, e.g. a rotated Stokes reference),
"mirrored" (|z_mirror| >= |z_ccw| + margin), "inconclusive" otherwise: too little polarization
along the edges, or edges only along directions where both hypotheses agree (multiples of 45
degrees, e.g. an axis-aligned box).

Also here: :func:`brightness_outliers` (views far brighter or darker than the others),
:func:`image_scale_ratio` (a dataset's 8-bit picture against its Stokes s0 / 2) and
:func:`orient_normal_map` (the frame of a dataset's GT normal maps, from the same silhouettes).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
import torch

from polargs_plugin.types import View

__all__ = [
    "VERDICTS",
    "SilhouetteStats",
    "CheckReport",
    "boundary_band",
    "silhouette_stats",
    "check_views",
    "brightness_outliers",
    "warn_brightness_outliers",
    "image_scale_ratio",
    "orient_normal_map",
]

VERDICTS = ("consistent", "rotated", "mirrored", "inconclusive")
MIN_DOLP = 0.02
"""Boundary pixels with a lower DoLP (noise level of 8-bit captures) are ignored."""
MIN_STRENGTH = 0.2
"""Below this |z| for both hypotheses the silhouettes say nothing."""
MARGIN = 0.15
"""One hypothesis must beat the other by this much."""
MAX_OFFSET_DEG = 10.0
"""Largest phase offset still called consistent."""


@dataclass
class SilhouetteStats:
    """Statistics of one view (or of all views pooled); see the module docstring.

    Attributes:
        name: view name, or "all".
        samples: boundary pixels used.
        weight: sum of their DoLP.
        strength: |z_ccw|; offset_deg: its phase / 4 in degrees (-45, 45].
        mirror_strength: |z_mirror|; mirror_offset_deg likewise.
        diffuse_fraction: DoLP-weighted share of pixels nearer the diffuse (0) than the specular
            (90 degree) relation under the delivered convention.
        verdict: one of :data:`VERDICTS`.
    """

    name: str
    samples: int
    weight: float
    strength: float
    offset_deg: float
    mirror_strength: float
    mirror_offset_deg: float
    diffuse_fraction: float
    verdict: str


@dataclass
class CheckReport:
    """Result of :func:`check_views`: the pooled verdict, per-view statistics and warnings."""

    verdict: str
    overall: SilhouetteStats
    views: list[SilhouetteStats] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "overall": asdict(self.overall), "views": [asdict(v) for v in self.views],
                "messages": list(self.messages)}


def boundary_band(mask: np.ndarray, inner_px: float = 3.0, border_px: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of the mask's boundary band and the outward edge normal there.

    Args:
        mask: (H, W) bool.
        inner_px: band width inside the mask, pixels.
        border_px: pixels this close to the image border are left out (a mask cut by the
            frame has no real edge there).

    Returns:
        (rows, cols, normals (M, 2) unit outward normals in image coordinates (x right, y down)).
    """
    mask = np.asarray(mask, dtype=bool)
    height, width = mask.shape
    if mask.all() or not mask.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    m8 = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m8, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 5)
    signed = cv2.GaussianBlur((outside - inside).astype(np.float32), (0, 0), 1.5)
    gy, gx = np.gradient(signed)
    band = mask & (inside <= inner_px)
    band[:border_px], band[-border_px:], band[:, :border_px], band[:, -border_px:] = False, False, False, False
    rows, cols = np.nonzero(band)
    normals = np.stack([gx[rows, cols], gy[rows, cols]], 1).astype(np.float64)
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-6
    return rows[ok], cols[ok], normals[ok] / length[ok, None]


def _circular(weights: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """(|mean|, phase / 4 in degrees) of the weighted mean of exp(4i angles)."""
    total = weights.sum()
    if not total > 0:
        return 0.0, 0.0
    z = (weights * np.exp(4j * angles)).sum() / total
    return float(abs(z)), float(np.degrees(np.angle(z)) / 4)


def _verdict(strength: float, offset: float, mirror: float, max_offset_deg: float = MAX_OFFSET_DEG) -> str:
    if max(strength, mirror) < MIN_STRENGTH:
        return "inconclusive"
    if strength >= mirror + MARGIN:
        return "consistent" if abs(offset) <= max_offset_deg else "rotated"
    if mirror >= strength + MARGIN:
        return "mirrored"
    return "inconclusive"


def _samples(view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(beta, AoLP, DoLP) at the usable boundary pixels of one view."""
    if view.mask is None:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    rows, cols, normals = boundary_band(view.mask[0].cpu().numpy())
    stokes = view.stokes.detach().cpu().double().mean(dim=1).numpy()  # (3, H, W) channel mean
    s0, s1, s2 = (plane[rows, cols] for plane in stokes)
    dolp = np.sqrt(s1**2 + s2**2) / np.maximum(s0, 1e-12)
    aolp = 0.5 * np.arctan2(s2, s1)
    beta = np.arctan2(-normals[:, 1], normals[:, 0])  # counter-clockwise, image up
    ok = (s0 > 1e-6) & (dolp >= MIN_DOLP) & np.isfinite(dolp)
    return beta[ok], aolp[ok], np.clip(dolp[ok], 0.0, 1.0)


def silhouette_stats(name: str, beta: np.ndarray, aolp: np.ndarray, dolp: np.ndarray) -> SilhouetteStats:
    """:class:`SilhouetteStats` of boundary samples (angles in radians)."""
    strength, offset = _circular(dolp, aolp - beta)
    mirror, mirror_offset = _circular(dolp, -aolp - beta)
    total = dolp.sum()
    diffuse = float((dolp * (np.cos(2 * (aolp - beta)) > 0)).sum() / total) if total > 0 else math.nan
    return SilhouetteStats(name, int(len(beta)), float(total), strength, offset, mirror, mirror_offset, diffuse,
                           _verdict(strength, offset, mirror))


def check_views(views: Sequence[View]) -> CheckReport:
    """Silhouette check of the AoLP convention of ``views`` (module docstring).

    Views without a mask are skipped. The verdict pools every view's samples; views whose own
    verdict disagrees with it are listed in ``messages``.
    """
    per_view, pooled = [], ([], [], [])
    for view in views:
        beta, aolp, dolp = _samples(view)
        if len(beta) == 0:
            continue
        per_view.append(silhouette_stats(view.name, beta, aolp, dolp))
        for store, values in zip(pooled, (beta, aolp, dolp)):
            store.append(values)
    messages = []
    if not per_view:
        overall = SilhouetteStats("all", 0, 0.0, 0.0, 0.0, 0.0, 0.0, math.nan, "inconclusive")
        messages.append("no view has a mask with polarized boundary pixels; nothing to check")
        return CheckReport("inconclusive", overall, [], messages)
    overall = silhouette_stats("all", *(np.concatenate(store) for store in pooled))
    if overall.verdict == "mirrored":
        messages.append(
            f"AoLP looks mirrored: along the silhouettes it matches -AoLP (strength {overall.mirror_strength:.2f}) "
            f"rather than the AoLP (strength {overall.strength:.2f}); the reader's AoLP direction is probably "
            "clockwise where counter-clockwise is expected (docs/readers.md)")
    elif overall.verdict == "rotated":
        messages.append(f"AoLP is offset by {overall.offset_deg:+.1f} degrees along the silhouettes (rotated Stokes reference?)")
    elif overall.verdict == "inconclusive":
        messages.append(f"inconclusive: strength {overall.strength:.2f} (as delivered) vs {overall.mirror_strength:.2f} "
                        "(mirrored); too little polarization along the silhouettes, or edges only at multiples of 45 degrees")
    odd = [s.name for s in per_view if s.verdict not in (overall.verdict, "inconclusive")]
    if odd:
        messages.append(f"{len(odd)} view(s) disagree with the pooled verdict: {', '.join(odd[:10])}")
    return CheckReport(overall.verdict, overall, per_view, messages)


# ---------------------------------------------------------------------------------------------
# Brightness of the views against each other.

BRIGHTNESS_FACTOR = 4.0
"""A view whose mean s0 is this many times above or below the median view's is named in a warning."""


def brightness_outliers(views: Sequence[View], factor: float = BRIGHTNESS_FACTOR) -> list[tuple[str, float]]:
    """Views whose mean brightness (s0 over every pixel and channel) is ``factor`` or more times
    above or below that of the median view, as (name, mean / median mean).

    Views of one scene taken with one camera differ in brightness by what they see (the bundled
    scenes by less than a factor 2); a factor of 4 or more points to a reading error instead: a
    wrong bit depth (8-bit values in a 16-bit file read 257 times too dark), another exposure,
    a broken file. Fewer than 3 views have no median to compare with: none is named.
    """
    if len(views) < 3:
        return []
    means = [float(view.stokes[0].detach().double().mean()) for view in views]
    median = float(np.median(means))
    if not median > 0:
        return []
    return [(view.name, mean / median) for view, mean in zip(views, means)
            if mean >= factor * median or mean * factor <= median]


def warn_brightness_outliers(views: Sequence[View], source: str, factor: float = BRIGHTNESS_FACTOR) -> list[tuple[str, float]]:
    """:func:`brightness_outliers`, with a warning naming them (``source``: the dataset)."""
    outliers = brightness_outliers(views, factor)
    if outliers:
        named = ", ".join(f"'{name}' ({ratio:.3g} times brighter)" if ratio > 1 else f"'{name}' ({1 / ratio:.3g} times darker)"
                          for name, ratio in outliers[:5]) + (", ..." if len(outliers) > 5 else "")
        warnings.warn(f"{source}: {len(outliers)} of {len(views)} views differ from the median view's brightness by a "
                      f"factor of {factor:g} or more: {named}; a wrong bit depth, another exposure or a broken file?",
                      stacklevel=2)
    return outliers


# ---------------------------------------------------------------------------------------------
# 8-bit picture against the Stokes.


def _srgb_to_linear(values: np.ndarray) -> np.ndarray:
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


ENCODINGS = {
    "srgb": _srgb_to_linear,
    "gamma2.2": lambda v: v**2.2,
    "linear": lambda v: v,
}


def image_scale_ratio(stokes: np.ndarray | torch.Tensor, image: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """How an 8-bit picture of a view relates to its training colour s0 / 2.

    Each decoding of :data:`ENCODINGS` is tried; the picture's linear value divided by s0 / 2 at
    well-exposed pixels (codes 8..247, inside ``mask``) should be a constant k. The decoding with
    the least spread of log k wins. k = 1 means the Stokes scale matches the picture; k = 2 would
    mean the stored s0 is half the intensity the picture shows (factor 2 missing), k = 0.5 that
    it is twice (a loader factor 0.5 needed).

    Args:
        stokes: (3, C, H, W) Stokes as read (s0 = full intensity under the reader's factor).
        image: (H, W, C) or (H, W) uint8 picture, RGB.
        mask: optional (H, W) bool.

    Returns:
        dict ``ratio`` (k), ``encoding``, ``spread`` (median absolute deviation of log2 k),
        ``pixels``; ``ratio`` is NaN when fewer than 50 pixels are usable.
    """
    s0 = torch.as_tensor(stokes)[0].double().cpu().numpy()  # (C, H, W)
    picture = np.asarray(image)
    if picture.ndim == 2:
        picture = picture[..., None]
    picture = picture.transpose(2, 0, 1).astype(np.float64)
    channels = min(picture.shape[0], s0.shape[0])
    picture, s0 = picture[:channels], s0[:channels]
    if picture.shape[1:] != s0.shape[1:]:
        raise ValueError(f"picture {picture.shape[1:]} and Stokes {s0.shape[1:]} differ in size")
    valid = (picture >= 8) & (picture <= 247) & (s0 > 1e-6)
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)[None]
    best = {"ratio": math.nan, "encoding": None, "spread": math.nan, "pixels": int(valid.sum())}
    if valid.sum() < 50:
        return best
    for name, decode in ENCODINGS.items():
        log_ratio = np.log2(decode(picture[valid] / 255.0) / (s0[valid] / 2))
        median = float(np.median(log_ratio))
        spread = float(np.median(np.abs(log_ratio - median)))
        if not spread >= best["spread"]:  # NaN-safe: the first one always wins
            best.update(ratio=float(2**median), encoding=name, spread=spread)
    return best


def warn_image_scale(source: str, stokes, image, mask=None, tolerance: float = 1.25, stacklevel: int = 2) -> dict:
    """:func:`image_scale_ratio` plus a warning when k is outside [1/tolerance, tolerance].

    ``stacklevel`` places the warning as ``warnings.warn(..., stacklevel)`` called by the caller
    of this function would (2: the caller's caller, e.g. the code that called a reader).
    """
    result = image_scale_ratio(stokes, image, mask)
    k = result["ratio"]
    if np.isfinite(k) and not (1 / tolerance <= k <= tolerance):
        warnings.warn(
            f"{source}: the 8-bit picture is {k:.3g} x s0/2 ({result['encoding']} decoding, {result['pixels']} pixels); "
            f"the Stokes scale of this reader may be off by that factor (docs/readers.md)",
            stacklevel=stacklevel + 1,
        )
    return result


# ---------------------------------------------------------------------------------------------
# GT normal maps: which frame?

NORMAL_FRAMES = ("opencv", "opengl", "world")


def orient_normal_map(normal: np.ndarray, mask: np.ndarray, world_to_camera: np.ndarray) -> tuple[np.ndarray, str, float]:
    """Bring a GT normal map into the OpenCV camera frame, telling its frame from the silhouette.

    Candidates: OpenCV camera (x right, y down, z forward), OpenGL / Blender camera (x right,
    y up, z backward: (x, -y, -z)), world (rotated by ``world_to_camera``). At the mask edge
    the true normal's image projection points outwards; the candidate whose (n_x, n_y) agrees
    best (mean cosine, the score) wins.

    Args:
        normal: (3, H, W) float normals as stored (any length; zero outside the object).
        mask: (H, W) bool.
        world_to_camera: (4, 4).

    Returns:
        (normals (3, H, W) float32 unit OpenCV camera frame, 0 outside ``mask``, frame, score).
    """
    normal = np.asarray(normal, dtype=np.float64)
    rotation = np.asarray(world_to_camera, dtype=np.float64)[:3, :3]
    candidates = {
        "opencv": normal,
        "opengl": normal * np.array([1.0, -1.0, -1.0])[:, None, None],
        "world": np.einsum("ij,jhw->ihw", rotation, normal),
    }
    rows, cols, outward = boundary_band(mask)
    scores = {}
    for name, n in candidates.items():
        xy = n[:2, rows, cols].T
        length = np.linalg.norm(xy, axis=1)
        ok = length > 1e-6
        scores[name] = float((np.einsum("ij,ij->i", xy[ok], outward[ok]) / length[ok]).mean()) if ok.any() else -1.0
    frame = max(scores, key=scores.get)
    out = candidates[frame]
    out = out / np.maximum(np.linalg.norm(out, axis=0, keepdims=True), 1e-12)
    out = np.where(np.asarray(mask, dtype=bool)[None], out, 0.0)
    return out.astype(np.float32), frame, scores[frame]
