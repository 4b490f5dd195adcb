"""Bad edits: one clear error line, exit code 2, no traceback, no output file.

Each case goes through ``python -m splatdeform.cli deform`` in a subprocess and, where natural,
through the Python API (InputError / ConfigError / RegionError).
"""

from __future__ import annotations

import copy
import subprocess
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.edit.config import load_edit, parse_edit
from splatdeform.errors import ConfigError, InputError, RegionError

N_BAR = 1500
N_LINE = 12  # extra collinear points past the bar's end (the degenerate handle)


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scans")
    sd.save(bumpy_bar(N_BAR, seed=21), root / "bar.ply")
    # bar + a straight line of points continuing it along x (collinear handle candidates)
    bar = bumpy_bar(N_BAR, seed=21)
    line = np.stack([np.linspace(4.02, 4.4, N_LINE), np.zeros(N_LINE), np.zeros(N_LINE)], 1)
    spike = sd.PointModel(positions=np.vstack([bar.positions, line]))
    sd.save(spike, root / "spike.ply")
    bad = bumpy_bar(N_BAR, seed=21)
    bad.positions[7] = np.nan
    sd.save(bad, root / "nan.ply")
    return root


def base_config(scans: Path) -> dict:
    return {
        "input": str(scans / "bar.ply"),
        "output": "out/bent.ply",
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [-1, -1, -1], "max": [1.0, 1, 1]}}],
                    "handle": [{"box": {"min": [3.0, -1, -1], "max": [5, 1, 1]}}]},
        "handle": {"transform": {"pivot": "centroid",
                                 "rotate": {"axis": [0, 0, 1], "degrees": 20},
                                 "translate": [0, 0.2, 0]}},
        "fit": {"tolerance": 1e-3},
        "backend": "numpy",
    }


def _set(cfg: dict, dotted: str, value) -> dict:
    keys = dotted.split(".")
    node = cfg
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return cfg


def _del(cfg: dict, dotted: str) -> dict:
    keys = dotted.split(".")
    node = cfg
    for k in keys[:-1]:
        node = node[k]
    del node[keys[-1]]
    return cfg


def _box(lo, hi):
    return [{"box": {"min": lo, "max": hi}}]


# name -> (mutation of the config dict or raw YAML text, needles the error line must contain)
CASES = {
    "unknown_key": (lambda c: _set(c, "handle.transform.bogus", 1),
                    ["handle.transform.bogus", "unknown key"]),
    "wrong_type": (lambda c: _set(c, "fit.tolerance", "abc"), ["fit.tolerance"]),
    "missing_output": (lambda c: _del(c, "output"), ["output", "missing"]),
    "missing_input": (lambda c: _set(c, "input", "no_such_scan.ply"), ["no_such_scan.ply"]),
    "output_is_input": (lambda c: _set(c, "output", c["input"]), ["bar.ply", "input"]),
    "empty_fixed": (lambda c: _set(c, "regions.fixed", _box([10, 10, 10], [11, 11, 11])),
                    ["regions.fixed"]),
    "empty_handle": (lambda c: _set(c, "regions.handle", _box([10, 10, 10], [11, 11, 11])),
                     ["regions.handle"]),
    "overlap": (lambda c: _set(c, "regions.fixed", _box([-1, -1, -1], [3.5, 1, 1])),
                ["regions", "overlap"]),
    "cover_everything": (lambda c: _set(_set(c, "regions.fixed", _box([-1, -1, -1], [2, 1, 1])),
                                        "regions.handle", _box([2.0000001, -1, -1], [5, 1, 1])),
                         ["regions", "every point"]),
    "touching": (lambda c: _set(_set(c, "regions.fixed", _box([-1, -1, -1], [2, 1, 1])),
                                "regions.handle", _box([2.01, -1, -1], [5, 1, 1])),
                 ["regions", "adjacent"]),
    "degenerate_handle": (lambda c: _set(_set(c, "input", c["input"].replace("bar", "spike")),
                                         "regions.handle",
                                         [{"indices": list(range(N_BAR, N_BAR + N_LINE))}]),
                          ["regions.handle", "collinear"]),
    "handle_and_curve": (lambda c: _set(c, "curve", {
        "control_points": [[1.5, 0, 0.5], [2, 0, 0.5], [2.5, 0, 0.5]],
        "moved_to": [[1.5, 0, 0.6], [2, 0, 0.7], [2.5, 0, 0.6]], "capture_radius": 0.1}),
                         ["handle", "curve"]),
    "invalid_yaml": ("input: [bar.ply\noutput: x.ply\n", ["edit.yaml", "YAML"]),
    "not_a_mapping": ("- input\n- output\n", ["edit.yaml", "mapping"]),
    "nan_coordinates": (lambda c: _set(c, "input", c["input"].replace("bar", "nan")),
                        ["nan.ply", "NaN"]),
    "unknown_backend": (lambda c: _set(c, "backend", "cuda"), ["backend", "cuda"]),
}


def _write(tmp_path: Path, scans: Path, case) -> Path:
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    path = cfg_dir / "edit.yaml"
    if isinstance(case, str):
        path.write_text(case)
    else:
        path.write_text(yaml.safe_dump(case(copy.deepcopy(base_config(scans)))))
    return path


def _run(*args, cwd) -> subprocess.CompletedProcess:
    return helpers.run_cli(*args, cwd=cwd, timeout=120)


def _assert_one_line_error(res: subprocess.CompletedProcess, needles) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr + res.stdout
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    line = lines[0]
    assert line.startswith("splatdeform: error:"), line
    for needle in needles:
        assert needle in line, (needle, line)
    return line


def _files_under(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()] if folder.exists() else []


@pytest.mark.parametrize("name", sorted(CASES))
def test_cli_bad_edit(name, scans, tmp_path):
    case, needles = CASES[name]
    cfg = _write(tmp_path, scans, case)
    before = {p: p.read_bytes() for p in _files_under(scans)}
    res = _run("deform", cfg, cwd=tmp_path)
    _assert_one_line_error(res, needles)
    # nothing written: no output (nor temporary) file beside the config, inputs untouched
    assert _files_under(tmp_path / "cfg") == [cfg]
    assert {p: p.read_bytes() for p in _files_under(scans)} == before


def test_cli_missing_config_and_bad_flag(scans, tmp_path):
    res = _run("deform", tmp_path / "nope.yaml", cwd=tmp_path)
    _assert_one_line_error(res, ["nope.yaml"])
    cfg = _write(tmp_path, scans, lambda c: c)
    res = _run("deform", cfg, "--backend", "cuda", cwd=tmp_path)
    _assert_one_line_error(res, ["--backend"])
    assert _files_under(tmp_path / "cfg") == [cfg]


# ----------------------------------------------------------------------------- Python API

@pytest.mark.parametrize("name, needles", [
    ("unknown_key", ["handle.transform.bogus"]),
    ("wrong_type", ["fit.tolerance"]),
    ("missing_output", ["output"]),
    ("handle_and_curve", ["curve"]),
    ("unknown_backend", ["backend"]),
])
def test_api_config_errors(name, needles, scans):
    data = CASES[name][0](copy.deepcopy(base_config(scans)))
    with pytest.raises(ConfigError) as info:
        parse_edit(data, "edit.yaml")
    msg = str(info.value)
    assert msg.startswith("edit.yaml: ")
    for needle in needles:
        assert needle in msg


@pytest.mark.parametrize("text", ["input: [bar.ply\n", "- a\n- b\n"])
def test_api_bad_yaml(text, tmp_path):
    path = tmp_path / "edit.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match="edit.yaml"):
        load_edit(path)


def test_api_missing_and_nan_input(scans):
    with pytest.raises(InputError, match="no_such_scan.ply"):
        sd.load(scans / "no_such_scan.ply")
    with pytest.raises(InputError, match="NaN"):
        sd.load(scans / "nan.ply")


def test_api_output_is_input(scans):
    model = sd.load(scans / "bar.ply")
    before = (scans / "bar.ply").read_bytes()
    with pytest.raises(InputError, match="input"):
        sd.save(model, scans / "bar.ply")
    assert (scans / "bar.ply").read_bytes() == before


@pytest.fixture(scope="module")
def bar_model(scans):
    return sd.load(scans / "bar.ply")


def _masks(model, fixed_hi, handle_lo):
    x = model.positions[:, 0]
    return x <= fixed_hi, x >= handle_lo


@pytest.mark.parametrize("name, masks, match", [
    ("empty_fixed", lambda m: (np.zeros(m.n_points, bool), m.positions[:, 0] >= 3),
     "regions.fixed"),
    ("empty_handle", lambda m: (m.positions[:, 0] <= 1, np.zeros(m.n_points, bool)),
     "regions.handle"),
    ("overlap", lambda m: _masks(m, 3.5, 3.0), "overlap"),
    ("cover_everything", lambda m: (m.positions[:, 0] <= 2, m.positions[:, 0] > 2),
     "every point"),
    ("touching", lambda m: _masks(m, 2.0, 2.01), "adjacent"),
])
def test_api_region_errors(name, masks, match, bar_model):
    fixed, handle = masks(bar_model)
    with pytest.raises(RegionError, match=match):
        sd.prepare_handle(bar_model, fixed, handle, tolerance=1e-3, backend="numpy")


def test_api_degenerate_handle(scans):
    model = sd.load(scans / "spike.ply")
    handle = sd.select(model, [sd.Indices(indices=tuple(range(N_BAR, N_BAR + N_LINE)))])
    pts = model.positions[handle]
    # the handle really is collinear (independent check: rank of the centred points is 1)
    assert np.linalg.matrix_rank(pts - pts.mean(0), tol=1e-9) == 1
    fixed = model.positions[:, 0] <= 1
    with pytest.raises(RegionError, match="collinear"):
        sd.prepare_handle(model, fixed, handle, tolerance=1e-3, backend="numpy")
