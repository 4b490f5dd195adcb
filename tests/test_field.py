"""``deform --save-field`` / ``apply`` / ``sd.Field``: byte-identical re-application, the
callable field and its Jacobian, indices refusal, a streamed apply under a small budget."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from splatdeform.cli import main
from splatdeform.field import Field
from splatdeform.io import load, save
from splatdeform.model import PointModel
from tests.conftest import shared_file

HANDLE = """input: in.ply
output: out.ply
regions:
  units: relative
  fixed: [{box: {min: [0,0,0], max: [1,0.2,1]}}]
  handle: [{box: {min: [0,0.8,0], max: [1,1,1]}}]
handle:
  transform: {rotate: {axis: [0,0,1], degrees: 15}, translate: [0.05, 0, 0]}
"""
POINTS = """input: in.ply
output: out.ply
regions:
  units: relative
  fixed: [{box: {min: [0,0,0], max: [1,0.15,1]}}]
points:
  pairs: [[0.5,0.9,0.5, 0.55,0.92,0.5], [0.2,0.6,0.5, 0.2,0.6,0.55],
          [0.8,0.5,0.3, 0.8,0.52,0.3]]
"""


@pytest.mark.parametrize("config", [HANDLE, POINTS], ids=["handle", "points"])
def test_apply_is_byte_identical(tmp_path, config):
    shutil.copy(shared_file("scans/bunny_res2.ply"), tmp_path / "in.ply")
    shutil.copy(tmp_path / "in.ply", tmp_path / "copy.ply")
    (tmp_path / "e.yaml").write_text(config)
    field = tmp_path / "f.npz"
    assert main(["deform", str(tmp_path / "e.yaml"), "--save-field", str(field),
                 "--quiet"]) == 0
    assert field.stat().st_size < 200_000
    assert main(["apply", str(field), str(tmp_path / "copy.ply"), "-o",
                 str(tmp_path / "ap.ply")]) == 0
    assert (tmp_path / "ap.ply").read_bytes() == (tmp_path / "out.ply").read_bytes()
    f = Field.load(field)
    pts = load(tmp_path / "in.ply").positions[:50].astype(np.float64)
    jac = f.jacobian(pts)
    h = 1e-6
    num = (f(pts + [h, 0, 0]) - f(pts - [h, 0, 0])) / (2 * h)
    assert np.abs(jac[:, :, 0] - num).max() < 1e-5


def test_indices_field_refuses_other_models(tmp_path):
    shutil.copy(shared_file("scans/bunny_res2.ply"), tmp_path / "in.ply")
    bunny = load(tmp_path / "in.ply")
    save(PointModel(positions=bunny.positions + 1e-4), tmp_path / "other.ply")
    (tmp_path / "e.yaml").write_text(
        "input: in.ply\noutput: out.ply\nregions:\n  fixed: [{indices: [0, 1, 2, 3, 4, 5]}]\n"
        "points:\n  pairs: [[-0.02,0.1,0.0,-0.018,0.1,0.0]]\n")
    assert main(["deform", str(tmp_path / "e.yaml"), "--save-field",
                 str(tmp_path / "f.npz"), "--quiet"]) == 0
    assert main(["apply", str(tmp_path / "f.npz"), str(tmp_path / "in.ply"), "-o",
                 str(tmp_path / "same.ply")]) == 0
    assert main(["apply", str(tmp_path / "f.npz"), str(tmp_path / "other.ply"), "-o",
                 str(tmp_path / "x.ply")]) == 2
    assert not (tmp_path / "x.ply").exists()


def test_streamed_apply_matches_in_memory(tmp_path, capsys):
    rng = np.random.default_rng(2)
    save(PointModel(positions=rng.uniform(0, 100, (300_000, 3))), tmp_path / "big.ply")
    save(PointModel(positions=rng.uniform(0, 100, (3000, 3))), tmp_path / "in.ply")
    (tmp_path / "e.yaml").write_text(
        "input: in.ply\noutput: out.ply\nbackend: numpy\npoints:\n  pairs: "
        "[[10,10,10,11,10,10],[90,10,20,90,12,20],[50,90,50,50,90,53],[50,50,90,50,50,90]]\n")
    assert main(["deform", str(tmp_path / "e.yaml"), "--save-field",
                 str(tmp_path / "f.npz"), "--quiet"]) == 0
    assert main(["apply", str(tmp_path / "f.npz"), str(tmp_path / "big.ply"), "-o",
                 str(tmp_path / "s.ply"), "--memory-budget", "200MB"]) == 0
    assert "streamed" in capsys.readouterr().out
    assert main(["apply", str(tmp_path / "f.npz"), str(tmp_path / "big.ply"), "-o",
                 str(tmp_path / "m.ply")]) == 0
    a, b = load(tmp_path / "s.ply").positions, load(tmp_path / "m.ply").positions
    assert np.abs(a - b).max() <= 1e-9 * 200
