"""Run-time sources (kernels/, shaders/) are found from the checkout and from an installed wheel;
``splatdeform info --json`` prints machine-readable JSON."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from data_tools.synth import bumpy_bar, sphere
from splatdeform.io import save
from splatdeform.resources import resource_dir, resource_path

ROOT = Path(__file__).resolve().parents[1]
EXPECTED = {"kernels": {".cl"}, "shaders": {".vert", ".frag", ".geom", ".glsl"}}


def _files(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if p.is_file()}


@pytest.mark.parametrize("name", ["kernels", "shaders"])
def test_resources_from_checkout(name: str) -> None:
    folder = resource_dir(name)
    assert folder.is_dir()
    # editable install / checkout: the top-level folder of the repository
    assert folder.resolve() == (ROOT / name).resolve()
    files = _files(folder)
    assert files == _files(ROOT / name)
    assert {Path(f).suffix for f in files} & EXPECTED[name]
    some = sorted(files)[0]
    assert resource_path(name, some).read_bytes() == (ROOT / name / some).read_bytes()


def test_resource_errors() -> None:
    with pytest.raises(ValueError, match="kernels"):
        resource_dir("textures")
    with pytest.raises(FileNotFoundError, match="no_such.cl"):
        resource_path("kernels", "no_such.cl")


def _build_wheel(out: Path) -> Path:
    """Build the wheel; offline with hatchling in the venv, else in pip's isolated build env."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)]
    if importlib.util.find_spec("hatchling") is not None:
        cmd.insert(5, "--no-build-isolation")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, cwd=out)
    if proc.returncode != 0:
        text = proc.stdout + proc.stderr
        if any(s in text for s in ("hatchling", "Network", "connection", "resolve")) and \
                importlib.util.find_spec("hatchling") is None:
            pytest.skip(f"cannot build the wheel offline without hatchling: {text[-300:]}")
        pytest.fail(f"pip wheel failed:\n{text}")
    wheels = list(out.glob("splatdeform-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


# slow-ish (a few seconds: builds and installs a wheel); no "slow" marker is registered yet
def test_resources_from_installed_wheel(tmp_path: Path) -> None:
    wheel = _build_wheel(tmp_path / "wheel")
    target = tmp_path / "site"
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q",
                           "--no-index", "--target", str(target), str(wheel)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (target / "splatdeform" / "_data" / "kernels").is_dir()
    script = (
        "import json, splatdeform.resources as r\n"
        "out = {'module': r.__file__}\n"
        "for n in ('kernels', 'shaders'):\n"
        "    d = r.resource_dir(n)\n"
        "    out[n] = [str(d), sorted(p.name for p in d.iterdir())]\n"
        "print(json.dumps(out))\n"
    )
    run_dir = tmp_path / "elsewhere"  # outside the repository
    run_dir.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target)}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=run_dir, env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout)
    assert Path(found["module"]).resolve().is_relative_to(target.resolve())
    for name in ("kernels", "shaders"):
        folder, files = Path(found[name][0]), set(found[name][1])
        assert folder.resolve().is_relative_to(target.resolve()), folder
        assert folder.resolve() == (target / "splatdeform" / "_data" / name).resolve()
        assert files == _files(ROOT / name)  # every run-time source is shipped
        assert {Path(f).suffix for f in files} & EXPECTED[name]
        for f in files:
            assert (folder / f).read_bytes() == (ROOT / name / f).read_bytes()


def _info_json(path: Path, cwd: Path) -> dict:
    proc = subprocess.run([sys.executable, "-m", "splatdeform.cli", "info", str(path), "--json"],
                          capture_output=True, text=True, cwd=cwd, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    return json.loads(proc.stdout)


@pytest.mark.parametrize("ext", [
    ".ply", ".pcd", ".xyzn", ".pts",
])
def test_info_json(ext: str, tmp_path: Path) -> None:
    model = bumpy_bar(2000, seed=3) if ext == ".ply" else sphere(800, seed=3)
    path = save(model, tmp_path / f"scan{ext}")
    info = _info_json(path, tmp_path)
    assert {"kind", "points", "bbox_min", "bbox_max"} <= set(info)
    assert info["points"] == model.n_points
    lo, hi = model.bbox()
    assert info["bbox_min"] == pytest.approx(lo.tolist(), abs=1e-6)
    assert info["bbox_max"] == pytest.approx(hi.tolist(), abs=1e-6)
    if ext == ".ply":
        assert info["kind"] == "surfel_radius"
        assert info["format"] == "binary_little_endian"
        assert info["normals"] == "unit"
        assert [e["name"] for e in info["elements"]] == ["vertex"]
    elif ext == ".pts":
        assert info["kind"] == "cloud"
    else:
        assert info["kind"] == "oriented_cloud"


def test_info_text_and_entry_point(tmp_path: Path) -> None:
    path = save(sphere(300, seed=9), tmp_path / "s.ply", text=True)
    script = Path(sys.executable).with_name("splatdeform")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "splatdeform.cli"]
    proc = subprocess.run([*cmd, "info", str(path)], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "surfel_radius" in proc.stdout and "ascii" in proc.stdout
    assert "300" in proc.stdout
