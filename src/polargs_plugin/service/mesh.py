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

    from polargs_plugin.types import View

    from polargs_plugin.backends.reference.model import GaussianModel

__all__ = ["MeshSettings", "MeshResult", "fuse_model", "mesh_run", "write_mesh_result"]


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
            0 keeps every pixel).
        masks: restrict fusion to the views' object masks (default True).
        min_cluster: connected pieces with fewer triangles than this fraction of the largest are
            dropped (default 0.05; 1 keeps only the largest, 0 keeps all).
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
    masks: bool = True
    min_cluster: float = 0.05
    incidence_trunc: float = 2.0

    def tsdf(self, source: str = "mesh") -> dict[str, float]:
        """``voxel_size``, ``sdf_trunc``, ``depth_trunc`` (scene units) of these settings;
        PolarInputError naming ``source`` when they are not valid lengths."""
        from polargs_plugin.mesh import mesh_settings

        try:
            if not self.incidence_trunc >= 1.0:  # NaN too
                raise ValueError(f"incidence_trunc must be a number >= 1, got {self.incidence_trunc}")
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
    import torch
    from tqdm import tqdm

    from polargs_plugin.densify.filters import incidence_cosine
    from polargs_plugin.mesh import tsdf_fuse

    tsdf = settings.tsdf(source or "mesh")
    start = time.perf_counter()
    depths, colors, Ks, w2cs, masks, alphas, incidences = [], [], [], [], [], [], []
    with torch.no_grad():
        for view in tqdm(views, desc="rendering", unit="view", disable=not progress):
            out = model.render_output(view)
            depth = out.median_depth if settings.depth == "median" else out.depth
            if depth is None:
                raise PolarInputError(source or "mesh", "the renderer returns no median depth; use --depth expected")
            depths.append(depth.cpu())
            if settings.incidence_trunc > 1.0:
                incidences.append(incidence_cosine(depth, out.normal, view.K, view.world_to_camera,
                                                   view.world_to_camera).cpu())
            colors.append(out.color.clamp(0, 1).cpu())
            alphas.append(out.alpha.cpu())
            masks.append(view.mask if settings.masks else None)
            Ks.append(view.K)
            w2cs.append(view.world_to_camera)
    threshold = settings.alpha_threshold if settings.alpha_threshold > 0 else None
    keep = settings.min_cluster if settings.min_cluster > 0 else False
    mesh = tsdf_fuse(depths, colors, Ks, w2cs, masks=masks, keep_largest=keep, alphas=alphas,
                     alpha_threshold=threshold, incidences=incidences or None,
                     max_trunc_scale=settings.incidence_trunc, progress=progress, **tsdf)
    if len(mesh.triangles) == 0:
        raise PolarInputError(source or "mesh", "the fused mesh is empty (check depth truncation, masks and alpha threshold)")
    info = {
        "run_dir": os.path.abspath(source) if source else source,
        "preset": settings.preset,
        **tsdf,
        "depth": settings.depth,
        "alpha_threshold": threshold,
        "masks": settings.masks,
        "min_cluster_fraction": settings.min_cluster,
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
