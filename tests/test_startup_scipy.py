"""Start-up (issue 45 item 6): scipy is imported where it is used, not by importing a module.

Validating an edit config (without ``points:``, whose pairs limit lives in the deform layer)
and importing the fitter, the kernel table and the numpy basis load no scipy; the fit's LAPACK
and ``cdist`` are imported on first use. Checked in a fresh interpreter (the set of modules,
not a time).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

EDIT = """\
input: bar.ply
output: bar_bent.ply
regions:
  units: relative
  fixed: [{box: {min: [0, 0, 0], max: [0.3, 1, 1]}}]
  handle: [{box: {min: [0.8, 0, 0], max: [1, 1, 1]}}]
handle:
  transform: {pivot: centroid, rotate: {axis: [0, 1, 0], degrees: 30}}
boundary: {continuity: 2, neighbors: 10}
"""


def _scipy_after(code: str, cwd: Path) -> list[str]:
    res = subprocess.run([sys.executable, "-c", code + "\nimport sys\n"
                          "print(' '.join(sorted(m for m in sys.modules "
                          "if m == 'scipy' or m.startswith('scipy.'))))"],
                         capture_output=True, text=True, cwd=cwd, timeout=120)
    assert res.returncode == 0, res.stderr
    return res.stdout.strip().splitlines()[-1:] if res.stdout.strip() else []


def test_config_validation_and_fitter_import_no_scipy(tmp_path):
    (tmp_path / "edit.yaml").write_text(EDIT)
    code = ("from splatdeform.edit.config import load_edit\n"
            "cfg = load_edit('edit.yaml')\n"
            "assert cfg.points is None\n"
            "import splatdeform.rbf.auto, splatdeform.rbf.fit, splatdeform.rbf.exact\n"
            "import splatdeform.rbf.kernel, splatdeform.basis.reference\n")
    assert _scipy_after(code, tmp_path) == []


def test_too_many_inline_pairs_still_refused(tmp_path):
    """The pairs limit is read from the deform layer on first use: the same one line."""
    rows = ", ".join("[0, 0, 0, 0, 0, 1]" for _ in range(3001))
    (tmp_path / "edit.yaml").write_text(EDIT + f"points: {{pairs: [{rows}]}}\n")
    res = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", "edit.yaml"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "splatdeform: error: edit.yaml: points.pairs: 3,001 inline pairs exceed the limit of "
        "3,000 (the dense fit: O(m^3) time, 8 m^2 bytes)"], res.stderr


def test_fit_imports_lapack_on_first_use():
    """The fit itself still runs through scipy's LAPACK (same results as before)."""
    code = ("import numpy as np\n"
            "from splatdeform.rbf.fit import fit_incremental\n"
            "rng = np.random.default_rng(0)\n"
            "x = rng.random((200, 3))\n"
            "fit = fit_incremental(x, np.sin(x), tolerance=1e-3, max_centers=60)\n"
            "assert np.all(np.isfinite(fit.weights))\n")
    assert "scipy.linalg" in _scipy_after(code, ROOT)[0].split()


def test_a_bad_config_is_refused_before_the_deform_path_is_imported(tmp_path):
    """``deform`` reads the config before it imports the plan and the run (and with them
    scipy): a wrong key costs the config's validation only."""
    (tmp_path / "edit.yaml").write_text(EDIT.replace("boundary:", "boundry:"))
    code = ("from splatdeform.cli import main\n"
            "try:\n    main(['deform', 'edit.yaml'])\nexcept SystemExit:\n    pass")
    assert _scipy_after(code, tmp_path) == []
