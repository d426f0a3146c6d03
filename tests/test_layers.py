"""The package's import graph, read with ``ast`` (module-level and function-level imports, absolute
and relative): every module imports only its own layer or lower ones, the adapter kit imports no
backend, and no imports run in a circle. Names imported through ``importlib.import_module`` are
not seen (the package's lazy re-exports use it; they point downwards)."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import pytest

import polargs_plugin

ROOT = "polargs_plugin"
PACKAGE_DIR = Path(polargs_plugin.__file__).parent

# Highest first. A component is a top-level sub-package or module of polargs_plugin; ROOT is the
# package's own __init__. A module may import its own layer and the layers below it.
LAYERS: list[set[str]] = [
    # the package's __init__: a facade re-exporting the config, PolarHooks and the contracts
    {ROOT},
    # the command-line front end: parses arguments, calls the layers below, prints
    {"cli"},
    # the ablation runner (grids of runs, reports)
    {"ablation"},
    # plain functions behind the CLI, the ablation, the examples and the adapters
    {"service"},
    # dry runs of upstream trainers: stand-ins of their CUDA extensions on the reference backend,
    # run inside the trainer's process (service.dryrun starts them; they use the kit and backends)
    {"dryrun"},
    # the adapter kit and the bundled reference backend (one way only: see WITHIN_LAYER_FORBIDDEN)
    {"kit", "backends"},
    # PolarHooks, what a trainer calls
    {"hooks"},
    # the PolarGS modules (losses, photometric correction, densification) and mesh evaluation
    {"losses", "correction", "densify", "depth_normal", "reflective_window", "scale_flatten", "ssim", "mesh", "metrics", "viz",
     "nearest"},
    # polarization optics, Gaussian geometry, the data contracts (and their compact storage) and the dataset readers
    {"optics", "geometry", "plane_depth", "types", "compact", "data"},
    # files and errors, configuration, the thread policy
    {"io", "config", "threads"},
]

# Imports between members of one layer that are not allowed (importer, imported).
WITHIN_LAYER_FORBIDDEN = {
    # the kit serves every trainer; the reference backend is one of them and may use the kit
    ("kit", "backends"),
}

class Edge(NamedTuple):
    importer: str  # dotted module name
    line: int
    imported: str  # dotted module name

    def __str__(self) -> str:
        return f"{self.importer}:{self.line} imports {self.imported}"


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package __init__) of every module of the package."""
    modules = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = (ROOT, *path.relative_to(PACKAGE_DIR).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        modules[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return modules


MODULES = _modules()


def _owner(name: str) -> str | None:
    """The module ``name`` lives in: itself, or the nearest package above it."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _targets(node: ast.AST, package: str) -> Iterator[str]:
    """Dotted names an import statement reaches (``from p import m`` reaches the module p.m when
    there is one, else p)."""
    if isinstance(node, ast.Import):
        yield from (alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
        else:
            base = node.module or ""
        for alias in node.names:
            yield f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base


def _edges() -> list[Edge]:
    edges = []
    for name, (path, is_package) in MODULES.items():
        package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            for target in _targets(node, package):
                imported = _owner(target) if target.split(".")[0] == ROOT else None
                if imported is not None and imported != name:
                    edges.append(Edge(name, node.lineno, imported))
    return sorted(set(edges))


EDGES = _edges()


def component(module: str) -> str:
    """The top-level sub-package or module of ``module`` (ROOT for the package's __init__)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT


def _layer(name: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if name in layer)


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the directed ``graph`` (its nodes in order, the first repeated), or None."""
    state: dict[str, str] = {}  # "open" while on the depth-first path, "done" after

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = "open"
        path = path + [node]
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":  # on the path: the path from it back to it is a cycle
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt, path)):
                return found
        state[node] = "done"
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start, [])):
            return found
    return None


def test_the_graph_sees_absolute_relative_and_function_level_imports() -> None:
    found = {(edge.importer, edge.imported) for edge in EDGES}
    assert ("polargs_plugin.kit.append", "polargs_plugin.geometry") in found  # module level, absolute
    assert ("polargs_plugin.backends.reference.rasterizer", "polargs_plugin.types") in found  # `from ...types`
    assert ("polargs_plugin.backends.reference.rasterizer", "polargs_plugin.backends.reference.composite_numba") in found  # in a function
    assert ("polargs_plugin.backends.reference.model", "polargs_plugin.kit.append") in found


def test_every_component_has_a_layer() -> None:
    placed = set().union(*LAYERS)
    missing = sorted({component(name) for name in MODULES} - placed)
    assert not missing, f"add these to a layer of LAYERS: {missing}"


def test_the_kit_imports_no_backend() -> None:
    wrong = [str(e) for e in EDGES if component(e.importer) == "kit" and component(e.imported) == "backends"]
    assert not wrong, "the adapter kit must not import a backend:\n" + "\n".join(wrong)


def test_modules_import_only_their_own_or_lower_layers() -> None:
    wrong = []
    for edge in EDGES:
        pair = (component(edge.importer), component(edge.imported))
        upward = _layer(pair[1]) < _layer(pair[0])
        if upward or pair in WITHIN_LAYER_FORBIDDEN:
            wrong.append(f"{edge}  ({pair[0]} -> {pair[1]})")
    assert not wrong, "imports against the layer order:\n" + "\n".join(wrong)


def test_no_import_cycle_between_components() -> None:
    graph: dict[str, set[str]] = {}
    for edge in EDGES:
        pair = (component(edge.importer), component(edge.imported))
        if pair[0] != pair[1]:
            graph.setdefault(pair[0], set()).add(pair[1])
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_import_cycle_between_modules() -> None:
    graph: dict[str, set[str]] = {}
    for edge in EDGES:
        graph.setdefault(edge.importer, set()).add(edge.imported)
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize(
    "graph, has_cycle",
    [
        ({"a": {"b"}, "b": {"c"}}, False),
        ({"a": {"b", "c"}, "b": {"c"}, "c": set()}, False),
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, True),
        ({"a": {"b"}, "b": {"b"}}, True),
        ({"x": {"a"}, "a": {"b"}, "b": {"a"}}, True),
    ],
)
def test_cycle_finder_on_small_graphs(graph: dict[str, set[str]], has_cycle: bool) -> None:
    cycle = _cycle(graph)
    assert (cycle is not None) == has_cycle
    if cycle is not None:
        assert cycle[0] == cycle[-1]
        assert all(b in graph[a] for a, b in zip(cycle, cycle[1:]))
