"""The lab's modules import one another without cycles, at the top or inside functions.

A function-level import can hide a cycle (``bench`` and ``bench_mpi`` imported each
other that way while the machine facts sat in ``bench``); this graph counts every
import statement of ``prdp_petsc/lab`` wherever it stands, except under
``TYPE_CHECKING``.  An edge from a module to a package that contains it is left out:
Python initialises a package before any of its modules, so it orders nothing.
"""

import ast
from pathlib import Path

LAB = Path(__file__).resolve().parents[2] / "prdp_petsc" / "lab"


def _modules() -> dict[str, Path]:
    out = {}
    for path in LAB.rglob("*.py"):
        parts = ("prdp_petsc", *path.relative_to(LAB.parent).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(name: str, path: Path, modules) -> set[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    hidden = {  # imports under `if TYPE_CHECKING:` run for type checkers only
        id(n)
        for block in ast.walk(ast.parse(path.read_text()))
        if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
        for n in ast.walk(block)
    }
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module
            if node.level:  # from . import x, from ..provenance import y
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            targets = [module, *(f"{module}.{a.name}" for a in node.names)]
        else:
            continue
        if id(node) not in hidden:
            found.update(t for t in targets if t in modules and not name.startswith(t + "."))
    return found - {name}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan)."""
    index, low, stack, groups = {}, {}, [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            groups.append(sorted(group))

    for v in graph:
        if v not in index:
            visit(v)
    return [g for g in groups if len(g) > 1]


def test_the_lab_has_no_import_cycle():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert sum(map(len, graph.values())) > 100  # the graph was read, not empty
    assert _cycles(graph) == []


def test_a_cycle_is_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
