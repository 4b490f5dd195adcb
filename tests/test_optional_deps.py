"""The core runs without OpenCL, EGL or Dask (issue 33 item 7), checked on real behaviour in
subprocesses, nothing uninstalled:

- no OpenCL platform: ``OCL_ICD_VENDORS`` pointed at an empty folder (the ICD loader finds no
  vendor file); ``backend: auto`` falls back to numpy, ``--backend opencl`` is one line;
- no EGL: ``__EGL_VENDOR_LIBRARY_DIRS`` pointed at an empty folder (libglvnd finds no vendor);
  ``info``/``deform`` run, ``render``/``--render`` are one line naming EGL;
- no Dask: a ``sitecustomize`` that sets ``sys.modules['dask'] = sys.modules['distributed'] =
  None`` (Python's own ImportError path, in every process, spawned workers included); where Dask
  is needed one line names the extra, batch's local ``--workers`` still run.

Each environment is first shown to really hide the device (a test fails, never skips, when it
does not).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import base_config, one_error_line, run_cli, write_config

from data_tools.synth import bumpy_bar
from splatdeform.io import save

ROOT = Path(__file__).resolve().parents[1]
EXTRA = "pip install 'splatdeform[dask]'"


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("optional")
    save(bumpy_bar(1500, seed=5), root / "bar.ply")
    (root / "empty").mkdir()
    return root


def no_opencl(root: Path) -> dict:
    return {"OCL_ICD_VENDORS": str(root / "empty"), "OCL_ICD_FILENAMES": "", "PYOPENCL_CTX": ""}


def no_egl(root: Path) -> dict:
    return {"__EGL_VENDOR_LIBRARY_DIRS": str(root / "empty")}


@pytest.fixture(scope="module")
def no_dask(tmp_path_factory) -> dict:
    site = tmp_path_factory.mktemp("nodask")
    (site / "sitecustomize.py").write_text(
        "import sys\nsys.modules['dask'] = None\nsys.modules['distributed'] = None\n")
    path = os.pathsep.join(p for p in (str(site), str(ROOT), os.environ.get("PYTHONPATH"))
                           if p)
    return {"PYTHONPATH": path}


def probe(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, env={**os.environ, **env})


def edit(scans: Path, name: str, **keys) -> Path:
    return write_config(scans / name, {**base_config(scans), "output": "out.ply", **keys})


# ------------------------------------------------------------------------------------- OpenCL


def test_the_empty_vendor_folder_hides_every_opencl_platform(scans):
    res = probe("import pyopencl as cl\ntry:\n    print(len(cl.get_platforms()))\n"
                "except cl.Error as exc:\n    print('none', exc)", no_opencl(scans))
    assert res.stdout.startswith("none"), res.stdout + res.stderr
    found = probe("import pyopencl as cl; print(len(cl.get_platforms()))", {})
    assert found.returncode == 0 and int(found.stdout) > 0, found.stderr  # the device is there


def test_auto_falls_back_to_numpy_without_opencl(scans):
    auto = edit(scans, "auto", backend="auto")
    numpy = edit(scans, "numpy", backend="numpy")
    res = run_cli("deform", auto, "--quiet", env=no_opencl(scans))
    assert res.returncode == 0, res.stderr
    assert run_cli("deform", numpy, "--quiet").returncode == 0
    assert (scans / "auto" / "out.ply").read_bytes() == (scans / "numpy" / "out.ply").read_bytes()
    assert run_cli("info", scans / "bar.ply", env=no_opencl(scans)).returncode == 0


def test_explicit_opencl_without_a_device_is_one_line(scans):
    cfg = edit(scans, "explicit", backend="opencl")
    one_error_line(run_cli("deform", cfg, env=no_opencl(scans)),
                   needles=["backend 'opencl'", "no OpenCL device", "pocl-opencl-icd"])
    assert not (scans / "explicit" / "out.ply").exists()


# ---------------------------------------------------------------------------------------- EGL


def test_the_empty_vendor_folder_hides_egl(scans):
    code = ("import moderngl\ntry:\n    moderngl.create_standalone_context(backend='egl')\n"
            "    print('context')\nexcept Exception as exc:\n    print('none', exc)")
    assert probe(code, no_egl(scans)).stdout.startswith("none")
    assert probe(code, {}).stdout.startswith("context")   # the real driver is there


def test_info_and_deform_run_without_egl_or_opencl(scans):
    env = {**no_egl(scans), **no_opencl(scans)}
    assert run_cli("info", scans / "bar.ply", env=env).returncode == 0
    cfg = edit(scans, "bare", backend="auto")
    res = run_cli("deform", cfg, env=env)
    assert res.returncode == 0, res.stderr
    assert (scans / "bare" / "out.ply").is_file()


def test_renders_without_egl_are_one_line_naming_it(scans):
    env = no_egl(scans)
    one_error_line(run_cli("render", scans / "bar.ply", "-o", scans / "r.png", env=env),
                   needles=["render:", "EGL", "libegl1"])
    assert not (scans / "r.png").exists()
    cfg = edit(scans, "render")
    one_error_line(run_cli("deform", cfg, "--render", scans / "render" / "r.png", "--quiet",
                           env=env), needles=["render:", "EGL"])
    assert not (scans / "render" / "r.png").exists()


# --------------------------------------------------------------------------------------- Dask


def test_the_sitecustomize_blocks_dask(no_dask):
    res = probe("import distributed", no_dask)
    assert res.returncode == 1 and "ModuleNotFoundError" in res.stderr, res.stderr


@pytest.mark.parametrize("flags, what", [(["--workers", "2"], "--workers"),
                                         (["--scheduler", "tcp://127.0.0.1:1"], "--scheduler")])
def test_deform_on_dask_without_dask_names_the_extra(scans, no_dask, flags, what):
    cfg = edit(scans, f"dask{what}")
    line = one_error_line(run_cli("deform", cfg, *flags, env=no_dask), needles=[what, EXTRA])
    assert line.count("splatdeform") == 2   # "splatdeform: error: ..." and the extra's name
    assert not (scans / f"dask{what}" / "out.ply").exists()


def batch_file(scans: Path, name: str, **keys) -> Path:
    edit_keys = {k: v for k, v in base_config(scans).items() if k not in ("input", "output")}
    path = scans / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"scans": str(scans / "bar.ply"), "edit": edit_keys,
                                    "output_dir": str(scans / name), **keys}))
    return path


def test_batch_on_dask_without_dask_names_the_extra(scans, no_dask):
    flag = batch_file(scans, "batch_flag")
    one_error_line(run_cli("batch", flag, "--scheduler", "tcp://127.0.0.1:1", env=no_dask),
                   needles=["scheduler", EXTRA])
    key = batch_file(scans, "batch_key", scheduler="tcp://127.0.0.1:1")
    one_error_line(run_cli("batch", key, env=no_dask), needles=["scheduler", EXTRA])


def test_batch_local_workers_need_no_dask(scans, no_dask):
    cfg = batch_file(scans, "batch_local")
    res = run_cli("batch", cfg, "--workers", "2", env=no_dask)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (scans / "batch_local" / "bar_deformed.ply").is_file()
    assert "[1/1] " in res.stdout   # the per-scan line (tqdm's LineBar) on a pipe
