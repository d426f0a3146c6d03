"""Trained Gaussians from the graphdeco PLY layout (``point_cloud.ply``), as raw parameters.

graphdeco's 3DGS writes one vertex per Gaussian with the properties ``x y z`` (world position),
``nx ny nz`` (unused, zeros), ``f_dc_0..2`` (the SH DC coefficient per colour channel),
``f_rest_0..3(K-1)-1`` (the higher SH bands, channel-major: ``f_rest_{c (K-1) + k}`` is band row
``k`` of channel ``c``), ``opacity`` (the logit), ``scale_0..2`` (log scales) and ``rot_0..3``
(the quaternion, w first, not normalised). GOF, PGSR, 2DGS (two scales), gsplat's exporter and
OpenSplat write the same layout; :func:`read_gaussian_ply` returns it under the names of
:data:`polargs_plugin.kit.append.RAW_NAMES`, ready for a
:class:`~polargs_plugin.backends.reference.model.GaussianModel`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from polargs_plugin.io import PolarInputError

__all__ = ["read_gaussian_ply", "GaussianPly"]

#: PLY property types and their numpy codes (both the spec's names and the sized aliases).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">"}


class GaussianPly(dict):
    """Raw parameters read by :func:`read_gaussian_ply` (a ``dict`` of name -> tensor) with the
    file's ``sh_degree``, ``path`` and ``comments`` (header comment lines, e.g. the iteration)."""

    sh_degree: int
    path: Path
    comments: list[str]


def _header(handle, path: Path) -> tuple[str, int, list[tuple[str, str]], list[str]]:
    """(byte-order code, vertex count, [(property, numpy code)], comments) of a PLY header."""
    if handle.readline().strip() != b"ply":
        raise PolarInputError(path, "not a PLY file (the first line is not 'ply')")
    order, count, props, comments, element = None, None, [], [], None
    for raw in iter(handle.readline, b""):
        words = raw.decode("ascii", errors="replace").split()
        if not words:
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if words[1] not in _FORMATS:
                raise PolarInputError(path, f"PLY format '{words[1]}' is not supported (binary little- or big-endian only)")
            order = _FORMATS[words[1]]
        elif words[0] == "comment":
            comments.append(" ".join(words[1:]))
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                count = int(words[2])
            elif count is None:
                raise PolarInputError(path, f"element '{element}' comes before the vertices; expected a Gaussian PLY")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list" or words[1] not in _PLY_TYPES:
                raise PolarInputError(path, f"vertex property '{' '.join(words[1:])}' is not a scalar PLY type")
            props.append((words[2], _PLY_TYPES[words[1]]))
    else:
        raise PolarInputError(path, "the PLY header has no end_header line")
    if order is None or count is None:
        raise PolarInputError(path, "the PLY header names no binary format or no vertex element")
    return order, count, props, comments


def _numbered(names: set[str], prefix: str) -> list[str]:
    """``prefix0, prefix1, ...`` present in ``names``, in numeric order, checked to be contiguous."""
    found = sorted((int(n[len(prefix):]) for n in names if n.startswith(prefix) and n[len(prefix):].isdigit()))
    if found != list(range(len(found))):
        raise ValueError(f"properties {prefix}* are not numbered 0..{len(found) - 1}: {found}")
    return [f"{prefix}{i}" for i in found]


def read_gaussian_ply(path: str | os.PathLike) -> GaussianPly:
    """Read a graphdeco-layout Gaussian PLY (module docstring) into raw parameters.

    Args:
        path: the ``.ply`` file (binary; graphdeco's ``point_cloud/iteration_N/point_cloud.ply``,
            OpenSplat's ``-o`` output, ...).

    Returns:
        :class:`GaussianPly`: ``means`` (N, 3), ``sh_dc`` (N, 1, 3), ``sh_rest`` (N, K - 1, 3),
        ``opacity_logits`` (N,), ``log_scales`` (N, 3; a 2DGS file's two scales get a third, a
        thousandth of the smaller one, so the surfel stays flat), ``quats`` (N, 4, wxyz as
        stored), float32 on the CPU; ``sh_degree`` from the number of ``f_rest`` properties.

    Raises:
        PolarInputError: naming the file: not a binary PLY, a property missing, an SH band count
            that is no degree's, fewer bytes than the header promises, or non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise PolarInputError(path, "no such Gaussian PLY file")
    with open(path, "rb") as handle:
        order, count, props, comments = _header(handle, path)
        dtype = np.dtype([(name, order + code) for name, code in props])
        data = np.fromfile(handle, dtype=dtype, count=count)
    if len(data) != count:
        raise PolarInputError(path, f"the header promises {count} vertices, the file holds {len(data)}")
    names = set(dtype.names or ())
    try:
        rest = _numbered(names, "f_rest_")
        scales = _numbered(names, "scale_")
    except ValueError as err:
        raise PolarInputError(path, str(err)) from None
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in names] + ([] if len(scales) in (2, 3) else ["scale_0..2"])
    if missing:
        raise PolarInputError(path, f"not a Gaussian PLY: missing vertex properties {', '.join(missing)}")
    bands = len(rest) // 3 + 1
    degree = round(math.sqrt(bands)) - 1
    if len(rest) % 3 or (degree + 1) ** 2 != bands:
        raise PolarInputError(path, f"{len(rest)} f_rest properties are no SH degree's (3 ((d + 1)^2 - 1))")

    def columns(keys: list[str]) -> Tensor:
        if not keys:  # SH degree 0: no f_rest
            return torch.zeros(count, 0)
        return torch.from_numpy(np.stack([data[k].astype(np.float32) for k in keys], axis=-1))

    log_scales = columns(scales)
    if log_scales.shape[1] == 2:  # a 2DGS surfel: flat along its normal
        log_scales = torch.cat([log_scales, log_scales.min(dim=1, keepdim=True).values - math.log(1e3)], dim=1)
    out = GaussianPly(
        means=columns(["x", "y", "z"]),
        sh_dc=columns(["f_dc_0", "f_dc_1", "f_dc_2"]).unsqueeze(1),
        # channel-major in the file: f_rest_{c (K-1) + k}
        sh_rest=columns(rest).reshape(count, 3, bands - 1).transpose(1, 2).contiguous(),
        opacity_logits=columns(["opacity"])[:, 0].contiguous(),
        log_scales=log_scales,
        quats=columns(["rot_0", "rot_1", "rot_2", "rot_3"]),
    )
    for name, tensor in out.items():
        if not torch.isfinite(tensor).all():
            bad = int((~torch.isfinite(tensor)).reshape(count, -1).any(dim=1).sum())
            raise PolarInputError(path, f"{bad} of {count} Gaussians have non-finite {name}")
    out.sh_degree, out.path, out.comments = degree, path, comments
    return out
