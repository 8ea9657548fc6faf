"""No import circles in the three packages (``scenesplat_stereo``, ``sgmodel``, ``pipelines``), and every module
imports on its own.

The graph is built from the source with ``ast``: an edge A -> B for every ``import B`` / ``from B import x``
anywhere in A (at the top or inside a function: a lazy import that closes a circle is still a circle), with
relative imports resolved, and ``from P import m`` counted as an edge to the module ``P.m`` when m is one;
imports under ``if TYPE_CHECKING:`` (for annotations, never run) are left out.
"""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("scenesplat_stereo", "sgmodel", "pipelines")


def modules() -> dict[str, Path]:
    """Dotted name -> file of every module of the three packages (a package is its ``__init__.py``)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except the bodies of ``if TYPE_CHECKING:`` (imports for annotations only,
    which never run)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def import_graph(found: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules of the three packages it imports (see the module docstring)."""
    graph: dict[str, set[str]] = {}
    for name, path in found.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = set()
        for node in _runtime_nodes(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in found else base for alias in node.names]
            else:
                continue
            edges |= {t for t in targets if t in found and t != name}
        graph[name] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_lazy_and_relative_imports():
    graph = import_graph(modules())
    assert "sgmodel.config" in graph["sgmodel.args"]  # from .config import ...
    assert "sgmodel.train.loop" in graph["sgmodel.cli"]  # from . import train, inside a function
    assert "scenesplat_stereo.shards.encode" in graph["scenesplat_stereo.shards.encode_pool"]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circles():
    assert cycles(import_graph(modules())) == []


def test_the_benches_and_the_command_line_do_not_import_each_other():
    graph = import_graph(modules())
    assert not any(m.startswith("sgmodel.cli") for b in graph if b.startswith("sgmodel.bench") for m in graph[b])
    assert "scenesplat_stereo.shards.encode_pool" not in graph["scenesplat_stereo.shards.encode"]


@pytest.mark.parametrize("name", [m for m in modules() if m.startswith("pipelines") or m.endswith(("cli", "args"))])
def test_each_entry_module_imports_alone(name):
    """A fresh interpreter imports the module first (no other module of ours loaded before it)."""
    done = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True, text=True, cwd=ROOT,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]


def test_every_module_imports():
    """Every module imports, but for one that needs an optional package absent here (triton on a CPU machine)."""
    for name in modules():
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as e:
            assert e.name.split(".")[0] not in PACKAGES, f"{name}: {e}"
