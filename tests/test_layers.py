"""The import graph runs one way, down the layers docs/DESIGN.md draws.

Every ``import`` of a bigT module by another (at the top of a file or inside a
function: a loop held open by a late import is still a loop) is read from the source
with ``ast``. A package may import its own modules and those of the layers below it,
never one above or beside it; no two modules import each other, directly or through
others; no module imports a private (``_name``) module of another subpackage.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "bigT"

#: The layers, lowest first, as docs/DESIGN.md draws them. A unit imports only units
#: of lower layers (and itself).
LAYERS = [
    {"errors", "pools"},  # pools: the process's named thread pools (kernels, fsyncs)
    # the package root re-exports the API lazily (importlib, at first use): statically
    # it imports only errors, and the CLI reads its __version__
    {"config", "atomic", "sizes", "progress", "colour", "__init__"},
    {"images", "metrics", "figures", "kernels"},
    {"calibration"},  # radiometric responses, HDR merge: draws through figures
    {"storage"},
    {"schedule", "spectral"},
    {"algorithms", "scenes"},
    {"compensation"},
    {"acquisition"},
    {"cli", "warm", "testing"},
]
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, name: str) -> set[str]:
    """The bigT modules (or packages) ``path`` imports, anywhere in the file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "bigT")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "bigT":
                continue
            for alias in node.names:  # "from .storage import frames" names a module
                found.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in MODULES
                          else target)
    return found


MODULES = {_module_name(p): p for p in ROOT.rglob("*.py")}
GRAPH = {name: _imports(path, name) - {name} for name, path in MODULES.items()}


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in MODULES}
    assert units <= set(RANK), f"not in any layer: {sorted(units - set(RANK))}"


def upward_imports(graph: dict[str, set[str]], module: str) -> list[str]:
    """The imports of ``module`` that reach a layer at or above its own."""
    return sorted(t for t in graph[module] if _unit(t) != _unit(module)
                  and RANK[_unit(t)] >= RANK[_unit(module)])


def private_imports(graph: dict[str, set[str]], module: str) -> list[str]:
    """The private (``_name``) modules of other subpackages that ``module`` imports."""
    return sorted(t for t in graph[module] if t.rpartition(".")[2].startswith("_")
                  and not t.endswith("__init__") and _unit(t) != _unit(module))


def find_cycle(graph: dict[str, set[str]], packages: set[str]) -> list[str] | None:
    """A cycle of module imports (as a path that returns to its start), or None. A
    package's ``__init__`` re-exporting its own modules is not counted as an edge."""
    edges = {m: {t for t in ts if t in graph and not (m in packages and t.startswith(m + "."))}
             for m, ts in graph.items()}
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if t not in state:
                found = visit(t, stack + [t])
                if found:
                    return found
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state:
            found = visit(m, [m])
            if found:
                return found
    return None


PACKAGES = {m for m, p in MODULES.items() if p.name == "__init__.py"}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_layers(module):
    upward = upward_imports(GRAPH, module)
    assert not upward, f"{module} imports a layer at or above its own: {upward}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_private_module_of_another_subpackage(module):
    private = private_imports(GRAPH, module)
    assert not private, f"{module} imports private modules of other subpackages: {private}"


def test_no_import_cycle_between_modules():
    cycle = find_cycle(GRAPH, PACKAGES)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_checks_catch_a_loop_an_upward_import_and_a_private_one():
    """Each check fails on a graph with the fault planted: the reader importing the
    writer back (the loop this issue removed), storage importing compensation, and
    algorithms importing compensation's private module."""
    graph = {m: set(ts) for m, ts in GRAPH.items()}
    assert find_cycle(graph, PACKAGES) is None
    graph["bigT.storage.block_csr"].add("bigT.storage.writer")  # writer imports block_csr
    assert "bigT.storage.block_csr" in GRAPH["bigT.storage.writer"]
    cycle = find_cycle(graph, PACKAGES)
    assert cycle is not None and {"bigT.storage.block_csr", "bigT.storage.writer"} <= set(cycle)

    graph = {m: set(ts) for m, ts in GRAPH.items()}
    graph["bigT.storage.block_csr"].add("bigT.compensation")
    assert upward_imports(graph, "bigT.storage.block_csr") == ["bigT.compensation"]
    graph["bigT.algorithms.target"].add("bigT.compensation._resident_kernels")
    assert private_imports(graph, "bigT.algorithms.target") == [
        "bigT.compensation._resident_kernels"]
    assert "bigT.compensation._resident_kernels" in upward_imports(graph, "bigT.algorithms.target")
