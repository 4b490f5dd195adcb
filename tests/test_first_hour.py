"""Issue 48 items 5-6: a points edit's regions line, the fit line's wording, labels that keep
'.' and ':' and wrap inside their panel (the pairs preview's legend), and the note that says
which up axis a render assumed when the file does not say and the shape hints at z-up."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from splatdeform.edit.selection import RegionCounts, format_counts
from splatdeform.io import save
from splatdeform.model import PointModel
from splatdeform.render.compare import LABEL_HEIGHT, side_by_side
from splatdeform.render.upaxis import up_note


def test_points_edit_regions_line():
    # a points-only edit: no region, the constraints are the pairs
    line = format_counts(RegionCounts(60000, 0, 0, 60000, [0], [12]))
    assert line == "regions: none (the 12 pairs are the constraints)  free 60,000  of 60,000 points"
    assert "rings 0" not in line and "handle" not in line
    # pairs beside a fixed region: its rings, then the pairs
    line = format_counts(RegionCounts(100, 30, 0, 70, [5, 5], [4]))
    assert line == "regions: fixed 30 (rings 5+5)  pairs 4  free 70  of 100 points"
    # a handle edit reads as before
    line = format_counts(RegionCounts(100, 30, 20, 50, [5], [6]))
    assert line == "regions: fixed 30 (rings 5)  handle 20 (rings 6)  free 50  of 100 points"


def test_points_deform_summary(tmp_path):
    rng = np.random.default_rng(7)
    save(PointModel(positions=rng.uniform(0, 10, (3000, 3))), tmp_path / "in.ply")
    src = np.array([[1, 1, 1], [9, 1, 2], [5, 9, 5], [5, 5, 9], [2, 7, 3]], float)
    rows = ", ".join(str([*a.tolist(), *(a + 0.3).tolist()]) for a in src)
    (tmp_path / "e.yaml").write_text(f"input: in.ply\noutput: out.ply\npoints:\n"
                                     f"  pairs: [{rows}]\n  smoothing: 0\n")
    res = run_cli("deform", tmp_path / "e.yaml", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "regions: none (the 5 pairs are the constraints)  free 3,000" in res.stdout
    assert "over all constraints" in res.stdout and "over the all" not in res.stdout


def _label(text: str, width: int = 200) -> np.ndarray:
    return side_by_side([np.full((20, width, 3), 255, np.uint8)], [text])


def test_labels_keep_dots_and_colons():
    assert (_label("a.b") != _label("ab")).any()
    assert (_label("a:b") != _label("ab")).any()
    dots = _label("x.spz, split: auto")[:LABEL_HEIGHT]
    assert (dots < 128).any()


def test_long_labels_wrap_inside_the_panel():
    text = "; ".join(["pairs: source dot, arrow to target (magenta)"] * 4)
    image = _label(text, width=300)
    assert image.shape[1] == 300 and image.shape[0] > 20 + LABEL_HEIGHT   # more lines
    assert (image.shape[0] - 20) % LABEL_HEIGHT == 0
    ink = np.nonzero((image[: image.shape[0] - 20] < 128).any(axis=(0, 2)))[0]
    assert ink.max() < 300 - 2   # nothing runs into the right edge
    short = _label("before")
    assert short.shape == (20 + LABEL_HEIGHT, 200, 3)   # one line: the strip as before


def _box(ext, seed=0) -> PointModel:
    rng = np.random.default_rng(seed)
    return PointModel(positions=rng.uniform(0, 1, (2000, 3)) * np.asarray(ext, float))


@pytest.mark.parametrize("ext, noted", [
    ((0.5, 0.3, 1.0), True),     # Lucy's proportions, scanned z-up
    ((0.16, 0.15, 0.12), False),  # the bunny
    ((0.23, 0.35, 0.42), False),  # the head (1.2x along z: not enough)
    ((4.0, 1.0, 1.0), False),    # the example bar
])
def test_up_note_when_the_shape_hints_at_z(ext, noted):
    note = up_note([_box(ext)])
    assert (note is not None) == noted
    if noted:
        assert "+y assumed" in note and "--up=+z" in note


def test_render_says_the_assumed_axis(tmp_path):
    save(_box((0.5, 0.3, 1.0)), tmp_path / "tall.ply")
    res = run_cli("render", "tall.ply", "-o", "t.png", "--size", "128x128", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    notes = [ln for ln in res.stderr.splitlines() if ln.startswith("splatdeform: note: ")]
    assert len(notes) == 1 and "--up=+z" in notes[0], res.stderr
    res = run_cli("render", "tall.ply", "-o", "t.png", "--size", "128x128", "--up=+z",
                  cwd=tmp_path)
    assert res.returncode == 0 and "note" not in res.stderr, res.stderr
