"""Load the anchor-line patch engine for ``adapters/<name>/patch.py`` without importing the package.

The engine (``polargs_plugin/kit/patching.py`` and ``kit/inria_anchors.py``) uses only the
standard library, but ``import polargs_plugin.kit`` would import torch: a patch script has to
run with a bare Python 3.8+, before the trainer's environment is complete. So the two modules are
imported from their folder as the submodules of a package of their own, :data:`PACKAGE`, whose
``__init__`` is never run. The folder is found next to this file: ``../src/polargs_plugin/kit`` in
a source checkout, ``../polargs_plugin/kit`` in an installed wheel.

A patch script reaches this file by its path (it is run as a script, not imported)::

    engine = runpy.run_path(str(Path(__file__).resolve().parents[1] / "patch_engine.py"))
    patching = engine["load"]("patching")
"""

import importlib
import sys
import types
from pathlib import Path

PACKAGE = "polargs_patch_engine"
"""Name under which the engine's modules are imported (``polargs_patch_engine.patching``)."""

MODULES = ("patching", "inria_anchors")
"""The modules of ``polargs_plugin/kit`` that make up the engine (standard library only)."""


def kit_folder() -> Path:
    """The folder holding ``patching.py``: the source checkout's or the installed package's kit."""
    here = Path(__file__).resolve().parent
    candidates = (here.parent / "src" / "polargs_plugin" / "kit", here.parent / "polargs_plugin" / "kit")
    for folder in candidates:
        if (folder / "patching.py").is_file():
            return folder
    raise ImportError(f"the patch engine (polargs_plugin/kit/patching.py) is in none of: {', '.join(map(str, candidates))}")


def load(name: str) -> types.ModuleType:
    """The engine module ``name`` (one of :data:`MODULES`), imported without ``polargs_plugin``."""
    if name not in MODULES:
        raise ValueError(f"{name!r} is not a module of the patch engine ({', '.join(MODULES)})")
    if PACKAGE not in sys.modules:
        package = types.ModuleType(PACKAGE)
        package.__path__ = [str(kit_folder())]
        sys.modules[PACKAGE] = package
    return importlib.import_module(f"{PACKAGE}.{name}")
