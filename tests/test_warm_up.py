"""basis.warm_up: the OpenCL device opened on a background thread before the basis is needed
(deform starts it before loading its input); results unchanged, failures left to the real call."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from splatdeform.edit.config import parse_edit
from splatdeform.edit.plain import basis_columns


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_warm_up_then_basis_is_the_same_basis():
    # a fresh process each, so the warm-up really runs first
    code = """
        import numpy as np
        from splatdeform.basis import compute_basis, warm_up
        from splatdeform.rbf import fit_incremental
        rng = np.random.default_rng(0)
        pts = rng.normal(size=(300, 3))
        fit = fit_incremental(pts, np.eye(300)[:, :4] + pts[:, :1], tolerance=1e-6)
        {warm}
        b = compute_basis(rng.normal(size=(5000, 3)), fit, backend="opencl")
        print(repr(b.values.sum()), repr(b.gradients.sum()))
    """
    cold = _run(code.format(warm=""))
    warm = _run(code.format(warm="warm_up('opencl', None, 4)"))
    assert cold == warm


def test_warm_up_failures_are_left_to_the_real_call():
    out = _run("""
        import numpy as np
        from splatdeform.basis import compute_basis, warm_up
        from splatdeform.errors import DeviceError
        from splatdeform.rbf import fit_incremental
        warm_up("opencl", "no-such-device-name", 4)   # must not raise
        pts = np.random.default_rng(0).normal(size=(50, 3))
        fit = fit_incremental(pts, pts[:, :1].repeat(4, 1), tolerance=1e-6)
        try:
            compute_basis(pts, fit, backend="opencl", device="no-such-device-name")
        except DeviceError as exc:
            print("DeviceError", "no-such-device-name" in str(exc))
    """)
    assert out.strip() == "DeviceError True"


def test_warm_up_is_nothing_for_numpy():
    out = _run("""
        import sys, threading
        from splatdeform.basis import warm_up
        warm_up("numpy", None, 4)
        print(threading.active_count(), "pyopencl" in sys.modules)
    """)
    assert out.strip() == "1 False"


def test_basis_columns_of_an_edit():
    base = {"input": "a.ply", "output": "b.ply",
            "regions": {"fixed": [{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}],
                        "handle": [{"box": {"min": [2, 2, 2], "max": [3, 3, 3]}}]},
            "handle": {"transform": {"translate": [0, 0, 1]}}}
    assert basis_columns(parse_edit(base, "t")) == 4
    two = {k: v for k, v in base.items() if k != "handle"}
    two["regions"] = {"fixed": base["regions"]["fixed"]}
    two["handles"] = [{"region": [{"box": {"min": [2, 2, 2], "max": [3, 3, 3]}}],
                       "transform": {"translate": [0, 0, 1]}},
                      {"region": [{"box": {"min": [4, 4, 4], "max": [5, 5, 5]}}],
                       "transform": {"translate": [0, 1, 0]}}]
    assert basis_columns(parse_edit(two, "t")) == 8


def test_cli_says_when_auto_falls_back_to_numpy(tmp_path):
    """backend: auto without a device used to run the numpy reference without a word (the CLI
    hides numpy's RuntimeWarnings); it now prints one warning line and still succeeds."""
    import yaml
    from helpers import base_config, run_cli

    from data_tools.synth import bumpy_bar
    from splatdeform.io import save

    (tmp_path / "scans").mkdir()
    save(bumpy_bar(3000, seed=2), tmp_path / "scans" / "bar.ply")
    cfg = base_config(tmp_path / "scans", backend="auto")
    (tmp_path / "edit.yaml").write_text(yaml.safe_dump(cfg))
    res = run_cli("deform", tmp_path / "edit.yaml", "--quiet", cwd=tmp_path,
                  env={"PYOPENCL_CTX": "no-such-device"})
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("splatdeform: warning: backend 'auto'")
    assert "numpy reference" in lines[0] and "pocl-opencl-icd" in lines[0]
    assert (tmp_path / "out" / "bent.ply").exists()
