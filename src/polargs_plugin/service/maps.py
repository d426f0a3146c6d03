"""The PolarGS maps cache of a run: where it lives and which views it already holds."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from polargs_plugin.io import FolderLock, check_writable, remove_stale_temporaries_in

if TYPE_CHECKING:
    from polargs_plugin.config import PolarConfig
    from polargs_plugin.types import View

__all__ = ["MAPS_NAME", "PREPROCESSED_NAME", "MapsCache", "Preprocessed", "maps_entries", "prepare_maps_cache", "preprocess",
           "rebuilt_reasons"]

#: A run's maps cache: ``RUN_DIR/maps``.
MAPS_NAME = "maps"
#: ``polargs preprocess DATASET`` writes ``DATASET/preprocessed/maps``.
PREPROCESSED_NAME = "preprocessed"
#: The lock ``polargs preprocess`` holds in its output folder while it writes.
PREPROCESS_LOCK_NAME = "preprocess.lock"


@dataclass(frozen=True)
class MapsCache:
    """A run's maps cache.

    Attributes:
        folder: the cache folder (``PolarConfig.cache_dir``).
        cached: views whose maps were found there (or copied there) before training.
        copied_from: the ``polargs preprocess`` folder the cached maps were copied from, if any.
        given: whether the folder was chosen by the user (``--maps-cache``).
    """

    folder: Path
    cached: int
    total: int
    copied_from: Path | None = None
    given: bool = False

    def describe(self) -> str:
        """One line for the user: what is reused and what is computed."""
        if self.given:
            rest = "" if self.cached == self.total else ", the others computed now"
            return f"maps: {self.cached} of {self.total} views cached in {self.folder}{rest}"
        if self.copied_from is not None:
            return (f"maps: reused {self.cached} of {self.total} views from {self.copied_from} (`polargs preprocess`), "
                    f"copied into {self.folder}")
        if self.cached:
            return f"maps: reused {self.cached} of {self.total} views from {self.folder}"
        return f"maps: computing {self.total} views (cached in {self.folder})"


def maps_entries(views: Sequence[View], config: PolarConfig, folder: Path) -> dict[str, Path]:
    """``{view name: its cache file in folder}`` for the maps of ``config``."""
    from polargs_plugin.hooks import maps_cache_file, maps_cache_key

    return {view.name: maps_cache_file(folder, view, maps_cache_key(view, config)) for view in views}


def prepare_maps_cache(views: Sequence[View], config: PolarConfig, run_dir: Path, given: Path | None,
                       dataset: str) -> MapsCache:
    """Choose a run's maps cache and seed it.

    Args:
        views: the run's views.
        config: the run's PolarConfig (its correction settings key the maps).
        run_dir: the run folder; the default cache is ``run_dir/maps``.
        given: a cache chosen by the user (a folder of maps, or a ``polargs preprocess --out``
            folder holding ``maps/``), or None.
        dataset: the dataset as given; maps that ``polargs preprocess`` left in
            ``DATASET/preprocessed/maps`` are copied into the default cache.
    """
    if given is not None:
        folder = given / MAPS_NAME if (given / MAPS_NAME).is_dir() else given
        check_writable(folder)
        found = sum(path.is_file() for path in maps_entries(views, config, folder).values())
        return MapsCache(folder, found, len(views), given=True)
    folder = run_dir / MAPS_NAME
    entries = maps_entries(views, config, folder)
    found = sum(path.is_file() for path in entries.values())
    source_dir = Path(dataset) / PREPROCESSED_NAME / MAPS_NAME
    if found == len(views) or not source_dir.is_dir():
        return MapsCache(folder, found, len(views))
    copied = 0
    for target in entries.values():
        source = source_dir / target.name
        if not target.is_file() and source.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
            copied += 1
    return MapsCache(folder, copied, len(views), copied_from=source_dir) if copied else MapsCache(folder, found, len(views))


@dataclass
class Preprocessed:
    """The PC maps of a dataset, computed or read from the cache.

    Attributes:
        cache: the cache folder the maps live in.
        maps: one :class:`~polargs_plugin.types.PolarMaps` per view, in order.
        reused: views whose maps were read from the cache.
        pictures: the folder of the pictures written, or None.
        rebuilt: ``{view name: why}`` for cache entries that could not be used and were computed
            again.
        notes: one-line notes for the user (temporary files a killed run left, removed; a stale
            lock taken over).
    """

    cache: Path
    maps: list[Any]
    reused: int
    pictures: Path | None
    rebuilt: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line for the user: what was reused, computed and rebuilt, and why."""
        total = len(self.maps)
        line = f"maps: reused {self.reused} of {total} views from {self.cache}" if self.reused else f"maps: computed {total} views"
        if self.rebuilt:
            line += f"; rebuilt {len(self.rebuilt)} whose cache entry could not be used ({rebuilt_reasons(self.rebuilt)})"
        return line


#: How many rebuilt views :func:`rebuilt_reasons` names (the count is always given).
REBUILT_NAMED = 3


def rebuilt_reasons(rebuilt: dict[str, str]) -> str:
    """``view: why; ...`` for the first :data:`REBUILT_NAMED` views of a
    :attr:`~polargs_plugin.correction.store.MapsStore.rebuilt`, and how many more."""
    named = "; ".join(f"{name}: {why}" for name, why in list(rebuilt.items())[:REBUILT_NAMED])
    return named + (f"; {len(rebuilt) - REBUILT_NAMED} more" if len(rebuilt) > REBUILT_NAMED else "")


def preprocess(views: Sequence["View"], config: "PolarConfig", out: Path, pictures: bool = True,
               command: str = "") -> Preprocessed:
    """Compute (or reuse) the PC maps of ``views`` into ``out/maps`` and draw them into
    ``out/pictures`` (``polargs preprocess``); Dense is not prepared.

    ``out`` is locked meanwhile (:data:`PREPROCESS_LOCK_NAME`, ``command`` recorded in it), so
    that the temporary files a killed earlier run left in the cache can be removed first.

    Raises:
        PolarInputError: ``out`` is not writable, or the hooks refuse a view (naming it).
        FolderLockedError: another ``polargs preprocess`` writes ``out`` now.
    """
    from dataclasses import replace

    from polargs_plugin.hooks import PolarHooks
    from polargs_plugin.viz import save_map_pictures

    cache = out / MAPS_NAME
    config = replace(config, densify=replace(config.densify, enabled=False), cache_dir=str(cache))
    check_writable(out)
    with FolderLock(out / PREPROCESS_LOCK_NAME, command=command) as lock:
        notes = [f"note: {lock.note}"] if lock.note else []
        removed = remove_stale_temporaries_in(cache, ".pt")
        if removed:
            notes.append(f"note: {cache}: removed {len(removed)} temporary file(s) a killed run left")
        hooks = PolarHooks(config)
        maps = hooks.preprocess(list(views))
        folder = out / "pictures" if pictures else None
        if folder is not None:
            for view, view_maps in zip(views, maps):
                save_map_pictures(view_maps, folder, view.name)
    return Preprocessed(cache, maps, hooks.maps.reused, folder, dict(hooks.maps.rebuilt), notes)
