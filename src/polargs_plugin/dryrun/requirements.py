"""What a checkout's training script imports that this environment lacks, found before any run.

:func:`required_imports` reads the script with :mod:`ast` and follows the checkout's own modules
it imports, transitively (absolute and relative imports, packages with or without
``__init__.py``). An import is required when it runs whenever its module is imported: at module
level, in a class body or a ``with`` block, and in the script's ``if __name__ == "__main__":``
block. Imports inside ``try:`` (optional upstream), under any other ``if`` and inside functions
are not required, and the checkout's modules they name are not followed.

:func:`missing_modules` keeps the top-level modules that are neither the checkout's own, nor
the standard library, nor served by the dry run (:func:`..trainers.served_modules`), nor
installed; :func:`install_command` is one command line that installs them.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from typing import Iterator, Mapping

from polargs_plugin.dryrun.finder import is_installed

__all__ = ["required_imports", "missing_modules", "install_command", "PIP_NAMES"]

#: Import name -> PyPI name, where they differ (for the names upstream trainers import).
PIP_NAMES = {
    "cv2": "opencv-python-headless",
    "skimage": "scikit-image",
    "PIL": "pillow",
    "yaml": "pyyaml",
    "sklearn": "scikit-learn",
}

#: Packages pip must not take from PyPI as they are: torchvision must match the installed torch
#: build (:func:`_torchvision_command`); pytorch3d has no wheels for torch 2.x and compiles.
_OWN_COMMANDS = {
    "pytorch3d": '-m pip install --no-build-isolation "git+https://github.com/facebookresearch/pytorch3d.git@stable"',
}

_STANDARD = frozenset(sys.stdlib_module_names) | frozenset(sys.builtin_module_names)


def _is_main_guard(test: ast.expr) -> bool:
    """``__name__ == "__main__"`` (either way round)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = [test.left, *test.comparators]
    names = [s for s in sides if isinstance(s, ast.Name) and s.id == "__name__"]
    mains = [s for s in sides if isinstance(s, ast.Constant) and s.value == "__main__"]
    return len(names) == 1 and len(mains) == 1


def _required(body: list[ast.stmt], script: bool) -> Iterator[ast.Import | ast.ImportFrom]:
    """The imports of ``body`` that run whenever it runs (module docstring)."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, (ast.ClassDef, ast.With, ast.AsyncWith)):
            yield from _required(node.body, script)
        elif isinstance(node, ast.If) and script and _is_main_guard(node.test):
            yield from _required(node.body, script)


class _Checkout:
    """The checkout's own modules: dotted name -> files that importing it runs."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def is_own(self, top: str) -> bool:
        base = self.root / top
        return base.with_suffix(".py").is_file() or base.is_dir() or any(self.root.glob(f"{top}.*.so"))

    def files(self, dotted: str) -> list[Path]:
        """The checkout's files that ``import dotted`` runs: each package's ``__init__.py`` on the
        way, then the module (as far as the checkout has them)."""
        found, folder = [], self.root
        for part in dotted.split("."):
            module, package = folder / f"{part}.py", folder / part
            if package.is_dir():
                init = package / "__init__.py"
                found += [init] if init.is_file() else []
                folder = package
            elif module.is_file():
                found.append(module)
                break
            else:
                break
        return found

    def dotted(self, path: Path) -> tuple[str, bool]:
        """The dotted name of a file of the checkout and whether it is a package's ``__init__``."""
        parts = path.relative_to(self.root).with_suffix("").parts
        return (".".join(parts[:-1]), True) if parts[-1] == "__init__" else (".".join(parts), False)


def _imported_names(node: ast.Import | ast.ImportFrom, checkout: _Checkout, path: Path, script: bool
                    ) -> Iterator[str]:
    """The dotted module names an import statement imports (``from M import a`` also ``M.a``, which
    may be a sub-module); relative names resolved against ``path``'s package."""
    if isinstance(node, ast.Import):
        yield from (alias.name for alias in node.names)
        return
    module = node.module or ""
    if node.level:
        if script:
            return  # a script run as __main__ has no package: the run fails at once anyway
        own, is_init = checkout.dotted(path)
        package = own.split(".") if is_init else own.split(".")[:-1]
        if node.level - 1 >= len(package):
            return  # beyond the top-level package: the run fails there
        base = package[:len(package) - (node.level - 1)]
        module = ".".join([*base, *filter(None, [module])])
    yield module
    yield from (f"{module}.{alias.name}" for alias in node.names if alias.name != "*")


def required_imports(checkout: Path, script: Path) -> dict[str, str]:
    """Dotted module name -> ``file:line`` where it is first imported, of every module outside the
    checkout that ``script`` and the checkout's modules it imports require (module docstring)."""
    own = _Checkout(checkout)
    found: dict[str, str] = {}
    seen: set[Path] = set()
    queue = [(script, True)]
    while queue:
        path, is_script = queue.pop(0)
        if path in seen:
            continue
        seen.add(path)
        try:
            tree = ast.parse(path.read_bytes(), filename=str(path))
        except (OSError, SyntaxError, ValueError):
            continue  # the run names it
        where = path.name if is_script else path.relative_to(checkout).as_posix()
        for node in _required(tree.body, is_script):
            names = list(_imported_names(node, own, path, is_script))
            if isinstance(node, ast.ImportFrom) and names and not own.is_own(names[0].split(".")[0]):
                names = names[:1]  # another package's `from M import a`: M is what must be installed
            for name in names:
                if own.is_own(name.split(".")[0]):
                    queue += [(file, False) for file in own.files(name)]
                else:
                    found.setdefault(name, f"{where}:{node.lineno}")
    return found


def _served(name: str, served: Mapping[str, str]) -> bool:
    """Whether the dry run's stand-ins answer ``import name`` (it or a package above one)."""
    return name in served or any(key.startswith(name + ".") for key in served)


def missing_modules(checkout: Path, script: Path, served: Mapping[str, str]) -> list[str]:
    """The top-level modules ``script`` requires (:func:`required_imports`) that are not the
    standard library, not served (``served``: upstream name -> stand-in) and not installed; sorted."""
    missing = set()
    for name in required_imports(checkout, script):
        top = name.split(".")[0]
        if top in _STANDARD:
            continue
        if top in served and _served(name, served):
            continue
        if not is_installed(top):
            missing.add(top)
    return sorted(missing, key=str.lower)


def _torchvision_command(python: str) -> str:
    """torchvision for the installed torch: pinning torch keeps pip from replacing it, and torch's
    own wheel index of its build (``+cpu``, ``+cu121``, ...) has the torchvision that fits it."""
    import torch

    version = torch.__version__
    build = version.partition("+")[2]
    index = f" --index-url https://download.pytorch.org/whl/{build}" if build else ""
    return f'{python} -m pip install torchvision "torch=={version}"{index}'


def install_command(names: list[str], python: str | None = None) -> str:
    """One command line that installs the modules ``names`` for ``python`` (default: this
    interpreter): their PyPI names (:data:`PIP_NAMES`) in one ``pip install``, torchvision and
    pytorch3d each in a command of their own, joined by ``&&``."""
    python = python or sys.executable
    plain = [PIP_NAMES.get(name, name) for name in names if name not in ("torchvision", *_OWN_COMMANDS)]
    commands = [f"{python} -m pip install {' '.join(plain)}"] if plain else []
    if "torchvision" in names:
        commands.append(_torchvision_command(python))
    commands += [f"{python} {_OWN_COMMANDS[name]}" for name in names if name in _OWN_COMMANDS]
    return " && ".join(commands)
