"""The one pre-flight (issue 33 items 3-4): paths, stream-or-not and the view decided once into
an :class:`~splatdeform.edit.plan.EditPlan` that the CLI, batch and the Python API hand to
``run_edit``; a config's relative paths start at its file's folder from any working folder;
batch streams a scan over its per-worker budget where ``deform`` would, and refuses it with
deform's line where deform would; the same region error in memory and streamed."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bar_edit

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform import memory
from splatdeform.cli import main
from splatdeform.edit.plan import EditPlan, plan_edit
from splatdeform.edit.stream import StreamOptions
from splatdeform.io import atomic, save

EDIT = bar_edit({"pivot": [0.75, 0.5, 0.5], "rotate": {"axis": [0, 0, 1], "degrees": 20},
                 "translate": [0, 0.05, 0]}, fit={"tolerance": 1e-3, "max_centers": 200})


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """``edits/`` holding a binary PLY bar, an ascii one, a LAS one and edit files naming them
    by relative paths; the tests run from another folder."""
    root = tmp_path_factory.mktemp("preflight")
    edits = root / "edits"
    edits.mkdir()
    save(bumpy_bar(6000, seed=11), edits / "bar.ply")
    save(bumpy_bar(6000, seed=12), edits / "bar_ascii.ply", text=True)
    save(bumpy_bar(6000, seed=13), edits / "bar.las")
    for name, extra in (("e.yaml", {}),
                        ("empty.yaml", {"regions": {**EDIT["regions"], "handle": [
                            {"box": {"min": [2, 2, 2], "max": [3, 3, 3]}}]}})):
        (edits / name).write_text(yaml.safe_dump({**EDIT, "input": "bar.ply",
                                                  "output": "out.ply", **extra}))
    (root / "elsewhere").mkdir()
    return root


@pytest.fixture()
def checks(monkeypatch) -> list:
    """Every call of the one path check (io.atomic.check_io_paths) on an edit's paths (its
    inputs name the "input model"), counted; io.save's own guard of the file it writes (the
    in-memory path's save, labelled "input file") is the writer's, not a pre-flight."""
    calls: list = []
    real = atomic.check_io_paths

    def spy(inputs, outputs):
        inputs = list(inputs)
        if any(label == "input model" for label, _ in inputs):
            calls.append(1)
        return real(inputs, outputs)

    monkeypatch.setattr(atomic, "check_io_paths", spy)
    return calls


def one_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_plan_fields_from_a_config_file(folder: Path, monkeypatch) -> None:
    monkeypatch.chdir(folder / "elsewhere")
    plan = plan_edit(Path("../edits/e.yaml"))
    edits = (folder / "edits").resolve()
    assert isinstance(plan, EditPlan)
    assert plan.base_dir == edits and plan.input == edits / "bar.ply"
    assert plan.output == edits / "out.ply" and plan.source == Path("../edits/e.yaml")
    assert not plan.streamed and plan.choice.mode == "memory" and plan.budget is None
    assert plan.view is None and plan.render is None
    small = plan_edit(Path("../edits/e.yaml"), stream=StreamOptions(budget="64MB"))
    assert small.streamed and small.choice.mode == "stream"
    assert small.budget == 64 * 2**20 and small.choice.explicit
    dry = plan_edit(Path("../edits/e.yaml"), save_output=False)
    assert dry.output is None and not dry.streamed


@pytest.mark.parametrize("budget", [None, "64MB"], ids=["memory", "streamed"])
def test_deform_checks_paths_once(folder: Path, tmp_path: Path, checks: list, budget,
                                  monkeypatch, capsys) -> None:
    monkeypatch.chdir(folder / "elsewhere")
    out = tmp_path / "o.ply"
    args = ["deform", str(folder / "edits" / "e.yaml"), "-o", str(out), "--quiet"]
    assert main(args + ([] if budget is None else ["--memory-budget", budget])) == 0, \
        capsys.readouterr().err
    assert len(checks) == 1 and out.is_file()


def test_the_api_checks_paths_once_and_streams_from_the_plan(folder: Path, tmp_path: Path,
                                                             checks: list) -> None:
    result = sd.run_edit(folder / "edits" / "e.yaml", output=tmp_path / "s.ply",
                         stream=StreamOptions(budget="64MB", quiet=True))
    assert result.model is None and result.stats["chunk"]   # streamed
    assert len(checks) == 1


def test_relative_paths_resolve_against_the_config_folder(folder: Path, tmp_path: Path,
                                                          monkeypatch, capsys) -> None:
    """CLI, Python API (a path, or a mapping with its base folder) from another folder."""
    monkeypatch.chdir(folder / "elsewhere")
    edits = folder / "edits"
    (edits / "out.ply").unlink(missing_ok=True)
    assert main(["deform", "../edits/e.yaml", "--quiet"]) == 0, capsys.readouterr().err
    cli = (edits / "out.ply").read_bytes()
    (edits / "out.ply").unlink()
    result = sd.run_edit("../edits/e.yaml")
    assert Path(result.output).resolve() == (edits / "out.ply").resolve()
    assert (edits / "out.ply").read_bytes() == cli
    data = {**EDIT, "input": "bar.ply", "output": str(tmp_path / "dict.ply")}
    sd.run_edit(data, edits)
    assert (tmp_path / "dict.ply").read_bytes() == cli
    with pytest.raises(sd.InputError, match="no such file|not found|does not exist"):
        sd.run_edit(data)   # a mapping has no folder: the current one, which lacks bar.ply
    assert not list(Path(".").iterdir())


def test_batch_resolves_the_edit_files_paths_from_another_folder(folder: Path, tmp_path: Path,
                                                                 monkeypatch) -> None:
    from splatdeform.batch import run_batch

    edits = folder / "edits"
    (edits / "handle.txt").write_text("\n".join(str(i) for i in range(5900, 6000)))
    (edits / "idx.yaml").write_text(yaml.safe_dump({
        **EDIT, "regions": {**EDIT["regions"], "handle": [{"indices": {"file": "handle.txt"}}]}}))
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "a.ply").write_bytes((edits / "bar.ply").read_bytes())
    (tmp_path / "b.yaml").write_text(yaml.safe_dump({
        "scans": "scans/*.ply", "edit": os.path.relpath(edits / "idx.yaml", tmp_path),
        "output_dir": "out"}))
    monkeypatch.chdir(folder / "elsewhere")
    summary = run_batch(tmp_path / "b.yaml", workers=1, quiet=True)
    assert summary["exit_code"] == 0, summary["rows"]
    assert (tmp_path / "out" / "a_deformed.ply").is_file()


def rows(out: Path) -> dict[str, dict]:
    return {Path(r["scan"]).name: r for r in
            json.loads((out / "report.json").read_text())["scans"]}


def test_batch_streams_a_scan_over_its_budget_as_deform_does(folder: Path, tmp_path: Path,
                                                             capsys) -> None:
    """64 MiB per worker: below every in-memory estimate (the interpreter alone is counted at
    150 MB), so deform --memory-budget 64MB streams the binary PLY and the LAS and refuses the
    ascii PLY; batch does the same (a streamed run's timings: no save), with deform's line."""
    from splatdeform.batch import run_batch

    edits = folder / "edits"
    scans = tmp_path / "scans"
    scans.mkdir()
    for name in ("bar.ply", "bar_ascii.ply", "bar.las"):
        (scans / name).write_bytes((edits / name).read_bytes())
    (tmp_path / "b.yaml").write_text(yaml.safe_dump({
        "scans": "scans", "edit": EDIT, "output_dir": "out",
        "memory_per_worker_mb": 64}))
    summary = run_batch(tmp_path / "b.yaml", workers=1, quiet=True)
    got = rows(tmp_path / "out")
    assert got["bar.ply"]["status"] == "ok" and got["bar.las"]["status"] == "ok", got
    assert got["bar_ascii.ply"]["status"] == "failed" and summary["exit_code"] == 1
    for name, ext in (("bar.ply", ".ply"), ("bar.las", ".las")):
        cfg = tmp_path / f"d_{name}.yaml"
        cfg.write_text(yaml.safe_dump({**EDIT, "input": str(scans / name),
                                       "output": str(tmp_path / f"d{ext}")}))
        assert main(["deform", str(cfg), "--memory-budget", "64MB"]) == 0
        assert "streaming" in capsys.readouterr().out
        batch_out = tmp_path / "out" / f"{Path(name).stem}_deformed{ext}"
        a, b = sd.load(batch_out), sd.load(tmp_path / f"d{ext}")
        # the same streamed run (a worker's one BLAS thread rounds the fit differently)
        assert a.n_points == b.n_points and np.allclose(a.positions, b.positions, atol=1e-6)
        assert "total" in got[name]["timings"] and "save" not in got[name]["timings"]
    cfg = tmp_path / "d_ascii.yaml"
    cfg.write_text(yaml.safe_dump({**EDIT, "input": str(scans / "bar_ascii.ply"),
                                   "output": str(tmp_path / "d_ascii.ply")}))
    assert main(["deform", str(cfg), "--memory-budget", "64MB"]) == 2
    line = one_error(capsys)
    assert line == f"splatdeform: error: {got['bar_ascii.ply']['error']}"
    assert "streaming needs a binary PLY" in line


def test_a_budget_too_small_to_stream_in_is_still_refused(folder: Path, tmp_path: Path) -> None:
    from splatdeform.batch import run_batch

    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "a.ply").write_bytes((folder / "edits" / "bar.ply").read_bytes())
    (tmp_path / "b.yaml").write_text(yaml.safe_dump({
        "scans": "scans", "edit": EDIT, "output_dir": "out", "memory_per_worker_mb": 8}))
    summary = run_batch(tmp_path / "b.yaml", workers=1, quiet=True)
    (row,) = summary["rows"]
    assert row["status"] == "failed" and "8 MiB per worker" in row["error"], row


def test_empty_region_same_line_in_memory_and_streamed(folder: Path, tmp_path: Path,
                                                       capsys) -> None:
    cfg = str(folder / "edits" / "empty.yaml")
    out = str(tmp_path / "x.ply")
    assert main(["deform", cfg, "-o", out, "--quiet"]) == 2
    in_memory = one_error(capsys)
    assert main(["deform", cfg, "-o", out, "--quiet", "--memory-budget", "64MB"]) == 2
    streamed = one_error(capsys)
    assert streamed == in_memory
    assert in_memory == (f"splatdeform: error: {cfg}: regions.handle: selects no point; "
                         "widen the handle region")


def test_worker_budget_is_half_the_ram_shared() -> None:
    assert memory.worker_budget(4) == memory.default_budget() // 4
    assert memory.default_budget() == memory.machine_memory() // 2
    assert memory.worker_budget(0) == memory.default_budget()
