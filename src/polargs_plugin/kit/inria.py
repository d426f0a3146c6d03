"""What the adapters of the graphdeco (Inria 3DGS) family share: graphdeco, GOF and PGSR.

These trainers have one layout: a ``Scene`` whose ``getTrainCameras()`` are FoV cameras named by
``image_name`` (:mod:`.cameras`), a ``GaussianModel`` with raw ``_xyz``, ``_features_dc``,
``_features_rest``, ``_opacity`` (N, 1), ``_scaling``, ``_rotation`` and its activated getters,
one Adam with a group per parameter, and ``densification_postfix`` as the append path (it
concatenates the rows with zero Adam moments and resets the densification statistics).
:class:`InriaAdapter` translates that layout; a trainer's adapter subclasses it and says how its
render package becomes a :class:`RenderOut` and how its ``densification_postfix`` is called.

Patched training loops call three methods (all iterations 1-based, as the loops count)::

    polar = adapter_module.attach(scene, gaussians, pipe, render, **render_kwargs)   # before the loop
    loss = loss + polar.loss(iteration, viewpoint_cam, render_pkg)            # before backward
    polar.densify(iteration, viewpoint_cam, render_pkg)                       # after the step

Each adapter module's ``attach`` reads the polarimetric data and the settings from the
environment (``POLARGS_DATA``, ``POLARGS_PRESET``, ``POLARGS_CONFIG``, ``POLARGS_KEEP_NATIVE``:
:mod:`polargs_plugin.service.adapters`) and builds the adapter.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from polargs_plugin.config import PolarConfig
from polargs_plugin.data.resolution import area_resize, nearest_resize
from polargs_plugin.hooks import PolarHooks
from polargs_plugin.io import PolarInputError
from polargs_plugin.kit.append import pad_rows, raw_from_new
from polargs_plugin.kit.cameras import view_from_graphdeco
from polargs_plugin.types import GaussianState, NewGaussians, RenderOut, View

__all__ = ["match_views", "polar_data_by_name", "InriaAdapter"]


def _resized(image: Tensor, height: int, width: int, mode: str) -> Tensor:
    """(..., h, w) -> (..., height, width) on the pixel-centre convention of ``--resolution``
    (:mod:`polargs_plugin.data.resolution`): Stokes area-averaged (they are linear, so the average
    stays valid), masks sampled at the new pixel centres; a larger size is interpolated bilinearly."""
    if tuple(image.shape[-2:]) == (height, width):
        return image
    if mode == "nearest":
        return nearest_resize(image, (width, height))
    if height <= image.shape[-2] and width <= image.shape[-1]:
        return area_resize(image, (width, height)).to(image.dtype)
    flat = image.reshape(1, -1, *image.shape[-2:]).float()
    out = F.interpolate(flat, size=(height, width), mode="bilinear", align_corners=False)
    return out.reshape(*image.shape[:-2], height, width).to(image.dtype)


def polar_data_by_name(
    images: Sequence[tuple[str, int, int]], polar_views: Sequence[View], source: str = ""
) -> dict[str, View]:
    """The polarimetric view of each of a trainer's images, at that image's resolution.

    Args:
        images: ``(name, height, width)`` of each trainer image.
        polar_views: the dataset's views; an image takes the view of its name, or of its file
            stem. Stokes are resampled when the trainer loaded its images at another size (area
            average, Stokes being linear), masks by nearest neighbour.
        source: the dataset folder, for messages.

    Returns:
        ``name -> View`` with the dataset's camera and the resampled Stokes and mask (the
        caller puts the trainer's camera in).

    Raises:
        PolarInputError: an image has no polarimetric view of its name (the message lists a few
            names from each side).
    """
    by_name = {view.name: view for view in polar_views}
    by_name.update({Path(view.name).stem: view for view in polar_views if Path(view.name).stem not in by_name})
    missing = [name for name, _, _ in images if name not in by_name and Path(name).stem not in by_name]
    if missing:
        raise PolarInputError(
            source or "polarimetric dataset",
            f"no view for {len(missing)} of the trainer's {len(images)} images (e.g. {missing[:3]}); "
            f"the dataset has {len(by_name)} views named e.g. {sorted(by_name)[:3]}",
        )
    out = {}
    for name, height, width in images:
        data = by_name.get(name) or by_name[Path(name).stem]
        stokes = _resized(data.stokes, height, width, "area")
        mask = None if data.mask is None else _resized(data.mask, height, width, "nearest").bool()
        out[name] = replace(data, stokes=stokes, mask=mask)
    return out


def match_views(cameras: Sequence[Any], polar_views: Sequence[View], source: str = "") -> dict[str, View]:
    """One :class:`View` per trainer camera: its geometry, the polarimetric data of the same name.

    The trainer's cameras are the geometry that is rendered, so they define K and the pose; the
    dataset's view of the same name (``camera.image_name``, or the dataset view's file stem)
    gives the Stokes and mask (:func:`polar_data_by_name`).

    Raises:
        PolarInputError: a camera has no polarimetric view of its name.
    """
    images = [(cam.image_name, int(cam.image_height), int(cam.image_width)) for cam in cameras]
    data = polar_data_by_name(images, polar_views, source)
    return {
        cam.image_name: view_from_graphdeco(
            cam, data[cam.image_name].stokes, mask=data[cam.image_name].mask, source=data[cam.image_name].source
        )
        for cam in cameras
    }


class InriaAdapter:
    """PolarHooks driven from a graphdeco-family training loop.

    Args:
        scene: the trainer's ``Scene`` (``getTrainCameras()``).
        gaussians: the trainer's ``GaussianModel``.
        pipe: the pipeline parameters its ``render`` takes.
        render: the trainer's ``render(camera, gaussians, pipe, bg, ...)`` function.
        polar_views: the polarimetric views (matched to the cameras by name, :func:`match_views`).
        config: PolarGS settings (default :meth:`PolarConfig.real`). The loss switches of
            :attr:`native_terms` are turned off unless ``keep_native_terms``.
        keep_native_terms: keep the plug-in's copies of terms the trainer already has.
        render_kwargs: extra keyword arguments of the trainer's ``render`` (GOF's ``kernel_size``).
        max_gaussians: appends stop at this many Gaussians (None: the model's own cap named by
            :attr:`model_cap`, else no cap).
        source: the dataset folder, for messages.

    Attributes:
        hooks: the :class:`PolarHooks`; views: View per camera name; logs: the last loss logs
            (detached tensors); appended: Gaussians appended so far.
    """

    #: PolarConfig.losses switches of terms the trainer computes itself, with the reason.
    native_terms: ClassVar[dict[str, str]] = {}
    #: per-Gaussian statistics of the model that ``densification_postfix`` resets; kept (padded).
    statistics: ClassVar[tuple[str, ...]] = ("xyz_gradient_accum", "denom", "max_radii2D")
    #: whether the trainer's render package holds depth, normal and alpha (no extra pass needed).
    geometry_in_render: ClassVar[bool] = False
    #: the model's attribute holding its own point cap (PGSR's ``max_all_points``): the default
    #: of ``max_gaussians``.
    model_cap: ClassVar[str | None] = None

    def __init__(
        self,
        scene: Any,
        gaussians: Any,
        pipe: Any,
        render: Callable[..., dict],
        polar_views: Sequence[View],
        *,
        config: PolarConfig | None = None,
        keep_native_terms: bool = False,
        render_kwargs: Mapping[str, Any] | None = None,
        max_gaussians: int | None = None,
        source: str = "",
    ) -> None:
        self.config = config if config is not None else PolarConfig.real()
        if not keep_native_terms:
            for switch in self.native_terms:
                setattr(self.config.losses, switch, False)
        self.scene, self.gaussians, self.pipe, self.render = scene, gaussians, pipe, render
        self.render_kwargs = dict(render_kwargs or {})
        if max_gaussians is None and self.model_cap is not None and getattr(gaussians, self.model_cap, None) is not None:
            max_gaussians = int(getattr(gaussians, self.model_cap))
        self.max_gaussians = max_gaussians
        cameras = list(scene.getTrainCameras())
        self.cameras = {cam.image_name: cam for cam in cameras}
        self.views = match_views(cameras, polar_views, source)
        self.hooks = PolarHooks(self.config)
        self.hooks.preprocess(list(self.views.values()))
        self.logs: dict[str, Tensor] = {}
        self.appended = 0

    @classmethod
    def from_inputs(cls, inputs: Any, scene: Any, gaussians: Any, pipe: Any, render: Callable[..., dict],
                    **render_kwargs: Any) -> "InriaAdapter":
        """The adapter of a patched loop, from the views and settings its environment gave
        (``polargs_plugin.service.adapter_inputs``: ``views``, ``config``, ``source``). The
        settings already hold the native-term switches, so they are kept as given."""
        return cls(scene, gaussians, pipe, render, inputs.views, config=inputs.config, keep_native_terms=True,
                   render_kwargs=render_kwargs, source=inputs.source)

    # ------------------------------------------------------------------ translation
    def gaussian_state(self) -> GaussianState:
        """The model's activated, autograd-connected Gaussians."""
        g = self.gaussians
        return GaussianState(
            means=g.get_xyz, quats=g.get_rotation, scales=g.get_scaling, opacities=g.get_opacity.reshape(-1)
        )

    def world_to_camera(self, camera: Any) -> Tensor:
        """(4, 4) world-to-camera of a trainer camera (its ``world_view_transform`` transposed)."""
        return camera.world_view_transform.transpose(0, 1)

    def render_out(self, camera: Any, render_pkg: Mapping[str, Any], geometry: bool = True) -> RenderOut:
        """The :class:`RenderOut` of a render package; ``geometry=False`` may leave depth, normal
        and alpha zero (the hooks do not read them then)."""
        raise NotImplementedError

    def _background(self, like: Tensor) -> Tensor:
        return torch.zeros(3, dtype=like.dtype, device=like.device)

    def _color_only(self, color: Tensor) -> RenderOut:
        zero = color.new_zeros((1, *color.shape[-2:]))
        return RenderOut(color=color, depth=zero, normal=color.new_zeros(color.shape), alpha=zero)

    def render_view(self, view: View) -> RenderOut:
        """Render a training view with the trainer's own renderer (for Dense's sources)."""
        camera = self.cameras[view.name]
        like = self.gaussians.get_xyz
        pkg = self.render(camera, self.gaussians, self.pipe, self._background(like), **self.render_kwargs)
        return self.render_out(camera, pkg, geometry=True)

    def _view(self, camera: Any) -> View:
        try:
            return self.views[camera.image_name]
        except KeyError:
            raise KeyError(f"camera '{camera.image_name}' is not a training camera of this adapter") from None

    # ------------------------------------------------------------------------ hooks
    def loss(self, iteration: int, camera: Any, render_pkg: Mapping[str, Any]) -> Tensor:
        """The PolarGS loss to add to the trainer's loss before ``backward`` (1-based iteration)."""
        view = self._view(camera)
        render = self.render_out(camera, render_pkg, geometry=self.hooks.geometry_needed(iteration, view.name))
        extra, self.logs = self.hooks.loss(iteration, view, render, self.gaussian_state())
        return extra

    def densify(self, iteration: int, camera: Any, render_pkg: Mapping[str, Any] | None = None) -> int:
        """Dense after the optimizer step (1-based iteration): appends through the trainer's
        ``densification_postfix``; returns how many Gaussians were appended."""
        if not self.hooks.densify_due(iteration):  # off Dense's schedule: no state, no render conversion
            return 0
        with torch.no_grad():
            view = self._view(camera)
            render = None
            if self.geometry_in_render and render_pkg is not None:
                render = self.render_out(camera, render_pkg, geometry=True)
            new = self.hooks.densify(iteration, view, self.render_view, self.gaussian_state(), render=render)
            if new is None or len(new) == 0:
                return 0
            return self.append(new)

    # ----------------------------------------------------------------------- append
    def append(self, new: NewGaussians) -> int:
        """Append through the trainer's append path, keeping its densification statistics.

        Returns:
            How many were appended (fewer than ``len(new)`` at ``max_gaussians``).
        """
        g = self.gaussians
        n = int(g.get_xyz.shape[0])
        m = len(new)
        if self.max_gaussians is not None:
            m = max(0, min(m, self.max_gaussians - n))
        if m == 0:
            return 0
        rows = raw_from_new(_first_rows(new, m), int(g._features_rest.shape[1]), like=g._xyz)
        kept = {
            name: getattr(g, name)
            for name in self.statistics
            if isinstance(getattr(g, name, None), Tensor) and getattr(g, name).shape[:1] == (n,)
        }
        self._postfix(
            dict(
                new_xyz=rows["means"],
                new_features_dc=rows["sh_dc"],
                new_features_rest=rows["sh_rest"],
                new_opacities=rows["opacity_logits"][:, None],
                new_scaling=rows["log_scales"],
                new_rotation=rows["quats"],
            )
        )
        for name, value in kept.items():  # the postfix zeroes them: keep what was accumulated
            setattr(g, name, pad_rows(value, m))
        self._after_append()
        self.appended += m
        return m

    def _postfix(self, rows: dict[str, Tensor]) -> None:
        """Call the trainer's ``densification_postfix`` with the raw rows (Inria names)."""
        self.gaussians.densification_postfix(**rows)

    def _after_append(self) -> None:
        """What the trainer needs after a topology change (GOF: its 3D filter)."""


def _first_rows(new: NewGaussians, m: int) -> NewGaussians:
    if m == len(new):
        return new
    return NewGaussians(new.means[:m], new.quats[:m], new.scales[:m], new.colors[:m], new.opacities[:m])
