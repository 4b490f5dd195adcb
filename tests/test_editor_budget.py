"""The editor's own memory budget (``edit --memory-budget``, the YAML's ``memory_budget``,
default half the RAM: over it, one line naming the estimate and the budget, before the model is
read) and the Fit panel's figures in significant digits (the page's own ``fitFigures`` run by
node: "boundary error 0.00" hid 0.000495). No browser."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import helpers
import pytest
import yaml

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor.budget import check_budget, editor_estimate
from splatdeform.errors import InputError
from splatdeform.memory import default_budget

EDITOR_JS = Path(sd.__file__).parent / "editor" / "web" / "editor.js"


@pytest.fixture(scope="module")
def bar_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("budget") / "bar.ply"
    sd.save(bumpy_bar(2000, seed=5), path)
    return path


def test_edit_over_the_budget_is_refused_in_one_line(bar_path):
    need = editor_estimate(bar_path)
    assert need > 300 * 2**20       # interpreter + the fit's working set at the default centers
    run = helpers.run_cli("edit", str(bar_path), "--memory-budget", "300MB", "--port", "0",
                          cwd=bar_path.parent, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr
    assert f"{bar_path}: the in-memory estimate is " in lines[0]
    assert "memory budget of 300 MB (--memory-budget)" in lines[0]
    assert "the editor holds the whole model" in lines[0]


def test_bad_budget_is_one_line():
    run = helpers.run_cli("edit", "whatever.ply", "--memory-budget", "lots", cwd=Path.cwd(),
                          timeout=120)
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
    assert "--memory-budget" in run.stderr


def test_within_the_budget_opens_and_the_default_is_half_the_ram(bar_path):
    assert check_budget(bar_path, "4GB") == editor_estimate(bar_path)
    if editor_estimate(bar_path) <= default_budget():
        assert check_budget(bar_path) == editor_estimate(bar_path)


def test_the_yaml_memory_budget_applies_and_the_flag_wins(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = {"input": "bar.ply", "output": "bent.ply", "memory_budget": "128MB",
           "regions": {"units": "model",
                       "fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}],
                       "handle": [{"box": {"min": [3, -1, -1], "max": [5, 1, 1]}}]},
           "handle": {"transform": {"translate": [0.0, 0.3, 0.0]}},
           "fit": {"max_centers": 500}}
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    with pytest.raises(InputError, match=r"budget of 128 MB \(memory_budget\)"):
        check_budget(path)
    # fewer centers: a smaller estimate than the bare model's default
    assert check_budget(path, "2GB") < editor_estimate(bar_path)


def _fit_figures(states: list[dict]) -> list[str]:
    js = EDITOR_JS.read_text()
    fn = re.search(r"^function fitFigures\(st\) \{.*?^\}\n", js, re.S | re.M)
    assert fn, "fitFigures not found in editor.js"
    script = fn.group(0) + f"for (const st of {json.dumps(states)}) " \
        "console.log(JSON.stringify(fitFigures(st)));"
    from data_tools.splat_transform import node_bin  # the oracles' node (fails if missing)

    out = subprocess.run([str(node_bin() / "node"), "-e", script], capture_output=True,
                         text=True, timeout=60, check=True).stdout
    return [json.loads(line) for line in out.splitlines()]


def test_fit_figures_keep_three_significant_digits():
    def state(residual: float, kept: int) -> dict:
        return {"fit": {"stats": {"method": "exact-kept", "centers": 505, "constraints": 1112,
                                  "kept": kept, "residual": residual, "tolerance": 0.00015,
                                  "converged": True, "seconds": 0.09914}},
                "counts": {"fixed": 100, "handle": 50, "free": 8918}}

    small, zero, full = _fit_figures([state(0.000495123, 505), state(0.0, 505),
                                      state(1.234e-7, 1112)])
    assert "boundary error 0.000495 over the kept constraints (tolerance 0.00015)" in small
    assert "boundary error 0 over the kept constraints" in zero and "0.00 " not in zero
    assert "boundary error 1.23e-7 (tolerance 0.00015)" in full
    assert small.endswith(" · 0.0991 s")
