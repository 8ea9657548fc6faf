"""The architecture, enforced: no import circles in the three packages (``scenesplat_stereo``, ``sgmodel``,
``pipelines``), none between their stage folders, the floors between stages (docs/architecture.md), and every
module imports on its own.

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


def test_the_graph_sees_lazy_and_relative_imports(tmp_path):
    """On a small package written here: a relative import, ``from . import m`` inside a function, ``from P import
    m`` (an edge to the module P.m) and an import under ``if TYPE_CHECKING:`` (left out)."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for name, text in {"__init__.py": "", "config.py": "", "sub/__init__.py": "",
                       "args.py": "from .config import X\n",
                       "cli.py": "def f():\n    from . import args\n",
                       "sub/leaf.py": "from pkg import config\nfrom typing import TYPE_CHECKING\n"
                                      "if TYPE_CHECKING:\n    from pkg import cli\n"}.items():
        (pkg / name).write_text(text)
    found = {"pkg": pkg / "__init__.py", "pkg.config": pkg / "config.py", "pkg.args": pkg / "args.py",
             "pkg.cli": pkg / "cli.py", "pkg.sub": pkg / "sub" / "__init__.py", "pkg.sub.leaf": pkg / "sub" / "leaf.py"}
    graph = import_graph(found)
    assert graph["pkg.args"] == {"pkg.config"} and graph["pkg.cli"] == {"pkg.args"}
    assert graph["pkg.sub.leaf"] == {"pkg.config"}
    assert "scenesplat_stereo.shards.encode" in import_graph(modules())["scenesplat_stereo.shards.encode_pool"]
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


# --- The stages (docs/architecture.md): one folder per stage of the data flow.

#: stages that make and read a user's scene may never import how the model is trained, judged or timed
FLOORS = {("sgmodel.model", "sgmodel.pairs", "sgmodel.predict"): ("sgmodel.train", "sgmodel.evaluation", "sgmodel.bench")}
#: the only folders that import Warp or Triton (the rasteriser exports its launch helpers under public names)
GPU_FOLDERS = ("scenesplat_stereo.raster", "sgmodel.kernels")
#: test truth: the float64 twin of the rasteriser; read by tests and by the benchmarks that measure against it
TEST_TRUTH = "scenesplat_stereo.raster.reference"
TRUTH_READERS = ("scenesplat_stereo.raster.reference", "scenesplat_stereo.bench")
MAX_TOP_MODULES, MAX_FOLDER_MODULES = 8, 16


def stage(module: str) -> str:
    """The stage folder of a module (``sgmodel.model.layers`` -> ``sgmodel.model``); a package's top-level module
    is a stage of its own (``sgmodel.cli``, ``sgmodel.config``)."""
    return ".".join(module.split(".")[:2])


def stage_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for a, targets in graph.items():
        out.setdefault(stage(a), set()).update(stage(b) for b in targets if stage(b) != stage(a))
    return out


def test_no_circle_between_stage_folders():
    assert cycles(stage_graph(import_graph(modules()))) == []


def test_model_pairs_and_predict_never_import_training_evaluation_or_benches():
    graph = import_graph(modules())
    for lower, upper in FLOORS.items():
        bad = sorted((a, b) for a, targets in graph.items() if stage(a) in lower
                     for b in targets if stage(b) in upper)
        assert bad == [], f"stages {lower} import {upper}: {bad}"


def _imported_names(path: Path) -> set[str]:
    names = set()
    for node in _runtime_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
    return names


def test_only_the_rasteriser_and_the_kernels_import_warp_or_triton():
    bad = sorted(name for name, path in modules().items()
                 if _imported_names(path) & {"warp", "triton"} and not name.startswith(GPU_FOLDERS))
    assert bad == []


def test_nothing_outside_tests_and_benches_imports_the_float64_reference():
    graph = import_graph(modules())
    bad = sorted(a for a, targets in graph.items() if TEST_TRUTH in targets and not a.startswith(TRUTH_READERS))
    assert bad == []


def test_packages_stay_small_enough_to_read():
    """At most 8 modules at the top of a package and 16 in a folder (``__init__`` not counted)."""
    for package in PACKAGES:
        for folder in [ROOT / package, *(p.parent for p in (ROOT / package).rglob("__init__.py"))]:
            count = len([p for p in folder.glob("*.py") if p.name != "__init__.py"])
            limit = MAX_TOP_MODULES if folder == ROOT / package else MAX_FOLDER_MODULES
            assert count <= limit, f"{folder.relative_to(ROOT)} holds {count} modules (at most {limit})"


def test_every_stage_folder_says_what_it_does():
    """Each package's and folder's ``__init__.py`` opens with a docstring: what the stage does, its public names."""
    for name, path in modules().items():
        if path.name == "__init__.py":
            doc = ast.get_docstring(ast.parse(path.read_text()))
            assert doc and len(doc.split()) >= 8, f"{path.relative_to(ROOT)} has no docstring saying what it does"


def test_each_command_line_is_a_table_of_modules_with_add_arguments_and_run():
    from scenesplat_stereo.cli import COMMANDS as TOOLKIT
    from sgmodel.cli import COMMANDS as MODEL

    def leaves(commands):
        for c in commands:
            yield from leaves(c.commands) if c.commands else [c]

    for command in [*leaves(TOOLKIT), *leaves(MODEL)]:
        module = importlib.import_module(command.module)
        assert callable(getattr(module, "add_arguments", None)) and callable(getattr(module, "run", None)), command
