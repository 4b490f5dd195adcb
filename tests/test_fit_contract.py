"""Issue-10 contract end to end: the tolerance on real files, the default's fidelity against the
exact interpolant, and never a silent miss (CLI warning, ``on_not_converged: error``, batch
report)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml
from conftest import bar_edit, shared_file

from data_tools.synth import bumpy_bar
from splatdeform import deform as df
from splatdeform.basis.reference import evaluate_field
from splatdeform.basis.result import Basis
from splatdeform.deform.handle import compose_transform, delta_for_transform
from splatdeform.edit.selectors import Box, select
from splatdeform.io import load, save
from splatdeform.model import PointModel
from splatdeform.rbf import Normalization, fit_incremental
from splatdeform.rbf.exact import fit_exact

ROOT = Path(__file__).resolve().parents[1]


def slab_handle_edit(model: PointModel):
    """Fixed: first 30% of the longest bbox axis; handle: last 20%, rotated 30 degrees and
    moved 10% of the diagonal. Returns (deformation without basis, delta_c, largest move)."""
    axis = int(np.argmax(np.ptp(model.positions, axis=0)))
    f_max, h_min = np.ones(3), np.zeros(3)
    f_max[axis], h_min[axis] = 0.3, 0.8
    fixed = select(model, [Box((0, 0, 0), tuple(f_max))], "relative")
    handle = select(model, [Box(tuple(h_min), (1, 1, 1))], "relative")
    across, move = np.zeros(3), np.zeros(3)
    across[(axis + 1) % 3], move[(axis + 2) % 3] = 1.0, 0.1 * model.diagonal()
    matrix = compose_transform(pivot=model.positions[handle].mean(0), axis=across,
                               degrees=30.0, translate=move)
    d = df.prepare_handle(
        model, fixed, handle,
        fit_fn=lambda p, r: fit_incremental(p, r, tolerance=1.0, max_centers=0),
        basis_fn=lambda p, f: Basis(np.zeros((p.shape[0], f.k)), None))
    moved = model.positions[handle] @ matrix[:3, :3].T + matrix[:3, 3]
    largest = float(np.linalg.norm(moved - model.positions[handle], axis=1).max())
    return d, delta_for_transform(d.control_points, matrix), largest


@pytest.mark.parametrize("name", ["scans/bunny.ply", "scans/armadillo_oriented.ply"])
def test_default_fit_meets_tolerance_and_is_within_3_percent_of_exact(name):
    model = load(shared_file(name))
    d, delta, largest = slab_handle_edit(model)
    norm = Normalization.of(model.positions)
    fit = fit_incremental(d.constraint_points, d.constraint_rhs, normalization=norm)
    assert fit.converged
    r = d.constraint_rhs - evaluate_field(d.constraint_points, fit)
    assert np.abs(r).max() <= fit.tolerance
    # model units: a ring point misses its target by at most k * tolerance * largest move
    miss = np.linalg.norm(r @ delta, axis=1).max()
    assert miss <= 4 * fit.tolerance * np.linalg.norm(delta, axis=1).max()
    exact = fit_exact(d.constraint_points, d.constraint_rhs, normalization=norm)
    free = model.positions[d.free_idx]
    dev = np.linalg.norm((evaluate_field(free, fit) - evaluate_field(free, exact)) @ delta,
                         axis=1).max()
    assert dev <= 0.03 * largest


def test_default_fit_meets_tolerance_on_a_generated_scene():
    model = bumpy_bar(40_000, seed=5)
    d, _, _ = slab_handle_edit(model)
    fit = fit_incremental(d.constraint_points, d.constraint_rhs)
    assert fit.converged
    r = d.constraint_rhs - evaluate_field(d.constraint_points, fit)
    assert np.abs(r).max() <= fit.tolerance


@pytest.fixture(scope="module")
def bar_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("conv")
    save(bumpy_bar(3000, seed=2), root / "bar.ply")
    return root


def write_edit(root: Path, name: str, **fit) -> Path:
    cfg = bar_edit({"rotate": {"axis": [0, 0, 1], "degrees": 30}}, fit=fit,
                   input="bar.ply", output=f"{name}.ply")
    path = root / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def deform(cfg: Path) -> subprocess.CompletedProcess:
    return helpers.run_cli("deform", cfg, timeout=300)


def test_not_converged_warns_one_line_and_still_writes(bar_dir):
    res = deform(write_edit(bar_dir, "warn", tolerance=1e-9, max_centers=5, method="incremental"))
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "warning" in lines[0] and "did not converge" in lines[0]
    assert "fit.max_centers" in lines[0] and "fit.tolerance" in lines[0]
    assert "converged: false" in res.stdout
    assert (bar_dir / "warn.ply").is_file()


def test_on_not_converged_error_exits_1_writes_nothing(bar_dir):
    res = deform(write_edit(bar_dir, "err", tolerance=1e-9, max_centers=5, method="incremental",
                            on_not_converged="error"))
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "warning" not in lines[0], res.stderr
    assert "did not converge" in lines[0]
    assert not (bar_dir / "err.ply").exists()
    assert not list(bar_dir.glob(".err*"))


def test_converged_fit_prints_no_warning(bar_dir):
    res = deform(write_edit(bar_dir, "ok"))
    assert res.returncode == 0 and res.stderr == "", res.stderr
    assert "converged: true" in res.stdout


def test_reuse_key_ignores_on_not_converged(bar_dir):
    from splatdeform.edit.cache import edit_key
    from splatdeform.edit.config import load_edit

    a = load_edit(write_edit(bar_dir, "k1", on_not_converged="warn"))
    b = load_edit(write_edit(bar_dir, "k2", on_not_converged="error"))
    c = load_edit(write_edit(bar_dir, "k3", tolerance=1e-3))
    assert edit_key(a, bar_dir / "bar.ply") == edit_key(b, bar_dir / "bar.ply")
    assert edit_key(a, bar_dir / "bar.ply") != edit_key(c, bar_dir / "bar.ply")


def test_batch_report_flags_unconverged_scans(bar_dir):
    edit = yaml.safe_load(write_edit(bar_dir, "b", tolerance=1e-9, max_centers=5,
                                     method="incremental").read_text())
    for key in ("input", "output"):
        edit.pop(key)
    batch = bar_dir / "batch.yaml"
    batch.write_text(yaml.safe_dump({"scans": "bar.ply", "edit": edit, "output_dir": "bout",
                                     "workers": 1}))
    res = subprocess.run([sys.executable, "-m", "splatdeform.cli", "batch", str(batch)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    report = json.loads((bar_dir / "bout" / "report.json").read_text())
    (row,) = report["scans"]
    assert row["status"] == "ok" and row["converged"] is False
    html = (bar_dir / "bout" / "index.html").read_text()
    assert "unconverged" in html and "not converged" in html


def test_deform_imports_only_what_an_edit_needs(bar_dir):
    """Start-up: a numpy-backend edit of a PLY imports no Open3D, moderngl, Dask, viser, laspy,
    pyopencl or Pillow."""
    cfg = write_edit(bar_dir, "imports")
    code = ("import sys\nfrom splatdeform.cli import main\n"
            f"rc = main(['deform', {str(cfg)!r}])\n"
            "heavy = {'open3d', 'moderngl', 'dask', 'distributed', 'viser', 'laspy', 'pyopencl',"
            " 'PIL'}\n"
            "print(rc, sorted({m.split('.')[0] for m in sys.modules} & heavy))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         timeout=300)
    assert res.stdout.strip().splitlines()[-1] == "0 []", res.stdout + res.stderr
