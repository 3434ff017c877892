"""The package layout: data flows one way. Every `ggns` import in src/ (at module level or inside a
function) is an edge of the import graph; the graph of modules has no cycle, and no two packages
import each other."""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import ggns

SRC = Path(ggns.__file__).resolve().parent


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, root: Path, modules: set[str]) -> set[str]:
    """The ggns modules that `path` imports anywhere in its body (a `from p import x` names module
    p.x when that is a module, else p)."""
    name = module_name(path, root)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else node.module
            found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return {m for m in found if m in modules and m != name}


def import_graph(root: Path = SRC) -> dict[str, set[str]]:
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    return {name: imported_modules(path, root, set(files)) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def package_of(module: str) -> str:
    """ggns.data.schema -> ggns.data; top-level modules (ggns.batch) are their own unit."""
    return ".".join(module.split(".")[:2])


def test_the_cycle_finder_finds_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_sees_relative_and_function_level_imports(tmp_path):
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    for name in ("pkg/__init__.py", "pkg/sub/__init__.py", "pkg/top.py"):
        (tmp_path / name).write_text("")
    (tmp_path / "pkg" / "sub" / "leaf.py").write_text("def f():\n    from ..top import x\n")
    (tmp_path / "pkg" / "top.py").write_text("from .sub import leaf\n")
    graph = import_graph(tmp_path / "pkg")
    assert graph["pkg.sub.leaf"] == {"pkg.top"} and graph["pkg.top"] == {"pkg.sub.leaf"}
    assert cycles(graph) == [["pkg.sub.leaf", "pkg.top"]]


def test_no_import_cycle_between_modules():
    assert cycles(import_graph()) == []


def test_no_two_packages_import_each_other():
    graph = import_graph()
    uses = defaultdict(set)
    for module, imported in graph.items():
        for other in imported:
            if package_of(other) != package_of(module):
                uses[package_of(module)].add(package_of(other))
    mutual = sorted({tuple(sorted((a, b))) for a in uses for b in uses[a] if a in uses.get(b, ())})
    assert mutual == []


def test_no_private_name_is_imported_across_modules():
    """A name with a leading underscore is its module's own; what another module needs is public."""
    private = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("ggns")):
                private += [f"{path.relative_to(SRC)}: {node.module}.{a.name}" for a in node.names
                            if a.name.startswith("_") and a.name != "__version__"]
    assert private == []


# the layers in import order (README "Layout"): each imports only layers listed before it
LAYERS = ("ggns", "ggns.errors", "ggns.phases", "ggns.checks", "ggns.trajectory", "ggns.batch", "ggns.geometry", "ggns.config", "ggns.reports", "ggns.checkpoints", "ggns.sim",
          "ggns.scenes", "ggns.sensors", "ggns.data", "ggns.graphs", "ggns.viz", "ggns.paraview", "ggns.evaluation", "ggns.models",
          "ggns.baselines", "ggns.pretrained", "ggns.online", "ggns.sweeps", "ggns.callbacks", "ggns.bench", "ggns.cli",
          "ggns.__main__")


def test_every_layer_imports_only_layers_before_it():
    graph = import_graph()
    assert {package_of(m) for m in graph} == set(LAYERS)  # a new package or module gets a place in the list
    upward = sorted(f"{m} -> {o}" for m, imported in graph.items() for o in imported
                    if LAYERS.index(package_of(o)) > LAYERS.index(package_of(m)))
    assert upward == []
