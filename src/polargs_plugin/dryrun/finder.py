"""The import hook that serves the stand-ins under the upstream module names.

:class:`StandinFinder` sits first on ``sys.meta_path`` of the dry-run process: ``import
diff_gaussian_rasterization`` (or ``from simple_knn._C import distCUDA2``) gets the stand-in module
named in its table, whatever is installed, and nothing is written anywhere. A name whose
sub-modules are also in the table is given a ``__path__`` so that ``import a.b`` works.
:func:`is_installed` says whether a module is importable from the environment itself, any
stand-in finder aside.

:func:`install_attributes` replaces single attributes of installed packages (gsplat's
``rasterization``), in the process's imported modules only.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
from types import ModuleType
from typing import Mapping, Sequence

__all__ = ["StandinFinder", "install_standins", "install_attributes", "is_installed"]


class _AliasLoader(importlib.abc.Loader):
    """Loads an upstream name as an existing module of this package."""

    def __init__(self, target: str, is_package: bool) -> None:
        self.target = target
        self.is_package = is_package

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(self.target)
        if self.is_package and not hasattr(module, "__path__"):
            module.__path__ = []  # type: ignore[attr-defined]  (lets `import name.sub` go on)
        return module

    def exec_module(self, module: ModuleType) -> None:
        """The target module is already executed."""


class StandinFinder(importlib.abc.MetaPathFinder):
    """Finds upstream module names in ``table`` (upstream name -> module of this package)."""

    def __init__(self, table: Mapping[str, str]) -> None:
        self.table = dict(table)

    def find_spec(self, fullname: str, path: Sequence[str] | None = None, target: ModuleType | None = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in self.table:
            return None
        is_package = any(name.startswith(fullname + ".") for name in self.table)
        loader = _AliasLoader(self.table[fullname], is_package)
        return importlib.machinery.ModuleSpec(fullname, loader, is_package=is_package)


def install_standins(table: Mapping[str, str]) -> StandinFinder:
    """Put a :class:`StandinFinder` for ``table`` first on ``sys.meta_path`` (dropping any upstream
    module of those names already imported); returns it (remove it from ``sys.meta_path`` to undo)."""
    for name in table:
        sys.modules.pop(name, None)
    finder = StandinFinder(table)
    sys.meta_path.insert(0, finder)
    return finder


def is_installed(name: str) -> bool:
    """Whether the top-level module ``name`` is importable here without a :class:`StandinFinder`
    (the finders of ``sys.meta_path`` asked in turn, the stand-in finders skipped; nothing imported)."""
    for finder in sys.meta_path:
        find_spec = getattr(finder, "find_spec", None)
        if isinstance(finder, StandinFinder) or find_spec is None:
            continue
        try:
            if find_spec(name, None) is not None:
                return True
        except (ImportError, ValueError):
            continue
    return False


def _resolve(path: str) -> tuple[ModuleType, str]:
    module, _, attribute = path.partition(":")
    return importlib.import_module(module), attribute


def install_attributes(table: Mapping[str, str]) -> list[tuple[ModuleType, str, object]]:
    """Replace ``"module:attribute"`` by the stand-in ``"module:attribute"`` of ``table`` (importing
    both); returns ``(module, attribute, original)`` per replacement, to undo it."""
    undo = []
    for upstream, standin in table.items():
        module, attribute = _resolve(upstream)
        owner, name = _resolve(standin)
        undo.append((module, attribute, getattr(module, attribute)))
        setattr(module, attribute, getattr(owner, name))
    return undo
