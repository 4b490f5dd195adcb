"""Start-up (issue 38 item 1): each verb imports only what it needs. The import set is checked
in a fresh interpreter, not a time: ``--help``, ``info`` and ``deform --help`` load no pydantic
(the config models), no scipy.spatial, no pyopencl, no Open3D, no renderer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NEVER = {"pydantic", "yaml", "scipy.spatial", "pyopencl", "open3d", "moderngl", "dask",
         "laspy", "PIL", "splatdeform.batch.config", "splatdeform.edit.config",
         "splatdeform.render.renderer", "splatdeform.deform", "splatdeform.rbf.fit"}


def imported_after(argv: list[str]) -> tuple[int, set[str]]:
    code = ("import contextlib, io, sys\nfrom splatdeform.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n        rc = main(sys.argv[1:])\n"
            "    except SystemExit as exc:\n        rc = exc.code\n"
            "print(rc)\nprint(' '.join(sorted(sys.modules)))\n")
    res = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    lines = res.stdout.strip().splitlines()
    assert len(lines) >= 2, res.stdout + res.stderr
    return int(lines[-2]), set(lines[-1].split())


@pytest.fixture(scope="module")
def small_ply(tmp_path_factory) -> Path:
    from data_tools.synth import bumpy_bar
    from splatdeform.io import save

    path = tmp_path_factory.mktemp("startup") / "small.ply"
    save(bumpy_bar(1000), path)
    return path


@pytest.mark.parametrize("argv", [["--help"], ["deform", "--help"], ["batch", "--help"],
                                  ["info", "SMALL"], ["info", "SMALL", "--json"]])
def test_light_verbs_import_no_heavy_module(argv, small_ply):
    argv = [str(small_ply) if a == "SMALL" else a for a in argv]
    rc, mods = imported_after(argv)
    assert rc == 0
    heavy = {m for m in mods if m in NEVER or m.split(".")[0] in NEVER}
    assert not heavy, f"{argv} imported {sorted(heavy)}"


def test_public_api_is_lazy():
    """``import splatdeform`` and its render / batch packages load none of their exports."""
    code = ("import sys, splatdeform, splatdeform.render, splatdeform.batch\n"
            "print(' '.join(sorted(sys.modules)))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    mods = set(res.stdout.split())
    assert not {m for m in mods if m in NEVER or m.split(".")[0] in NEVER}, res.stderr
    from splatdeform.batch import load_batch
    from splatdeform.render import View, save_png

    assert callable(load_batch) and callable(save_png) and View.__name__ == "View"
