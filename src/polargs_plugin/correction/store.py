"""Where a run's :class:`~polargs_plugin.types.PolarMaps` live between their uses.

A view's maps take ~60 bytes per pixel as float32; for a real capture (tens of millions of
pixels) that is more than the images themselves. :class:`MapsStore` keeps them compact: the
float maps as float16 (the AoLP to 1.5e-3 rad, relative 4.9e-4 otherwise), the training colour
``intensity`` as float32 (PC's plain term must cancel the trainer's colour loss to the bit), the
masks as bool. With a cache folder (``PolarConfig.cache_dir``) each view's maps are a file,
read when the view is used; the last few read stay in memory within :data:`MEMORY_BUDGET`.
Without one they stay in memory, compact.

The cache file of a view is keyed by what the maps depend on (:func:`maps_cache_key`): its Stokes
and mask, the correction settings and :data:`CACHE_VERSION`.
"""

from __future__ import annotations

import json
import pickle
import re
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from polargs_plugin.config import PolarConfig
from polargs_plugin.io import atomic_torch_save
from polargs_plugin.types import PolarMaps, View, content_digest, describe_view

__all__ = ["CACHE_VERSION", "MEMORY_BUDGET", "BytesLRU", "MapsStore", "expanded_dtype", "maps_cache_key", "maps_cache_file",
           "compact_maps", "expand_maps", "tensor_bytes"]

#: Bumped when compute_polar_maps or the stored form changes for the same input: older cache files
#: are ignored. 2: the HDR white level, the rule between the DoLP ranges, the physical-cone
#: projection. 3: float16 values.
CACHE_VERSION = 3
#: Bytes of maps (and of other per-view constants built from them) kept in memory between uses.
MEMORY_BUDGET = 32 << 20

_MAP_FIELDS = ("aolp", "dolp", "intensity", "specular_mask", "overexposed_mask", "pri", "i_diff", "i_chro")
# Stored as float32: PC's plain colour term must cancel the trainer's, which reads the view's own Stokes.
_EXACT_FIELDS = ("intensity",)


def maps_cache_key(view: View, config: PolarConfig) -> str:
    """SHA-256 of what the maps depend on: Stokes, object mask, correction settings, cache version.

    Args:
        view: the view (its Stokes and mask are hashed, not its name or camera).
        config: settings; only ``config.correction`` enters the key.

    Returns:
        Hex digest.
    """
    settings = json.dumps({"version": CACHE_VERSION, "correction": asdict(config.correction)}).encode()
    return content_digest(view, settings)


def maps_cache_file(cache_dir: Path, view: View, key: str) -> Path:
    """Where a view's maps are cached: ``<cache_dir>/<name>-<key prefix>.pt``."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", view.name)[:80]
    return Path(cache_dir) / f"{stem}-{key[:24]}.pt"


def tensor_bytes(value: Any) -> int:
    """Bytes held by the tensors of ``value``: a tensor, a mapping or sequence of them, or an
    object's attributes (one level)."""
    if isinstance(value, Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, Mapping):
        return sum(tensor_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(tensor_bytes(v) for v in value)
    attributes = getattr(value, "__dict__", None)
    return 0 if attributes is None else sum(v.numel() * v.element_size() for v in attributes.values()
                                            if isinstance(v, Tensor))


def compact_maps(maps: PolarMaps) -> dict[str, Tensor]:
    """``{field: tensor}`` of the maps (``extras.<name>`` for extras) on the CPU, float values as
    float16 except ``intensity``."""
    entries = {name: getattr(maps, name) for name in _MAP_FIELDS if getattr(maps, name) is not None}
    entries.update({f"extras.{name}": value for name, value in maps.extras.items()})
    return {name: _compact_value(name, value) for name, value in entries.items()}


def _compact_value(name: str, value: Tensor) -> Tensor:
    value = value.detach().cpu()
    if value.is_floating_point() and name not in _EXACT_FIELDS:
        return value.to(torch.float16)
    return value


def expand_maps(data: Mapping[str, Tensor], device: torch.device | str = "cpu") -> PolarMaps:
    """The :class:`PolarMaps` of :func:`compact_maps`' output: float values as float32 on ``device``."""
    if any(name not in data for name in _MAP_FIELDS[:3]):
        raise KeyError("cache entry lacks aolp/dolp/intensity")

    def expanded(value: Tensor) -> Tensor:
        return value.to(device).to(expanded_dtype(value))

    extras = {name[len("extras."):]: expanded(value) for name, value in data.items() if name.startswith("extras.")}
    return PolarMaps(**{name: None if data.get(name) is None else expanded(data[name]) for name in _MAP_FIELDS},
                     extras=extras)


def expanded_dtype(value: Tensor) -> torch.dtype:
    """The dtype :func:`expand_maps` gives a stored map: float32 for float values, else its own."""
    return torch.float32 if value.is_floating_point() else value.dtype


def _entry_problem(data: Any, height: int, width: int) -> str | None:
    """Why a cache entry cannot be trusted for a view of ``height`` x ``width`` (None if it can)."""
    if not isinstance(data, dict) or any(name not in data for name in _MAP_FIELDS[:3]):
        return "not a maps entry (no aolp/dolp/intensity)"
    for name, value in data.items():
        if not isinstance(value, Tensor):
            return f"{name} is not a tensor"
        if value.ndim != 3 or tuple(value.shape[-2:]) != (height, width):
            return f"{name} has shape {tuple(value.shape)}, the view is {height}x{width}"
        if value.is_floating_point() and (value.dtype != torch.float16) != (name in _EXACT_FIELDS):
            return f"{name} is {value.dtype}, not the cache's dtype"
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            return f"{name} holds non-finite values (NaN or inf)"
    return None


class BytesLRU:
    """A least-recently-used cache bounded by the bytes of what it holds.

    Args:
        budget: the most bytes held; an entry larger than that is not kept.
        cycle: the number of keys the entries cycle through (e.g. the training views, visited in
            a random order), or None (unknown). An entry is then kept only when ``cycle`` entries
            of its size fit in the budget: a cache holding a few of many views in a random order
            would rarely hit and only hold memory (real-size images), while one holding every view
            always hits (small images).
    """

    def __init__(self, budget: int, cycle: int | None = None):
        self.budget = budget
        self._entries: OrderedDict[Any, tuple[Any, int]] = OrderedDict()
        self.bytes = 0
        self.cycle = cycle

    def set_cycle(self, cycle: int | None) -> None:
        """Set :attr:`cycle`, dropping what it no longer lets the cache keep."""
        self.cycle = cycle
        for key in [k for k, (_, size) in self._entries.items() if not self._fits(size)]:
            self.discard(key)

    def _fits(self, size: int) -> bool:
        return size * (self.cycle or 1) <= self.budget

    def get(self, key: Any) -> Any:
        """The entry of ``key`` (now the most recently used), or None."""
        if key not in self._entries:
            return None
        self._entries.move_to_end(key)
        return self._entries[key][0]

    def put(self, key: Any, value: Any, size: int) -> None:
        """Keep ``value`` (``size`` bytes), dropping the least recently used entries beyond the
        budget; nothing is kept when the entry does not fit (see ``cycle``)."""
        self.discard(key)
        if not self._fits(size):
            return
        self._entries[key] = (value, size)
        self.bytes += size
        while self.bytes > self.budget:
            _, (_, dropped) = self._entries.popitem(last=False)
            self.bytes -= dropped

    def discard(self, key: Any) -> None:
        if key in self._entries:
            self.bytes -= self._entries.pop(key)[1]

    def clear(self) -> None:
        self._entries.clear()
        self.bytes = 0


class MapsStore(Mapping[str, PolarMaps]):
    """Every view's :class:`PolarMaps`, compact: in the cache folder (read when used) or in memory.

    ``store[name]`` gives the view's maps in float32 on the view's device, decoded afresh.

    Args:
        folder: the cache folder, or None to keep the compact maps in memory.
        budget: bytes of compact maps read from the folder kept in memory between uses.
    """

    def __init__(self, folder: str | Path | None, budget: int = MEMORY_BUDGET):
        self.folder = None if folder is None else Path(folder)
        self._files: dict[str, Path] = {}
        self._memory: dict[str, dict[str, Tensor]] = {}
        self._devices: dict[str, torch.device] = {}
        self._dtypes: dict[str, torch.dtype] = {}  # what each view's maps decode to (their intensity's)
        self._recent = BytesLRU(budget)
        #: views whose maps were read from the folder's cache
        self.reused = 0
        #: ``{view name: why}`` for views whose cache entry existed but could not be used, and
        #: was computed again and overwritten
        self.rebuilt: dict[str, str] = {}

    def prepare(self, view: View, config: PolarConfig, compute: Callable[[], PolarMaps]) -> None:
        """Make ``store[view.name]`` available: from the cache when it holds a valid entry for this
        view and these settings, else ``compute()``-d now (and cached). A cache entry that cannot
        be trusted is recomputed and overwritten, with a warning that says why (recorded in
        :attr:`rebuilt`)."""
        self._devices[view.name] = view.device
        if self.folder is None:
            data = self._memory[view.name] = compact_maps(compute())
        else:
            path = maps_cache_file(self.folder, view, maps_cache_key(view, config))
            data, problem = self._read(path, view) if path.is_file() else (None, None)
            if problem is not None:
                self.rebuilt[view.name] = problem
                warnings.warn(f"{path}: cache entry of {describe_view(view)} rebuilt: {problem}", stacklevel=3)
            if data is None:
                data = compact_maps(compute())
                atomic_torch_save(data, path)
            else:
                self.reused += 1
            self._files[view.name] = path
            self._recent.put(view.name, data, tensor_bytes(data))
        self._dtypes[view.name] = expanded_dtype(data["intensity"])

    def _read(self, path: Path, view: View) -> tuple[dict[str, Tensor] | None, str | None]:
        """``(the entry, None)``, or ``(None, why it cannot be used)``."""
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except (OSError, RuntimeError, EOFError, KeyError, TypeError, pickle.UnpicklingError) as err:
            # the error's type only: torch's own text advises loading untrusted files unsafely
            return None, f"unreadable ({type(err).__name__}; cut short or overwritten?)"
        problem = _entry_problem(data, view.height, view.width)
        return (data, None) if problem is None else (None, problem)

    def compact(self, name: str) -> dict[str, Tensor]:
        """The stored (compact, CPU) maps of view ``name``."""
        if name in self._memory:
            return self._memory[name]
        data = self._recent.get(name)
        if data is None:
            data = torch.load(self._files[name], map_location="cpu", weights_only=True)
            self._recent.put(name, data, tensor_bytes(data))
        return data

    def __getitem__(self, name: str) -> PolarMaps:
        if name not in self._devices:
            raise KeyError(name)
        return expand_maps(self.compact(name), self._devices[name])

    def dtype(self, name: str) -> torch.dtype:
        """The dtype ``store[name]``'s intensity decodes to, without reading or decoding the maps."""
        return self._dtypes[name]

    def __contains__(self, name: object) -> bool:  # without decoding (Mapping's would)
        return name in self._devices

    def __iter__(self) -> Iterator[str]:
        return iter(self._devices)

    def __len__(self) -> int:
        return len(self._devices)

    def cycle_through(self, count: int) -> None:
        """The views are used in turns of ``count`` (a training's random order): keep compact maps
        read from the folder in memory only when all of them fit in the budget."""
        self._recent.set_cycle(count)

    def sequence(self, names: Sequence[str]) -> Sequence[PolarMaps]:
        """The maps of ``names`` as a sequence that decodes an entry when it is indexed."""
        return _LazyMaps(self, list(names))


class _LazyMaps(Sequence):
    """``store[names[i]]`` for each i, decoded when indexed (one view's maps at a time)."""

    def __init__(self, store: MapsStore, names: list[str]):
        self._store, self._names = store, names

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self._store[name] for name in self._names[index]]
        return self._store[self._names[index]]
