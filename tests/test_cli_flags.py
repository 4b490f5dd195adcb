"""CLI flags that used to be accepted and then misbehave: ``--debug`` after the verb works like
before it, and ``--memory-budget`` with an option that needs the whole model in memory is one
error line (exit 2) instead of a budget silently ignored."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import bar_edit

from data_tools.synth import bumpy_bar
from splatdeform.cli import main
from splatdeform.io import save


@pytest.mark.parametrize("argv", [["info", "{missing}", "--debug"],
                                  ["--debug", "info", "{missing}"]])
def test_debug_before_or_after_the_verb(tmp_path: Path, capsys, argv) -> None:
    missing = str(tmp_path / "missing.ply")
    assert main([a.format(missing=missing) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "InputError" in err
    assert err.splitlines()[-1] == f"splatdeform: error: {missing}: no such file"


def test_no_debug_one_line(tmp_path: Path, capsys) -> None:
    assert main(["info", str(tmp_path / "missing.ply")]) == 2
    assert len(capsys.readouterr().err.splitlines()) == 1


@pytest.fixture()
def edit(tmp_path: Path) -> Path:
    save(bumpy_bar(500, seed=3), tmp_path / "bar.ply")
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(bar_edit(input="bar.ply", output="out.ply")))
    return path


@pytest.mark.parametrize("verb,extra,named", [
    ("deform", ["--reuse"], "--reuse"),
    ("deform", ["--reuse-file", "x.npz"], "--reuse"),
    ("deform", ["--drop-nonfinite"], "--drop-nonfinite"),
    ("select", ["--drop-nonfinite"], "--drop-nonfinite"),
])
def test_memory_budget_with_whole_model_options(edit: Path, capsys, verb, extra, named) -> None:
    assert main([verb, str(edit), "--memory-budget", "512MB", *extra]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("splatdeform: error: --memory-budget: not with ")
    assert named in err[0]
    assert sorted(p.name for p in edit.parent.iterdir()) == ["bar.ply", "edit.yaml"]


def test_each_alone_still_runs(edit: Path, capsys) -> None:
    assert main(["deform", str(edit), "--memory-budget", "512MB", "--quiet"]) == 0
    assert main(["deform", str(edit), "--drop-nonfinite", "--quiet"]) == 0
    assert (edit.parent / "out.ply").is_file()
