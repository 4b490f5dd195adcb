"""The package's layers, read from the source: the config layer (splatdeform.edit) is the only
one that knows the edit config, and every import points down the data flow.

    errors, interrupts, blas < model, resources < io, rbf, info, memory < basis < deform < render
    < edit < editor, batch < cli

(import statements anywhere in a module count, lazy ones inside functions too).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "splatdeform"
RANK = {"errors": 0, "lazy": 0, "interrupts": 0, "model": 1, "resources": 1, "io": 2, "rbf": 2,
        "info": 2, "memory": 2, "basis": 3, "deform": 4, "render": 5, "edit": 6, "editor": 7,
        "batch": 7, "cli": 8}
RANK["blas"] = 0   # the one BLAS limiter, below rbf/ and editor/
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
    assert "splatdeform.edit.stream" in found  # imported inside run_edit
    assert "splatdeform.deform" in found
