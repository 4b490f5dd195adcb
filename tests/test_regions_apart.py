"""Issue 43 item 7b: regions that do not touch.

With the fixed, free and handle regions as separate clusters (or only one of them apart), the
in-memory ``deform`` and ``select`` ended in ``internal error: ValueError: need at least one
array to concatenate`` and the streamed ``deform`` said ``regions.fixed: selects no point``
while ``select`` counted every fixed point. A region none of whose points has a neighbour edge
to the free region has no rings, so the edit is refused with the same one line in memory and
streamed (naming the region), and the streamed ``select`` counts what the in-memory masks
hold. Seeded clusters; every run in a subprocess; nothing written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import one_error_line, run_cli, snapshot, write_config

import splatdeform as sd
from splatdeform.model import PointModel

N = 40_000   # streams under --memory-budget 64MB
BUDGET = ["--memory-budget", "64MB"]


def _clusters(folder: Path, seed: int, gap_fixed: float, gap_handle: float
              ) -> tuple[Path, dict[str, int]]:
    """A fixed cube [0,1]^3, a free slab after ``gap_fixed``, a handle cube after
    ``gap_handle``; the config with boxes around each; the true counts."""
    rng = np.random.default_rng(seed)
    f0 = 1.0 + gap_fixed
    h0 = f0 + 1.0 + gap_handle
    parts = [rng.uniform([0, 0, 0], [1, 1, 1], (N // 2, 3)),
             rng.uniform([f0, 0, 0], [f0 + 1, 1, 1], (N // 4, 3)),
             rng.uniform([h0, 0, 0], [h0 + 1, 1, 1], (N // 4, 3))]
    sd.save(PointModel(positions=np.vstack(parts).astype(np.float32)), folder / "three.ply")
    eps = min(gap_fixed, gap_handle, 0.2) / 4
    text = ("input: three.ply\noutput: out.ply\nregions:\n  units: model\n"
            f"  fixed: [{{box: {{min: [-0.1,-0.1,-0.1], max: [{1 + eps},1.1,1.1]}}}}]\n"
            f"  handle: [{{box: {{min: [{h0 - eps},-0.1,-0.1], max: [{h0 + 1.1},1.1,1.1]}}}}]\n"
            "handle:\n  transform: {translate: [0, 0.5, 0]}\n")
    counts = {"fixed": N // 2, "handle": N // 4, "free": N // 4}
    return write_config(folder, text), counts


CASES = {
    # name: (gap after the fixed cube, gap before the handle cube, the region refused)
    "three_clusters": (2.0, 2.0, "regions.fixed"),
    "fixed_apart": (0.5, 0.0, "regions.fixed"),
    "handle_apart": (0.0, 0.5, "regions.handle"),
    "all_close_apart": (0.3, 0.3, "regions.fixed"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_separate_regions_one_line_in_memory_and_streamed(tmp_path, case):
    gap_f, gap_h, key = CASES[case]
    config, counts = _clusters(tmp_path, 7 + len(case), gap_f, gap_h)
    what = key.split(".")[1]
    needles = [key, f"no {what} point is adjacent to the free region", "separate cluster"]
    before = snapshot(tmp_path)
    lines = {}
    for name, args in {"deform": ["deform", config], "select": ["select", config],
                       "deform streamed": ["deform", config, "--quiet", *BUDGET]}.items():
        lines[name] = one_error_line(run_cli(*args, cwd=tmp_path), 2, needles)
        assert snapshot(tmp_path) == before, f"{name} wrote files"
    # one message, whichever path
    tail = {name: line.split("error: ", 1)[1] for name, line in lines.items()}
    assert len(set(tail.values())) == 1, tail
    # the streamed select counts what the masks hold (rings: see deform)
    res = run_cli("select", config, *BUDGET, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    out = " ".join(res.stdout.split())
    for region, count in counts.items():
        assert f"{region} {count:,}" in out, (region, out)


def test_touching_regions_still_deform_alike(tmp_path):
    """The control: the same clusters with no gaps deform in memory and streamed, and the
    fixed cube stays bit for bit."""
    config, _ = _clusters(tmp_path, 3, 0.0, 0.0)
    res = run_cli("deform", config, "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    whole = sd.load(tmp_path / "out.ply").positions
    (tmp_path / "out.ply").unlink()
    res = run_cli("deform", config, "--quiet", *BUDGET, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    streamed = sd.load(tmp_path / "out.ply").positions
    before = sd.load(tmp_path / "three.ply").positions
    assert np.array_equal(whole[: N // 2], before[: N // 2])
    assert np.array_equal(streamed[: N // 2], before[: N // 2])
    assert np.abs(whole - streamed).max() < 1e-3


def test_points_edit_with_a_separate_fixed_cluster(tmp_path):
    """Control-point pairs in the free cluster and a fixed cluster apart: the same line from
    deform and select (the fixed rings of a points: edit)."""
    config, _ = _clusters(tmp_path, 5, 2.0, 2.0)
    text = config.read_text().split("  handle:")[0]
    config.write_text(text + "points:\n  pairs: [[3.5,0.5,0.5,3.5,0.7,0.5], "
                      "[3.2,0.2,0.8,3.2,0.3,0.8]]\n")
    before = snapshot(tmp_path)
    lines = {cmd: one_error_line(run_cli(cmd, config, cwd=tmp_path), 2,
                                 ["regions.fixed", "no fixed point is adjacent"])
             for cmd in ("deform", "select")}
    assert lines["deform"] == lines["select"]
    assert snapshot(tmp_path) == before
