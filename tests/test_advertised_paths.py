"""Paths the README advertises that had no test: the plane / property / indices-file selectors
through an edit config, handle.matrix, normals: estimate, and the per-frame deform_frame."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.deform.arrays import deform_frame
from splatdeform.deform.handle import compose_transform
from splatdeform.edit.config import parse_edit
from splatdeform.edit.run import run_edit
from splatdeform.model import PointModel

ROOT = Path(__file__).resolve().parents[1]

FIXED = [{"box": {"min": [-1, -1, -1], "max": [1.0, 1, 1]}}]
HANDLE = [{"box": {"min": [3.0, -1, -1], "max": [5, 1, 1]}}]
TRANSFORM = {"pivot": [3.0, 0, 0], "rotate": {"axis": [0, 0, 1], "degrees": 20},
             "translate": [0, 0.1, 0]}


@pytest.fixture(scope="module")
def bar_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paths")
    sd.save(bumpy_bar(4000, seed=21), root / "bar.ply")
    return root


def edit(**over) -> dict:
    cfg = {"input": "bar.ply", "output": "out.ply",
           "regions": {"units": "model", "fixed": FIXED, "handle": HANDLE},
           "handle": {"transform": TRANSFORM}, "backend": "numpy"}
    cfg.update(over)
    return cfg


def masks(bar_dir: Path, **regions) -> tuple[np.ndarray, np.ndarray]:
    cfg = edit(regions={"units": "model", "fixed": FIXED, "handle": HANDLE, **regions})
    d = run_edit(parse_edit(cfg, "e.yaml"), bar_dir, save_output=False).deformation
    return d.fixed, d.moving


def test_plane_selector_in_model_and_relative_units(bar_dir):
    model = sd.load(bar_dir / "bar.ply")
    x = model.positions[:, 0]
    fixed, _ = masks(bar_dir, fixed=[{"plane": {"point": [0.8, 0, 0], "normal": [-1, 0, 0]}}])
    np.testing.assert_array_equal(fixed, x <= 0.8)
    lo, hi = model.bbox()
    cfg_rel = {"units": "relative",
               "fixed": [{"plane": {"point": [0.2, 0, 0], "normal": [-1, 0, 0]}}],
               "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]}
    cfg = edit(regions=cfg_rel, handle={"transform": {"rotate": {"degrees": 10}}})
    d = run_edit(parse_edit(cfg, "e.yaml"), bar_dir, save_output=False).deformation
    rel = (x - lo[0]) / (hi[0] - lo[0])
    np.testing.assert_array_equal(d.fixed, rel <= 0.2)


def test_property_selector(bar_dir):
    model = sd.load(bar_dir / "bar.ply")
    red = model.source.element("vertex").data["red"]
    value = int(red.min())  # the bar's colour ramps along x: the smallest red is at one end
    fixed, _ = masks(bar_dir, fixed=[{"property": {"name": "red", "equals": value}}])
    np.testing.assert_array_equal(fixed, red == value)


@pytest.mark.parametrize("suffix", [".txt", ".npy"])
def test_indices_file_selector(bar_dir, suffix):
    model = sd.load(bar_dir / "bar.ply")
    idx = np.flatnonzero(model.positions[:, 0] > 3.2)
    path = bar_dir / f"handle_idx{suffix}"
    if suffix == ".npy":
        np.save(path, idx)
    else:
        np.savetxt(path, idx, fmt="%d")
    _, moving = masks(bar_dir, handle=[{"indices": {"file": path.name}}])
    expected = np.zeros(model.n_points, dtype=bool)
    expected[idx] = True
    np.testing.assert_array_equal(moving, expected)


def test_handle_matrix_equals_the_same_transform(bar_dir):
    matrix = compose_transform(pivot=np.array([3.0, 0, 0]), axis=(0, 0, 1), degrees=20,
                               translate=(0, 0.1, 0))
    a = run_edit(parse_edit(edit(), "a.yaml"), bar_dir, save_output=False)
    b = run_edit(parse_edit(edit(handle={"matrix": matrix.tolist()}), "b.yaml"), bar_dir,
                 save_output=False)
    np.testing.assert_array_equal(a.deformed.positions, b.deformed.positions)
    np.testing.assert_array_equal(a.deformed.normals, b.deformed.normals)


def test_normals_estimate_gives_unit_normals_that_follow_the_surface(bar_dir):
    """A cloud saved without normals, edited with normals: estimate, comes out with unit
    normals; on the free part they agree (up to sign) with normals estimated afresh on the
    deformed cloud."""
    src = sd.load(bar_dir / "bar.ply")
    bare = PointModel(positions=src.positions.copy())
    sd.save(bare, bar_dir / "bare.ply")
    cfg = edit(input="bare.ply", normals="estimate")
    res = run_edit(parse_edit(cfg, "n.yaml"), bar_dir, save_output=False)
    out = res.deformed
    assert out.normals is not None
    np.testing.assert_allclose(np.linalg.norm(out.normals, axis=1), 1.0, atol=1e-6)
    fresh = sd.estimate_normals(PointModel(positions=out.positions.copy()), 16)
    free = res.deformation.free_idx
    cos = np.abs(np.einsum("ij,ij->i", out.normals[free], fresh.normals[free]))
    assert np.median(np.degrees(np.arccos(np.clip(cos, 0, 1)))) < 5.0


def test_deform_frame_equals_apply_on_the_free_points(bar_dir):
    res = run_edit(parse_edit(edit(), "f.yaml"), bar_dir, save_output=False)
    d, model = res.deformation, res.model
    free = d.free_idx
    pos32 = model.positions[free].astype(np.float32)
    nrm32 = model.normals[free].astype(np.float32)
    p, n = deform_frame(pos32, nrm32, d.basis.values.astype(np.float32),
                        d.basis.gradients.astype(np.float32), res.delta_c.astype(np.float32))
    scale = model.diagonal()
    np.testing.assert_allclose(p, res.deformed.positions[free], rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(n, res.deformed.normals[free], rtol=0, atol=1e-4)


def test_docs_python_api_runs_as_written(tmp_path):
    """The API page's first Python block (one handle, then two handles in one edit; it was the
    README's) runs verbatim on the real bunny, and each written model moves its handle points
    and keeps the rest."""
    import re
    import runpy

    block = re.search(r"# Python API\n.*?```python\n(.*?)```",
                      (ROOT / "docs" / "api.md").read_text(), re.S).group(1)
    (tmp_path / "bunny.ply").symlink_to(shared_file("scans/bunny.ply"))
    (tmp_path / "readme_api.py").write_text(block)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        runpy.run_path(str(tmp_path / "readme_api.py"))
    finally:
        os.chdir(cwd)
    src = sd.load(tmp_path / "bunny.ply")
    for name in ("bunny_bent.ply", "bunny_ears.ply"):
        out = sd.load(tmp_path / name)
        moved = np.linalg.norm(out.positions - src.positions, axis=1) > 1e-6
        assert 0 < moved.sum() < src.n_points, name
