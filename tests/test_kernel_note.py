"""Issue 48 item 3: the first (uncached) OpenCL build says once, from the CLI only, that it is
compiling and where the cache is; ``python -m splatdeform.basis.kernel_warm`` (make setup)
builds the kernels ahead. The threshold is set to 0 here (SPLATDEFORM_NOTE_AFTER_S): the
wiring is tested, not the duration of a build."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from helpers import base_config, run_cli, write_config

from data_tools.synth import bumpy_bar
from splatdeform.basis import kernel_cache
from splatdeform.io import save


@pytest.fixture
def said():
    lines: list[str] = []
    kernel_cache._SAID.clear()
    kernel_cache.set_note_sink(lines.append)
    yield lines
    kernel_cache.set_note_sink(None)
    kernel_cache._SAID.clear()


def test_note_once_per_process(said, monkeypatch, tmp_path):
    monkeypatch.setenv("POCL_CACHE_DIR", str(tmp_path))
    for _ in range(2):
        with kernel_cache.noting_slow_build("basis", "Portable Computing Language", after=0):
            pass
    assert len(said) == 1 and str(tmp_path) in said[0] and "compiling" in said[0]


def test_no_note_for_a_build_that_ends_in_time(said):
    with kernel_cache.noting_slow_build("basis", "Portable Computing Language", after=3600):
        pass
    assert said == []


def test_cache_places(monkeypatch, tmp_path):
    monkeypatch.delenv("POCL_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert kernel_cache.cache_place("Portable Computing Language") == str(tmp_path / "pocl")
    assert kernel_cache.cache_place("NVIDIA CUDA").startswith(str(tmp_path / "pyopencl"))


def test_cli_says_it_once_on_stderr(tmp_path):
    save(bumpy_bar(1500), tmp_path / "bar.ply")
    cfg = write_config(tmp_path, base_config(tmp_path, backend="opencl"))
    env = {"SPLATDEFORM_NOTE_AFTER_S": "0", "POCL_CACHE_DIR": str(tmp_path / "pocl")}
    res = run_cli("deform", cfg, cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr
    notes = [ln for ln in res.stderr.splitlines() if "compiling the OpenCL" in ln]
    assert len(notes) == 1 and str(tmp_path / "pocl") in notes[0], res.stderr
    assert "compiling" not in res.stdout


def test_the_library_alone_says_nothing(tmp_path):
    code = ("import numpy as np\nfrom splatdeform.basis import compute_basis\n"
            "from splatdeform.rbf import fit_incremental\n"
            "pts = np.random.default_rng(0).normal(size=(60, 3))\n"
            "fit = fit_incremental(pts, pts[:, :1].repeat(4, 1), tolerance=1e-6)\n"
            "compute_basis(pts, fit, backend='opencl')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=180, env={**os.environ,
                                           "SPLATDEFORM_NOTE_AFTER_S": "0",
                                           "POCL_CACHE_DIR": str(tmp_path)})
    assert res.returncode == 0 and res.stderr == "", res.stderr


def test_warm_up_module_builds_the_kernels(tmp_path):
    res = subprocess.run([sys.executable, "-m", "splatdeform.basis.kernel_warm"],
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "POCL_CACHE_DIR": str(tmp_path)})
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("OpenCL kernels ready: basis K=3"), res.stdout
    assert any(tmp_path.iterdir())   # PoCL wrote its cache where it was told
