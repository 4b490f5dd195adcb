"""The package's layers, read from the source: the config layer (splatdeform.edit) is the only
one that knows the edit config, and every import points down the data flow.

    errors, interrupts, blas < model, geometry, resources < io, rbf, info, memory < basis < deform
    < render < edit < editor, batch < cli

(import statements anywhere in a module count, lazy ones inside functions too).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "splatdeform"
RANK = {"errors": 0, "lazy": 0, "interrupts": 0, "blas": 0, "progress": 0, "dask_client": 0,
        "suggest": 0, "model": 1, "geometry": 1,
        "resources": 1, "io": 2, "rbf": 2, "info": 2, "memory": 2, "basis": 3, "deform": 4,
        "render": 5, "edit": 6, "editor": 7, "batch": 7, "field": 7, "field_schema": 7,
        "field_apply": 7, "conversion": 8, "verbs": 8, "examples": 8,
        "cli": 8}
CONFIG_LAYER = "edit"
BELOW_CONFIG = [name for name, rank in RANK.items() if rank < RANK[CONFIG_LAYER]]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path) -> set[str]:
    """Every module name ``path`` imports (relative imports resolved; ``from a import b`` gives
    ``a`` and ``a.b``)."""
    mod = module_name(path).split(".")
    base = mod if path.name == "__init__.py" else mod[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parent = base[:len(base) - node.level + 1]
                name = ".".join(parent + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.add(name)
            found.update(f"{name}.{a.name}" for a in node.names)
    return found


def layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "splatdeform" and len(parts) > 1 and parts[1] in RANK else None


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.parent != PACKAGE or p.stem != "__init__")


def test_every_module_sits_in_a_layer():
    unplaced = [module_name(p) for p in MODULES if layer(module_name(p)) is None]
    assert not unplaced, f"modules outside the layer table: {unplaced}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: module_name(p))
def test_imports_point_down_the_flow(path):
    own = layer(module_name(path))
    upward = sorted(m for m in imported(path)
                    if (other := layer(m)) is not None and RANK[other] > RANK[own])
    assert not upward, f"{module_name(path)} ({own}) imports a higher layer: {upward}"


def test_nothing_below_the_config_layer_knows_the_config():
    """No module of errors/model/io/rbf/basis/deform/render imports the config models, the
    selector entries, units or pydantic/YAML."""
    offenders = {}
    for path in MODULES:
        if layer(module_name(path)) not in BELOW_CONFIG:
            continue
        bad = sorted(m for m in imported(path)
                     if m.startswith(("splatdeform.edit", "pydantic", "yaml")))
        if bad:
            offenders[module_name(path)] = bad
    assert not offenders, offenders


def test_the_graph_reader_sees_lazy_imports():
    """The checks above would be empty if the reader missed imports inside functions."""
    found = imported(PACKAGE / "edit" / "run.py")
    assert "splatdeform.edit.cache" in found  # imported inside run_edit
    assert "splatdeform.deform" in found


def import_graph(package: str) -> dict[str, list[str]]:
    """Module -> the modules of ``package`` it imports (lazy imports count, and so do imports
    under ``if TYPE_CHECKING:``: a module that names another's types for its hints depends on
    it as much, even if Python never runs that import). One exception: a type-only import of
    the module's own package (``edit/selectors/not_.py`` names the union ``SelectorCfg`` of
    its package, which imports it: one recursive type). ``from pkg import sub`` of a submodule
    is an edge to ``pkg.sub`` only (Python finds a submodule while ``pkg`` is still
    initialising); of any other name, an edge to ``pkg``."""
    names = {module_name(p): p for p in MODULES + [PACKAGE / "__init__.py"]
             if module_name(p) == package or module_name(p).startswith(package + ".")}

    def typing_only(tree: ast.AST) -> set[ast.AST]:
        return {n for node in ast.walk(tree) if isinstance(node, ast.If)
                and "TYPE_CHECKING" in ast.unparse(node.test)
                for stmt in node.body for n in ast.walk(stmt)}

    def edges(m: str, path: Path) -> set[str]:
        tree = ast.parse(path.read_text())
        typing = typing_only(tree)
        mod = m.split(".")
        base = mod if path.name == "__init__.py" else mod[:-1]
        own_packages = {".".join(mod[:i]) for i in range(1, len(mod))}
        found = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                new = {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                name = (".".join(base[:len(base) - node.level + 1]
                                 + ([node.module] if node.module else []))
                        if node.level else node.module or "")
                subs = {f"{name}.{a.name}" for a in node.names}
                new = subs & names.keys() if subs <= names.keys() else subs | {name}
            else:
                continue
            found.update(new - own_packages if node in typing else new)
        return {x for x in found if x in names and x != m}

    return {m: sorted(edges(m, p)) for m, p in names.items()}


def find_cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """The cycles a depth-first walk of ``graph`` meets, each as its modules in import order;
    [] when the graph is acyclic."""
    cycles, state = [], {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = "open"
        for x in graph[m]:
            if state.get(x) == "open":
                cycles.append(path[path.index(x):] + [x])
            elif x not in state:
                visit(x, path + [x])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    return cycles


def test_no_import_cycle():
    """No module of the package imports itself back through others (lazy and type-only
    imports count: a cycle would need one to work at all, and a module whose hints name
    another's types depends on it). editor/saving.py reads the controller through the
    EditorState protocol it declares, not the controller's class. edit/run.py decides
    stream-or-not and calls edit/stream/, which builds its result in edit/result.py; the splat
    readers build their model in io/splat_model.py above both io/splats.py and io/ply.py; the
    batch worker owns the messages the runner also reports."""
    assert find_cycles(import_graph("splatdeform")) == []


def test_the_cycle_finder_finds_cycles():
    """The check above would pass vacuously if the finder missed cycles or the edges."""
    assert find_cycles({"a": ["b"], "b": ["c"], "c": ["a"]}) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": ["b", "c"], "b": ["c"], "c": []}) == []
    graph = import_graph("splatdeform.edit")
    assert "splatdeform.edit.stream" in graph["splatdeform.edit.run"]
    assert "splatdeform.edit.result" in graph["splatdeform.edit.stream"]
    whole = import_graph("splatdeform")
    # type-only imports are edges (batch/thumbnails.py names EditResult for its hints only;
    # editor/saving.py importing editor/controller.py so was the one circle of issue 44) ...
    assert "splatdeform.edit.result" in whole["splatdeform.batch.thumbnails"]
    # ... except a module's type-only import of its own package (a recursive type)
    assert "splatdeform.edit.selectors" not in whole["splatdeform.edit.selectors.not_"]


def test_no_module_above_500_lines_but_the_format_readers() -> None:
    """Small modules with one job each: only the format readers in io/ may be longer."""
    long = [str(p.relative_to(PACKAGE.parent)) for p in PACKAGE.rglob("*.py")
            if len(p.read_text().splitlines()) > 500
            and not (p.parent.name == "io" and p.parent.parent == PACKAGE)]
    assert not long, long


def test_no_test_module_imports_another() -> None:
    """Shared test code lives in helpers.py / fixtures.py (and the oracles), never in a test
    module that another imports (importing one runs its module-level fixtures twice)."""
    tests = Path(__file__).resolve().parent
    offenders = []
    for path in sorted(tests.glob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{path.name}: {n}" for n in names if n.startswith("test_")]
    assert not offenders, offenders
