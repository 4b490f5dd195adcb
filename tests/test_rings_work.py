"""Rings at memory speed (issue 45 item 2), by work counts, never timings (those are in
benchmarks/bench_rings.py): the in-memory rings put fewer points through kd-trees than the
streamed plan of the same file; the kNN over the border band answers as the whole-model tree;
the streamed border passes (3 and 4) run once when the border radius grows; the band's cells
need no sort of the points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fixtures import stream_edit

from data_tools.synth import bumpy_bar
from splatdeform.deform import border, cells, rings
from splatdeform.edit.config import EditConfig
from splatdeform.edit.plain import handle_matrix, make_fit_fn
from splatdeform.edit.stream import plan as stream_plan
from splatdeform.io import open_chunks, save
from splatdeform.model import PointModel


class KnnWork:
    """Counts the points that enter kd-trees (each tree once) and queries, over the modules
    that search neighbours (the in-memory rings, the cells, the streamed border)."""

    def __init__(self, monkeypatch) -> None:
        self.tree_points = 0
        self.queries = 0
        self._last = None
        for mod in (rings, cells, border):
            monkeypatch.setattr(mod, "knn_query", self._wrap(mod.knn_query))

    def _wrap(self, real):
        def query(tree, points, **kwargs):
            if tree is not self._last:
                self.tree_points += tree.n
                self._last = tree
            self.queries += len(points)
            return real(tree, points, **kwargs)
        return query

    def take(self) -> tuple[int, int]:
        out = (self.tree_points, self.queries)
        self.tree_points = self.queries = 0
        self._last = None
        return out


def _config(path: Path) -> EditConfig:
    return EditConfig.model_validate(dict(stream_edit(), input=str(path), output="out.ply"))


def _plan(path: Path, cfg: EditConfig, chunk: int = 250_000) -> stream_plan.Plan:
    return stream_plan.build_plan(open_chunks(path), cfg, path.parent, chunk=chunk, quiet=True,
                                  max_border=20_000_000, make_fit_fn=make_fit_fn,
                                  handle_matrix=handle_matrix)


@pytest.mark.slow
def test_in_memory_rings_do_less_knn_work_than_streaming_on_2m_points(tmp_path: Path,
                                                                        monkeypatch) -> None:
    """2M points: the in-memory rings' kd-trees hold the border band, not the model, and hold
    fewer points (and answer fewer queries) than the streamed plan's; the graph is the one the
    whole-model tree gives (same rings)."""
    path = tmp_path / "bar2m.ply"
    save(PointModel(positions=bumpy_bar(2_000_000, seed=7).positions), path)
    cfg = _config(path)
    work = KnnWork(monkeypatch)
    plan = _plan(path, cfg)
    streamed = work.take()
    positions = open_chunks(path).positions(0, 2_000_000)
    labels = plan.labels.astype(np.int8)
    stats: dict = {}
    adj = rings.border_knn_adjacency(positions, labels, cfg.boundary.neighbors,
                                     cfg.boundary.continuity + 2, stats=stats)
    in_memory = work.take()
    assert stats["tree_points"] < 0.2 * positions.shape[0] and stats["fallback"] == 0
    assert in_memory[0] <= streamed[0] and in_memory[1] <= streamed[1], (in_memory, streamed)
    fixed, handle = labels == 1, labels == 2
    ours = rings.boundary_rings(adj, fixed, handle, cfg.boundary.continuity + 1)
    ring_pts = np.unique(np.concatenate(ours[0] + ours[1]))
    assert np.isin(plan.border.constraint_idx, ring_pts).all()
    assert ring_pts.size == plan.border.constraint_idx.size


def test_subset_knn_answers_as_the_whole_tree_with_ties() -> None:
    """A quantised grid (every distance tied many times): queries whose k-th neighbour ties go
    to the whole-model tree, the rest are certified inside the subset: the neighbour sets are
    the whole tree's, row by row."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    pts = np.round(rng.uniform(0, 40, size=(30_000, 3))) / 4  # many exact ties
    pts = np.unique(pts, axis=0)
    labels = (pts[:, 0] > 5).astype(np.int8)
    grid = cells.Cells(pts, 1.0)
    core = grid.label_border(labels)
    search = cells.SubsetKnn(pts, grid, cells.levels_around(grid, core, 2), 2)
    idx = np.flatnonzero(core[grid.cell])
    got = np.sort(search.query(idx, 8), axis=1)
    want = np.sort(cKDTree(pts).query(pts[idx], k=8)[1], axis=1)
    np.testing.assert_array_equal(got, want)
    assert 0 < search.fallback < idx.size   # ties went to the whole tree, not everything


def test_knn_radius_is_the_whole_trees_value() -> None:
    """The band's radius (a quantile over a seeded sample) from subset trees equals the
    whole-model tree's value exactly, so the band is the same points as before."""
    from scipy.spatial import cKDTree

    model = bumpy_bar(1_000_000, seed=8)
    pts = model.positions
    radius, whole = rings.knn_radius(pts, 10)
    assert whole is None  # answered without a whole-model tree
    idx = rings.sample_indices(pts.shape[0])
    want = float(np.quantile(cKDTree(pts).query(pts[idx], k=11)[0][:, -1], 0.999))
    assert radius == want


def test_band_cells_without_sorting_the_points(monkeypatch) -> None:
    """The dense grid path: no np.unique / argsort over the points' keys (the sort that cost
    3-4.7 s at 5M); the band equals the sorted path's."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 1, size=(50_000, 3))
    labels = (pts[:, 0] > 0.5).astype(np.int8)
    dense = rings.border_band(pts, labels, 0.05)
    monkeypatch.setattr(cells, "_DENSE_PER_POINT", 0)
    monkeypatch.setattr(cells, "_DENSE_MIN", 0)
    sorted_band = rings.border_band(pts, labels, 0.05)
    np.testing.assert_array_equal(dense, sorted_band)
    calls = []
    real_unique = np.unique
    monkeypatch.setattr(cells, "_DENSE_PER_POINT", 8)
    monkeypatch.setattr(cells, "_DENSE_MIN", 1 << 22)
    monkeypatch.setattr(np, "unique", lambda a, *x, **k: calls.append(np.size(a))
                        or real_unique(a, *x, **k))
    rings.border_band(pts, labels, 0.05)
    assert all(size < pts.shape[0] for size in calls)


def test_streamed_border_passes_run_once_when_the_radius_grows(tmp_path: Path,
                                                               monkeypatch) -> None:
    """A first border radius too small for the rings (enlarged once): passes 3 and 4 gather
    the points once and the larger border set is filtered in memory; the plan (border set,
    constraints, fit) is the one re-reading the file gives."""
    path = tmp_path / "bar.ply"
    save(bumpy_bar(60_000, seed=4), path)
    cfg = _config(path)
    real_initial = stream_plan.initial_radius
    monkeypatch.setattr(stream_plan, "initial_radius",
                        lambda *a: 0.7 * real_initial(*a))  # needs one enlargement
    calls: list[float] = []
    real_gather = stream_plan.gather_border

    def gather(*args, **kwargs):
        calls.append(args[4])
        return real_gather(*args, **kwargs)

    monkeypatch.setattr(stream_plan, "gather_border", gather)
    once = _plan(path, cfg, chunk=7_000)
    assert len(calls) == 1
    calls.clear()
    monkeypatch.setattr(stream_plan, "_GATHER", 1.0)  # as before: each radius its own passes
    again = _plan(path, cfg, chunk=7_000)
    assert len(calls) >= 2 and once.radius == again.radius
    assert once.border_points == again.border_points
    np.testing.assert_array_equal(once.border.constraint_idx, again.border.constraint_idx)
    np.testing.assert_array_equal(once.border.fit.weights, again.border.fit.weights)
