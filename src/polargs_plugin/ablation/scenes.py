"""Scenes of an ablation grid: bundled synthetic scenes (generated once into a cache folder) or
dataset folders with a ground-truth mesh.

Spelling on the command line (``polargs ablate --scenes``, comma-separated):

- ``glossy_plane_sphere``: a bundled scene (``polargs generate --help`` lists them), generated
  with ``--views`` / ``--size`` into ``<cache>/<name>-<V>v-<W>x<H>-s<seed>-g<generator version>/``
  (reused when present; the folder appears complete or not at all);
- ``family:K``: the procedural family's scene of seed K (docs/scene-family.md), named
  ``family-K``, with its own views and size unless ``--views`` / ``--size`` are given, generated
  into ``<cache>/family-K-<V>v-<W>x<H>-g<generator version>/`` in the same way;
- ``NAME=PATH:GT_MESH``: a dataset folder in any supported format and its ground-truth mesh;
- ``NAME=PATH`` or ``PATH``: the ground-truth mesh is the first of :data:`GT_MESH_NAMES` found in
  the folder (``gt_mesh.ply``, then ``mesh.ply``, which the project's own scene format ships).
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from polargs_plugin.io import PolarInputError
from polargs_plugin.service.evaluation import GT_MESH_NAMES

__all__ = ["SceneSpec", "GT_MESH_NAMES", "parse_scene", "ensure_scene", "gt_mesh_path", "bundled_names"]

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")


def bundled_names() -> tuple[str, ...]:
    from polargs_plugin.data.scenes import SCENE_BUILDERS

    return tuple(SCENE_BUILDERS)


@dataclass(frozen=True)
class SceneSpec:
    """One scene as plain data.

    Attributes:
        name: short name used in run names and tables.
        path: dataset folder (for a bundled scene: the cache folder it is generated into).
        gt_mesh: ground-truth mesh file, or None to look for :data:`GT_MESH_NAMES` in ``path``.
        bundled: the generator's scene name for a bundled scene (``family`` for a family scene), else None.
        views, width, height, seed: generation settings of a bundled scene (the seed of a family
            scene is its family seed).
    """

    name: str
    path: str
    gt_mesh: str | None = None
    bundled: str | None = None
    views: int = 24
    width: int = 128
    height: int = 128
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SceneSpec":
        return cls(**data)


def parse_scene(text: str, cache_dir: str | os.PathLike, views: int | None = None, width: int | None = None,
                height: int | None = None) -> SceneSpec:
    """A :class:`SceneSpec` from its command-line spelling (module docstring); ``views``, ``width``
    and ``height`` of a generated scene, None for its own (24 views of 128x128 for a bundled scene,
    the seed's for a family scene).

    A path that does not exist is accepted here: its cells fail with a log, the rest of the grid
    runs. Raises ValueError for a malformed entry (empty, bad name: other characters than
    letters, digits, ``_ . -``, or a leading ``.``, which would hide its run folders).
    """
    text = text.strip()
    if not text:
        raise ValueError("empty scene entry")
    if "=" not in text and text in bundled_names():
        from polargs_plugin.data.synthetic import GENERATOR_VERSION

        views, width, height = views or 24, width or 128, height or 128
        # the generator's version in the name: a cache never hands out an older generator's scene
        folder = Path(cache_dir).resolve() / f"{text}-{views}v-{width}x{height}-s0-g{GENERATOR_VERSION}"
        return SceneSpec(text, str(folder), None, text, views, width, height, 0)
    from polargs_plugin.data.family import FAMILY

    if "=" not in text and text.startswith(f"{FAMILY}:"):
        return _family_scene(text, cache_dir, views, width, height)
    name, _, rest = text.partition("=") if "=" in text else ("", "", text)
    gt = None
    if ":" in rest and Path(rest).exists() is False:
        rest, gt = rest.rsplit(":", 1)
    if not rest:
        raise ValueError(f"scene '{text}': no dataset path")
    path = Path(rest)
    name = name or path.resolve().name
    if not _NAME_RE.match(name):
        raise ValueError(f"scene '{text}': name '{name}' may only hold letters, digits, '_', '.', '-'")
    if name.startswith("."):  # its run folders would be hidden ones, which gather and --status skip
        raise ValueError(f"scene '{text}': name '{name}' starts with '.'; give another name (NAME=PATH)")
    return SceneSpec(name, str(path.resolve()), str(Path(gt).resolve()) if gt else None)


def _family_scene(text: str, cache_dir: str | os.PathLike, views: int | None, width: int | None,
                  height: int | None) -> SceneSpec:
    """The :class:`SceneSpec` of ``family:K``; ValueError when K is not a seed."""
    from polargs_plugin.data.family import FAMILY, family_name, family_settings, parse_family
    from polargs_plugin.data.synthetic import GENERATOR_VERSION

    seed = parse_family(text)
    if seed is None:
        raise ValueError(f"scene '{text}': a family scene is family:SEED with SEED an integer >= 0")
    settings = family_settings(seed)
    views, width, height = views or settings.num_views, width or settings.size, height or settings.size
    name = family_name(seed)
    folder = Path(cache_dir).resolve() / f"{name}-{views}v-{width}x{height}-g{GENERATOR_VERSION}"
    return SceneSpec(name, str(folder), None, FAMILY, views, width, height, seed)


def ensure_scene(spec: SceneSpec, progress: bool = False) -> Path:
    """The scene's dataset folder; a bundled scene is generated first if its folder is missing.

    Generation writes a temporary folder beside it and renames it: concurrent callers (parallel
    cells, cluster jobs) never see a half-written scene; the first rename wins.
    """
    folder = Path(spec.path)
    if spec.bundled is None or folder.is_dir():
        return folder
    from polargs_plugin.data.family import FAMILY
    from polargs_plugin.service.scenes import SceneRequest, generate_scene_folder

    if spec.bundled not in (*bundled_names(), FAMILY):
        raise PolarInputError(folder, f"unknown bundled scene '{spec.bundled}' (known: {', '.join(bundled_names())}, {FAMILY})")
    request = SceneRequest(spec.bundled, views=spec.views, width=spec.width, height=spec.height, seed=spec.seed)
    return generate_scene_folder(request, folder, progress=progress).folder


def gt_mesh_path(spec: SceneSpec) -> Path:
    """The ground-truth mesh file of a scene; raises PolarInputError naming what was tried."""
    if spec.gt_mesh:
        path = Path(spec.gt_mesh)
        if not path.is_file():
            raise PolarInputError(path, "ground-truth mesh not found")
        return path
    for name in GT_MESH_NAMES:
        path = Path(spec.path) / name
        if path.is_file():
            return path
    raise PolarInputError(
        spec.path, f"no ground-truth mesh: give it as {spec.name}=PATH:GT_MESH or put {GT_MESH_NAMES[0]} in the folder"
    )
