"""Meshing a trained run: render every training view's depth and colour, fuse them (TSDF)."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Sequence

from polargs_plugin.io import PolarInputError, atomic_write
from polargs_plugin.service.runs import MESH_NAME, Run

if TYPE_CHECKING:
    import open3d as o3d

    from torch import Tensor

    from polargs_plugin.types import RenderOut, View

    from polargs_plugin.backends.reference.model import GaussianModel

__all__ = ["MeshSettings", "MeshResult", "fused_depth", "fuse_model", "mesh_run", "write_mesh_result"]


@dataclass(frozen=True)
class MeshSettings:
    """How ``polargs mesh`` fuses a run (docs/evaluation.md).

    Attributes:
        preset: TSDF settings in scene units: ``synthetic`` (voxel 1/128, SDF truncation 4/128,
            depth truncation 6: objects of radius ~1 seen from ~3 at 128 px) or ``paper``
            (0.008 / 0.04 / 10, PolarGS's). Default ``synthetic``.
        voxel: voxel size overriding the preset's; alone it keeps the preset's
            truncation-to-voxel ratio. None: the preset's.
        sdf_trunc: SDF truncation distance overriding the preset's. None: the preset's.
        depth_trunc: depths beyond this are ignored, overriding the preset's. None: the preset's.
        depth: the rendered depth fused: ``median`` (the transmittance-0.5 crossing, default) or
            ``expected`` (alpha-normalised mean depth).
        alpha_threshold: pixels with a rendered opacity below this are ignored (default 0.5;
            0 keeps every pixel), except the partly transparent ones of ``partial_alpha``.
        partial_alpha: inside a view's object mask, pixels whose rendered opacity is at least
            this but below ``alpha_threshold`` fuse the alpha-normalised expected depth (default
            0.2; ``alpha_threshold`` or above turns it off; views without a mask, and ``masks``
            False, keep ``alpha_threshold`` alone). Flat Gaussians render the surface that views
            see only at grazing angles partly transparent, where no median depth exists
            (transmittance never reaches 0.5), and the mesh would leave that surface out; the
            mask says the object is there, and the expected depth of the Gaussians that cover
            the pixel is where they put it (docs/evaluation.md).
        masks: restrict fusion to the views' object masks (default True).
        min_cluster: connected pieces with fewer triangles than this fraction of the largest are
            dropped (default 0.05; 1 keeps only the largest, 0 keeps all), except, with
            ``spare_pieces_in_masks``, those inside the masks.
        spare_pieces_in_masks: with masks on every view, a smaller piece is dropped only when
            more than a tenth of it lies outside some view's mask (dilated by one pixel); a piece
            inside every mask stays (default False: pieces are dropped by size alone; on the
            bundled scenes sparing them raised the Chamfer by 5-7 %, on the family's development
            seeds it lowered the grazing class's completeness distance by a third). A floater sticks
            out of the silhouettes that other views see; a piece of the surface that a hole has
            cut off from the rest, as often where views see it only at grazing angles, does not
            (docs/evaluation.md).
        incidence_trunc: a pixel's SDF truncation is the preset's times 1/cos of its incidence
            angle (from the rendered normal), capped at this factor (default 2; 1 gives every
            pixel the preset's): a fixed truncation leaves the surface that views see at grazing
            angles a band thinner than a voxel, and holes there (docs/evaluation.md).
    """

    preset: Literal["synthetic", "paper"] = "synthetic"
    voxel: float | None = None
    sdf_trunc: float | None = None
    depth_trunc: float | None = None
    depth: Literal["median", "expected"] = "median"
    alpha_threshold: float = 0.5
    partial_alpha: float = 0.2
    masks: bool = True
    min_cluster: float = 0.05
    spare_pieces_in_masks: bool = False
    incidence_trunc: float = 2.0

    @property
    def fuses_partial(self) -> bool:
        """Whether partly transparent pixels inside the masks are fused (``partial_alpha``)."""
        return self.masks and self.partial_alpha < self.alpha_threshold

    def tsdf(self, source: str = "mesh") -> dict[str, float]:
        """``voxel_size``, ``sdf_trunc``, ``depth_trunc`` (scene units) of these settings;
        PolarInputError naming ``source`` when they are not valid lengths."""
        from polargs_plugin.mesh import mesh_settings

        try:
            if not self.incidence_trunc >= 1.0:  # NaN too
                raise ValueError(f"incidence_trunc must be a number >= 1, got {self.incidence_trunc}")
            for name in ("alpha_threshold", "partial_alpha"):
                if not 0.0 <= getattr(self, name) <= 1.0:  # NaN too
                    raise ValueError(f"{name} must be a number in [0, 1], got {getattr(self, name)}")
            return mesh_settings(self.preset, self.voxel, self.sdf_trunc, self.depth_trunc)
        except ValueError as err:
            raise PolarInputError(source, f"bad TSDF settings: {err}") from None


@dataclass
class MeshResult:
    """A fused mesh and the record of how it was made.

    Attributes:
        mesh: the open3d triangle mesh.
        info: settings and counts, written beside the mesh as JSON (``write_mesh_result``).
        seconds: wall time of rendering and fusion.
    """

    mesh: "o3d.geometry.TriangleMesh"
    info: dict[str, Any]
    seconds: float


def fused_depth(out: "RenderOut", mask: Tensor | None, settings: MeshSettings) -> Tensor:
    """(1, H, W) the depth a rendered view contributes to the fusion, 0 where it contributes none.

    ``settings.depth`` where the render is opaque (alpha >= ``settings.alpha_threshold``); with
    a ``mask`` (1, H, W) and :attr:`MeshSettings.fuses_partial`, also the alpha-normalised
    expected depth where the mask holds and alpha is in [``partial_alpha``, ``alpha_threshold``).

    >>> import torch
    >>> from polargs_plugin.types import RenderOut
    >>> alpha = torch.tensor([[[0.9, 0.3, 0.3, 0.1]]])
    >>> out = RenderOut(color=torch.zeros(3, 1, 4), depth=torch.full((1, 1, 4), 2.0), normal=torch.zeros(3, 1, 4),
    ...                 alpha=alpha, median_depth=torch.tensor([[[1.9, 0.0, 0.0, 0.0]]]))
    >>> mask = torch.tensor([[[True, True, False, True]]])
    >>> fused_depth(out, mask, MeshSettings()).tolist()
    [[[1.899999976158142, 2.0, 0.0, 0.0]]]
    >>> fused_depth(out, None, MeshSettings()).tolist()
    [[[1.899999976158142, 0.0, 0.0, 0.0]]]
    """
    import torch

    depth = out.median_depth if settings.depth == "median" else out.depth
    keep = out.alpha >= settings.alpha_threshold
    if mask is not None and settings.fuses_partial:
        partial = mask.bool() & (out.alpha >= settings.partial_alpha)
        depth = torch.where(keep, depth, out.depth)
        keep = keep | partial
    return torch.where(keep, depth, torch.zeros_like(depth))


def fuse_model(model: "GaussianModel", views: Sequence[View], settings: MeshSettings = MeshSettings(),
               progress: bool = False, source: str = "") -> MeshResult:
    """Render ``views`` with ``model`` (:meth:`~polargs_plugin.backends.reference.model.GaussianModel.render_output`)
    and fuse their depths into a mesh.

    Args:
        model: the trained Gaussians.
        views: the views to render (a run's training views).
        settings: TSDF and masking settings.
        progress: show progress bars (rendering, fusion).
        source: the run folder, recorded in ``info`` and named in errors.

    Raises:
        PolarInputError: bad TSDF settings, no median depth for ``depth="median"``, or an empty mesh.
    """
    import numpy as np
    import torch
    from tqdm import tqdm

    from polargs_plugin.densify.filters import incidence_cosine
    from polargs_plugin.mesh import keep_largest_cluster, tsdf_fuse
    from polargs_plugin.metrics import cull_to_masks

    tsdf = settings.tsdf(source or "mesh")
    start = time.perf_counter()
    depths, colors, Ks, w2cs, masks, incidences = [], [], [], [], [], []
    with torch.no_grad():
        for view in tqdm(views, desc="rendering", unit="view", disable=not progress):
            out = model.render_output(view)
            if settings.depth == "median" and out.median_depth is None:
                raise PolarInputError(source or "mesh", "the renderer returns no median depth; use --depth expected")
            mask = view.mask if settings.masks else None
            depth = fused_depth(out, mask, settings)
            depths.append(depth.cpu())
            if settings.incidence_trunc > 1.0:
                incidences.append(incidence_cosine(depth, out.normal, view.K, view.world_to_camera,
                                                   view.world_to_camera).cpu())
            colors.append(out.color.clamp(0, 1).cpu())
            masks.append(mask)
            Ks.append(view.K)
            w2cs.append(view.world_to_camera)
    threshold = settings.alpha_threshold if settings.alpha_threshold > 0 else None
    keep = settings.min_cluster if settings.min_cluster > 0 else False
    spare = keep is not False and settings.spare_pieces_in_masks and all(mask is not None for mask in masks)
    # fused_depth has already left out the pixels below the opacity thresholds
    mesh = tsdf_fuse(depths, colors, Ks, w2cs, masks=masks, keep_largest=False if spare else keep,
                     incidences=incidences or None, max_trunc_scale=settings.incidence_trunc, progress=progress, **tsdf)
    if spare and len(mesh.vertices):
        inside = cull_to_masks(np.asarray(mesh.vertices), views, dilation_px=1)
        keep_largest_cluster(mesh, keep, spared=inside)
        mesh.compute_vertex_normals()
    if len(mesh.triangles) == 0:
        raise PolarInputError(source or "mesh", "the fused mesh is empty (check depth truncation, masks and alpha threshold)")
    info = {
        "run_dir": os.path.abspath(source) if source else source,
        "preset": settings.preset,
        **tsdf,
        "depth": settings.depth,
        "alpha_threshold": threshold,
        "partial_alpha": settings.partial_alpha if settings.fuses_partial else None,
        "masks": settings.masks,
        "min_cluster_fraction": settings.min_cluster,
        "spared_pieces_in_masks": spare,
        "incidence_trunc": settings.incidence_trunc,
        "views": len(views),
        "vertices": len(mesh.vertices),
        "triangles": len(mesh.triangles),
    }
    return MeshResult(mesh, info, time.perf_counter() - start)


def write_mesh_result(result: MeshResult, path: Path) -> Path:
    """Write the mesh to ``path`` and its settings to ``path`` with the suffix ``.json``, atomically."""
    from polargs_plugin.mesh import write_mesh

    try:
        write_mesh(path, result.mesh)
        with atomic_write(path.with_suffix(".json")) as handle:
            json.dump(result.info, handle, indent=2)
    except OSError as err:
        raise PolarInputError(path, f"cannot write the mesh ({err.strerror or err})") from None
    return path


def mesh_run(run: Run, settings: MeshSettings = MeshSettings(), out: Path | None = None,
             progress: bool = False) -> tuple[MeshResult, Path]:
    """Mesh a run read by :func:`~polargs_plugin.service.runs.load_run` and write
    ``out`` (default ``RUN_DIR/tsdf_mesh.ply``) with its JSON sidecar. Returns (result, path)."""
    result = fuse_model(run.model, run.views, settings, progress, source=str(run.folder))
    path = out or run.folder / MESH_NAME
    return result, write_mesh_result(result, path)
