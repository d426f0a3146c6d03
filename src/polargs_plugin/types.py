"""The data contracts shared by every module (docs/conventions.md).

Conventions, binding everywhere:

- Camera frame OpenCV (x right, y down, z forward). ``K`` is 3x3 with pixel centres at +0.5:
  pixel (u, v) (column u, row v) has its centre at (u + 0.5, v + 0.5).
  ``world_to_camera`` is a 4x4 (not transposed): x_cam = R @ x_world + t.
- Images are float32, channel-first (C, H, W), linear, in [0, 1], RGB order.
- A :class:`View` stores its images compactly (:mod:`polargs_plugin.compact`: 8/16-bit angle
  images, float16, bool masks) and decodes them on each read of ``view.stokes``,
  ``view.normal_gt``, ``view.depth_gt``: the decoded tensors have the shapes and dtypes above,
  and a caller keeps them only while it uses them.
- Stokes are (3, C, H, W) = (s0, s1, s2); s0 = (I0 + I45 + I90 + I135) / 2 is the full intensity,
  s1 = I0 - I90, s2 = I45 - I135. The training colour is s0 / 2.
- Depth is camera z (not ray length). Normals are unit camera-frame vectors facing the camera
  (n . z < 0).
- Cameras are float64 so that readers round-trip them to 1e-6; cast when rendering.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable, Protocol, runtime_checkable

import torch
from torch import Tensor

from polargs_plugin.compact import Stored, as_stored
from polargs_plugin.io import PolarInputError

__all__ = [
    "View", "PolarMaps", "RenderOut", "GaussianState", "NewGaussians", "TrainingHooks", "RenderFn",
    "describe_view", "validate_view", "content_digest",
]


class _StoredField:
    """A :class:`View` image field: kept as a stored form (:mod:`polargs_plugin.compact`), decoded
    to a fresh full-precision tensor on every read; assigning a tensor keeps it as it is, assigning
    a stored form (``Half``, ``AngleImages``) keeps that."""

    def __init__(self, required: bool):
        self.required = required

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.slot = name, f"_stored_{name}"

    def __get__(self, view: Any, owner: type | None = None) -> Any:
        if view is None:  # the dataclass asks for the default: none for a required field
            if self.required:
                raise AttributeError(self.name)
            return None
        stored = view.__dict__[self.slot]
        return None if stored is None else stored.decode()

    def __set__(self, view: Any, value: Any) -> None:
        if value is None and self.required:
            raise TypeError(f"View.{self.name} is required")
        view.__dict__[self.slot] = None if value is None else as_stored(value)


@dataclass
class View:
    """One polarimetric view: camera plus Stokes images.

    The image fields are stored compactly when a reader made them so (8/16-bit angle images,
    float16; :meth:`stored`) and decoded on every read to the shapes and dtypes below. A tensor
    given to the constructor (or assigned) is kept as it is.

    Attributes:
        name: unique view name (usually the file stem).
        K: (3, 3) float64 intrinsics, pixel centres at +0.5.
        world_to_camera: (4, 4) float64 rigid transform, OpenCV camera frame.
        stokes: (3, C, H, W) float32 linear Stokes (s0, s1, s2), C = 1 (mono) or 3 (RGB).
        mask: optional (1, H, W) bool object mask.
        normal_gt: optional (3, H, W) float32 ground-truth camera-frame normals (0 outside mask).
        depth_gt: optional (1, H, W) float32 ground-truth camera-z depth (0 outside mask).
        source: where the view came from (a file or folder), for error messages.
    """

    name: str
    K: Tensor
    world_to_camera: Tensor
    stokes: Tensor = _StoredField(required=True)  # type: ignore[assignment]
    mask: Tensor | None = _StoredField(required=False)  # type: ignore[assignment]
    normal_gt: Tensor | None = _StoredField(required=False)  # type: ignore[assignment]
    depth_gt: Tensor | None = _StoredField(required=False)  # type: ignore[assignment]
    source: str = ""

    #: The image fields, kept as stored forms.
    IMAGE_FIELDS = ("stokes", "mask", "normal_gt", "depth_gt")

    def stored(self, name: str) -> Stored | None:
        """The stored form of the image field ``name`` (one of :attr:`IMAGE_FIELDS`), not decoded."""
        if name not in self.IMAGE_FIELDS:
            raise KeyError(f"View has no image field {name!r} (fields: {', '.join(self.IMAGE_FIELDS)})")
        return self.__dict__[f"_stored_{name}"]

    @property
    def nbytes(self) -> int:
        """Bytes the view's images take in memory as stored."""
        return sum(s.nbytes for s in (self.stored(n) for n in self.IMAGE_FIELDS) if s is not None)

    @property
    def height(self) -> int:
        return int(self.stored("stokes").shape[-2])

    @property
    def width(self) -> int:
        return int(self.stored("stokes").shape[-1])

    @property
    def channels(self) -> int:
        """C, the colour channels of the Stokes images."""
        return int(self.stored("stokes").shape[1])

    @property
    def device(self) -> torch.device:
        """The device the images are on."""
        return self.stored("stokes").device

    @property
    def image(self) -> Tensor:
        """(C, H, W) training colour s0 / 2 (docs/conventions.md)."""
        return self.stokes[0] / 2

    @property
    def R(self) -> Tensor:
        """(3, 3) world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> Tensor:
        """(3,) world-to-camera translation."""
        return self.world_to_camera[:3, 3]

    @property
    def camera_center(self) -> Tensor:
        """(3,) camera centre in world coordinates, -R^T t."""
        return -self.R.T @ self.t

    def to(self, device: torch.device | str) -> View:
        """A copy with every tensor on ``device``, images in their stored forms (cameras keep float64)."""
        images = {name: None if self.stored(name) is None else self.stored(name).to(device)
                  for name in self.IMAGE_FIELDS}
        return self.replaced(K=self.K.to(device), world_to_camera=self.world_to_camera.to(device), **images)

    def replaced(self, **changes: Any) -> View:
        """:func:`dataclasses.replace` that keeps the images it does not change in their stored
        forms (``replace`` itself would decode them)."""
        kept = {name: self.stored(name) for name in self.IMAGE_FIELDS if name not in changes}
        return replace(self, **kept, **changes)


def content_digest(view: View, prefix: bytes = b"") -> str:
    """SHA-256 (hex) of ``prefix`` followed by the view's image content: the dtype, shape and
    bytes of its Stokes and of its mask. The name and the camera do not enter: what a view's
    maps are computed from (the maps cache key) and what a run was trained on (its data
    fingerprint) are both told by this digest."""
    digest = hashlib.sha256(prefix)
    for tensor in (view.stokes, view.mask):
        if tensor is None:
            digest.update(b"none")
            continue
        array = tensor.detach().cpu().contiguous().numpy()
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def describe_view(view: View) -> str:
    """How messages name a view: its name and, when known, where it came from."""
    return f"view '{view.name}'" + (f" ({view.source})" if view.source else "")


def _first_bad(tensor: Tensor) -> str:
    """Index of the first non-finite element, e.g. ``[0, 2, 5, 7]``."""
    index = (~torch.isfinite(tensor)).nonzero()[0].tolist()
    return "[" + ", ".join(str(i) for i in index) + "]"


def validate_view(view: View, where: str) -> None:
    """Refuse a view with wrong shapes or non-finite Stokes / camera values (one implementation for
    the readers' door, the hooks and the trainer).

    Args:
        view: the view.
        where: who checks, for the message (e.g. ``"hooks.preprocess"``).

    Raises:
        PolarInputError: naming the view's source (or name), the field and the problem.
    """
    described = describe_view(view)
    stokes = view.stored("stokes")  # shapes and finiteness without decoding
    if len(stokes.shape) != 4 or stokes.shape[0] != 3 or stokes.shape[1] not in (1, 3):
        raise PolarInputError(view.source or view.name, f"{where}: {described}: stokes has shape {tuple(stokes.shape)}, "
                              "expected (3, C, H, W) with C = 1 or 3")
    height, width = stokes.shape[-2:]
    expected = {"mask": (1, height, width), "normal_gt": (3, height, width), "depth_gt": (1, height, width)}
    problems = [f"{name} has shape {tuple(shape)}, expected {wanted}" for name, shape, wanted in (
        ("K", view.K.shape, (3, 3)), ("world_to_camera", view.world_to_camera.shape, (4, 4)),
        *((name, view.stored(name).shape, wanted) for name, wanted in expected.items() if view.stored(name) is not None),
    ) if tuple(shape) != wanted]
    for name, finite in (("stokes", stokes.all_finite()), ("K", _all_finite(view.K)),
                         ("world_to_camera", _all_finite(view.world_to_camera))):
        if not finite:
            value = getattr(view, name)
            count = int((~torch.isfinite(value)).sum())
            problems.append(f"{name} has {count} non-finite value(s) (NaN or inf), the first at index {_first_bad(value)}")
    if problems:
        raise PolarInputError(view.source or view.name, f"{where}: {described}: " + "; ".join(problems))


def _all_finite(tensor: Tensor) -> bool:
    return not tensor.is_floating_point() or bool(torch.isfinite(tensor).all())


@dataclass
class PolarMaps:
    """Per-view maps computed once by ``PolarHooks.preprocess`` (all (.., H, W), float32).

    Attributes:
        aolp: (1, H, W) AoLP in [0, pi) of the channel-mean Stokes, docs/conventions.md convention.
        dolp: (1, H, W) DoLP in [0, 1] of the channel-mean Stokes.
        intensity: (C, H, W) training colour s0 / 2.
        specular_mask: (1, H, W) bool, reflective (specular) pixels.
        overexposed_mask: (1, H, W) bool, overexposed pixels.
        pri: (1, H, W) polarimetric reference intensity.
        i_diff: (C, H, W) specular-free colour target I_diff (valid inside specular_mask).
        i_chro: (C, H, W) chromaticity target I_chro (valid inside overexposed_mask).
        extras: anything else a module caches (for example the DoLP weight omega).
    """

    aolp: Tensor
    dolp: Tensor
    intensity: Tensor
    specular_mask: Tensor | None = None
    overexposed_mask: Tensor | None = None
    pri: Tensor | None = None
    i_diff: Tensor | None = None
    i_chro: Tensor | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)


@dataclass
class RenderOut:
    """What a renderer returns for one view (the adapter contract).

    Attributes:
        color: (3, H, W) rendered colour.
        depth: (1, H, W) expected camera-z depth normalised by alpha (0 where alpha = 0).
        normal: (3, H, W) camera-frame normal, facing the camera (not renormalised).
        alpha: (1, H, W) accumulated opacity.
        median_depth: optional (1, H, W) depth where transmittance crosses 0.5.
        plane_depth: optional (1, H, W) unbiased plane depth (PGSR): the camera z where each
            pixel's ray (through its centre, +0.5) meets the plane n . x = -d of the
            alpha-blended camera-frame normal n and plane distance d (a Gaussian's d is
            -n_i . mean_cam); 0 where the ray does not meet it. L_dn uses it when given, else
            ``depth`` (``polargs_plugin.kit.depth_from_plane`` makes it from a renderer's
            blended distance and normal).
        means2d: optional (N, 2) screen-space means whose .grad drives densification.
        radii: optional (N,) screen-space radius in pixels (0 = not visible).
    """

    color: Tensor
    depth: Tensor
    normal: Tensor
    alpha: Tensor
    median_depth: Tensor | None = None
    plane_depth: Tensor | None = None
    means2d: Tensor | None = None
    radii: Tensor | None = None

    def detached(self) -> RenderOut:
        """The same render without its autograd graph: every tensor field ``.detach()``-ed (same
        storage, no copy), ``None`` fields kept. A trainer passes this to the densify hook, which
        runs after ``backward`` and must not extend or hold the graph."""
        return replace(self, **{f.name: getattr(self, f.name).detach() for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})


@dataclass
class GaussianState:
    """A trainer's Gaussians as the hooks see them (activated values, autograd-connected).

    Attributes:
        means: (N, 3) world positions.
        quats: (N, 4) rotations, wxyz (not necessarily normalised).
        scales: (N, 3) positive scales (after exp).
        opacities: (N,) in (0, 1) (after sigmoid).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor

    @property
    def num(self) -> int:
        return int(self.means.shape[0])


@dataclass
class NewGaussians:
    """Gaussians to append, as returned by ``PolarHooks.densify`` (activated values).

    Attributes:
        means: (M, 3) world positions.
        quats: (M, 4) wxyz rotations whose shortest axis is the seeding normal.
        scales: (M, 3) positive scales.
        colors: (M, 3) RGB in [0, 1].
        opacities: (M,) in (0, 1).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    colors: Tensor
    opacities: Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])


RenderFn = Callable[[View], RenderOut]
"""Renders any training view with the trainer's current Gaussians."""


@runtime_checkable
class TrainingHooks(Protocol):
    """What a trainer calls on its hooks object (``polargs_plugin.PolarHooks`` implements it).

    Iterations are 1-based everywhere in this protocol, as in vanilla 3DGS's ``train.py``: the
    first optimisation step is iteration 1, and every schedule (Dense window, the L_dn start)
    compares against that number. A trainer that counts from 0 (gsplat's ``step``) passes
    ``step + 1``.

    Per iteration, in this order: render; the trainer's own loss; :meth:`loss` (added before
    ``backward``); ``backward``; optimizer step; the trainer's own density control; then, under
    ``no_grad``, :meth:`densify` where :meth:`densify_due`, whose Gaussians the trainer appends with
    their optimizer state.
    """

    def preprocess(self, views: list[View]) -> Any:
        """Once, before the first iteration, with every training view."""
        ...

    def loss(self, iteration: int, view: View, render: RenderOut, gaussians: GaussianState) -> tuple[Tensor, dict]:
        """``(extra loss to add before backward, logs)`` for ``view`` rendered as ``render``."""
        ...

    def densify_due(self, iteration: int) -> bool:
        """Whether :meth:`densify` may return Gaussians at ``iteration``; where it is False a
        trainer skips the call and what it would build for it (the Gaussians' state, a render)."""
        ...

    def densify(
        self,
        iteration: int,
        view: View,
        render_fn: RenderFn,
        gaussians: GaussianState,
        render: RenderOut | None = None,
    ) -> NewGaussians | None:
        """Gaussians to append after the optimizer step (or ``None``); ``render`` is the caller's
        render of ``view`` from this iteration, used instead of rendering it again."""
        ...

    def state_dict(self) -> dict:
        """What a checkpoint must hold to resume."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        ...
