"""Ring thinning and ``fit.method: auto``: kept points are a subset of the rings, dropped ring
points are exact, auto picks by predicted cost, the reported boundary error covers every ring
point, results are deterministic, and the default fit stays close to scipy's exact interpolant
through every ring point (the oracle)."""

from __future__ import annotations

import re
from functools import partial

import numpy as np
import pytest
import yaml
from scipy.interpolate import RBFInterpolator

from data_tools.synth import sphere
from splatdeform import deform as sd
from splatdeform.basis import compute_basis
from splatdeform.basis.reference import evaluate_field
from splatdeform.deform.handle import compose_transform
from splatdeform.deform.rings import boundary_rings, region_adjacency
from splatdeform.deform.thin import (
    COARSE_CELL,
    SPACING_FLOOR,
    ring_width,
    thin_ring,
    thin_rings,
)
from splatdeform.edit.config import load_edit
from splatdeform.edit.run import format_report, run_edit
from splatdeform.io import save
from splatdeform.model import PointModel
from splatdeform.rbf.auto import (
    SMALL_DENSE,
    choose_method,
    dense_seconds,
    fit_auto,
    incremental_seconds,
    point_errors,
)
from splatdeform.rbf.exact import _solve, _solve_indefinite, dense_threads, fit_exact

NUMPY_BASIS = partial(compute_basis, gradients=False, backend="numpy")


def noisy_shell(n: int = 30_000, jitter: float = 1.5, seed: int = 4) -> PointModel:
    """A splat-like sphere: positions jittered normal to the surface by ``jitter`` times the
    point spacing (a thick, noisy 3D shell)."""
    model = sphere(n, seed=seed)
    rng = np.random.default_rng(seed)
    spacing = np.sqrt(4 * np.pi / n)
    pos = model.positions * (1 + jitter * spacing * rng.standard_normal((n, 1)))
    return PointModel(positions=pos)


def grid_sheet(nx: int = 600, ny: int = 200) -> PointModel:
    """A smooth, regularly sampled bumpy sheet: few centers meet the tolerance."""
    x, y = np.meshgrid(np.linspace(0, 3, nx), np.linspace(0, 1, ny), indexing="ij")
    z = 0.1 * np.sin(2 * x) * np.cos(3 * y)
    return PointModel(positions=np.stack([x.ravel(), y.ravel(), z.ravel()], 1))


def edit_masks(model: PointModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = model.positions[:, 0]
    lo, hi = x.min(), x.max()
    fixed = x < lo + 0.3 * (hi - lo)
    handle = x > lo + 0.75 * (hi - lo)
    matrix = compose_transform(pivot=model.positions[handle].mean(0), axis=(0, 0, 1),
                               degrees=25.0, translate=(0.0, 0.1, 0.0))
    return fixed, handle, matrix


@pytest.fixture(scope="module")
def shell() -> PointModel:
    return noisy_shell()


@pytest.fixture(scope="module")
def shell_def(shell):
    fixed, handle, _ = edit_masks(shell)
    return sd.prepare_handle(shell, fixed, handle, method="incremental", backend="numpy")


# ------------------------------------------------------------------------------- thinning

def test_line_ring_keeps_about_one_in_the_floor_and_thick_shell_loses_most():
    # a mesh ring one vertex wide: points along a curve, spacing 1. Its cells are at least
    # SPACING_FLOOR spacings (they used to be one, keeping every point: issue 38)
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    curve = np.stack([60 / np.pi * np.cos(t), 60 / np.pi * np.sin(t), np.zeros_like(t)], 1)
    width, spacing = ring_width(curve, 10)
    assert width == pytest.approx(spacing, rel=0.1)
    kept = thin_ring(curve, 10, 1.0)
    assert 0.35 * curve.shape[0] <= kept.size <= 0.75 * curve.shape[0]
    gap = np.linalg.norm(curve[:, None] - curve[kept][None], axis=2).min(axis=1)
    assert gap.max() <= SPACING_FLOOR * spacing
    # a thick noisy slab: 4000 points in a 40 x 4 x 4 box
    rng = np.random.default_rng(0)
    slab = rng.uniform([0, 0, 0], [40, 4, 4], size=(4000, 3))
    kept = thin_ring(slab, 10, 0.75)
    assert kept.size < 0.5 * slab.shape[0]
    assert np.array_equal(kept, np.unique(kept))
    assert thin_ring(slab, 10, 0.0).size == slab.shape[0]  # 0 keeps every point


def test_ring_with_cells_coarse_for_the_ring_set_is_thinned_at_the_coarse_cell():
    # a sparse 20^3 cube ring next to a dense slab 5x as long: its cells would be wider than
    # COARSE_CELL of the extent of both rings, so it is thinned at that cell (it used to be
    # kept whole: issue 38), keeping more than alone; the slab is still thinned
    rng = np.random.default_rng(1)
    chunky = rng.uniform([0, 0, 0], [20, 20, 20], size=(200, 3))
    long = rng.uniform([0, 30, 0], [100, 34, 4], size=(4000, 3))
    positions = np.vstack([chunky, long])
    rings = [np.arange(200), np.arange(200, 4200)]
    width, _ = ring_width(chunky, 10)
    extent = float(np.linalg.norm(positions.max(0) - positions.min(0)))
    assert width > COARSE_CELL * extent > ring_width(long, 10)[0]
    kept = thin_rings(positions, rings, 10, 1.0)
    alone = thin_ring(chunky, 10, 1.0).size  # alone, its own extent is not coarse
    assert alone < kept[:200].sum() < 200
    assert np.array_equal(np.flatnonzero(kept[:200]),
                          thin_ring(chunky, 10, 1.0, COARSE_CELL * extent))
    assert kept[200:].sum() < 0.5 * 4000


def test_kept_points_are_a_well_spread_subset_of_every_ring(shell, shell_def):
    d = shell_def
    assert d.kept is not None and d.kept.shape == d.constraint_idx.shape
    assert 0 < d.n_kept < d.constraint_idx.size
    # the rings, found independently: the kept points are ring points, every ring keeps some
    fixed, handle = d.fixed, d.moving
    adj = region_adjacency(shell, fixed, handle, 10, 4)
    f_rings, h_rings = boundary_rings(adj, fixed, handle, 3)
    rings = f_rings + h_rings
    assert np.array_equal(d.constraint_idx, np.concatenate(rings))
    start = 0
    for ring in rings:
        part = d.kept[start:start + ring.size]
        start += ring.size
        assert part.any()
        # well spread: every dropped point has a kept point of its ring within 2 ring widths
        width, _ = ring_width(shell.positions[ring], 10)
        dist = np.linalg.norm(shell.positions[ring][~part][:, None]
                              - shell.positions[ring][part][None], axis=2).min(axis=1)
        assert dist.max() <= 2.0 * width


def test_dropped_ring_points_are_exact(shell, shell_def):
    d = shell_def
    _, _, matrix = edit_masks(shell)
    out = sd.apply(d, shell, sd.delta_for(d, matrix), moving_matrix=matrix)
    dropped = d.constraint_idx[~d.kept]
    f_drop = dropped[d.fixed[dropped]]
    h_drop = dropped[d.moving[dropped]]
    assert f_drop.size and h_drop.size
    assert np.array_equal(out.positions[f_drop], shell.positions[f_drop])  # bit-exact
    want = shell.positions[h_drop] @ matrix[:3, :3].T + matrix[:3, 3]
    np.testing.assert_allclose(out.positions[h_drop], want, rtol=0,
                               atol=1e-12 * shell.diagonal())


def test_tolerance_holds_on_kept_and_error_covers_every_ring_point(shell, shell_def):
    d = shell_def
    _, _, matrix = edit_masks(shell)
    delta = sd.delta_for(d, matrix)
    r = evaluate_field(d.constraint_points, d.fit) - d.constraint_rhs  # (m, 4)
    assert np.abs(r[d.kept]).max() <= d.fit.tolerance * (1 + 1e-9)
    dist = np.linalg.norm(r @ delta, axis=1)
    err, rms = sd.constraint_errors(d, delta, NUMPY_BASIS)
    assert err == pytest.approx(dist.max(), rel=1e-9)
    assert rms == pytest.approx(np.sqrt(np.mean(dist ** 2)), rel=1e-9)
    assert err >= dist[d.kept].max()


def test_prepare_is_deterministic(shell, shell_def):
    fixed, handle, _ = edit_masks(shell)
    again = sd.prepare_handle(shell, fixed, handle, method="incremental", backend="numpy")
    assert np.array_equal(again.kept, shell_def.kept)
    assert np.array_equal(again.fit.centers, shell_def.fit.centers)
    assert np.array_equal(again.fit.weights, shell_def.fit.weights)


def test_default_fit_close_to_scipy_through_every_ring_point(shell):
    """The oracle: scipy RBFInterpolator(cubic, degree 1) through all ring points."""
    fixed, handle, matrix = edit_masks(shell)
    d = sd.prepare_handle(shell, fixed, handle, backend="numpy")  # defaults: auto, thinning
    delta = sd.delta_for(d, matrix)
    moved = shell.positions[handle] @ matrix[:3, :3].T + matrix[:3, 3]
    largest = np.linalg.norm(moved - shell.positions[handle], axis=1).max()
    exact = RBFInterpolator(d.constraint_points, d.constraint_rhs @ delta, kernel="cubic",
                            degree=1)
    free = shell.positions[d.free_idx[::7]]
    dev = np.linalg.norm(evaluate_field(free, d.fit) @ delta - exact(free), axis=1).max()
    assert dev <= 0.03 * largest
    err = sd.constraint_error(d, delta, NUMPY_BASIS)
    assert err <= 1e-3 * largest
    assert d.fit.converged


# ------------------------------------------------------------------------------ fit methods

def test_auto_picks_by_predicted_cost():
    small = choose_method(300, 280, 2)
    assert small.method == "exact" and small.dense <= small.incremental_start
    # a small scene solves densely at once, through the kept points (predicted cheaper)
    small_thinned = choose_method(1200, 300, 1)
    assert small_thinned.method == "exact-kept"
    assert small_thinned.dense_kept < small_thinned.dense <= SMALL_DENSE
    # a tiny one (a few milliseconds) through every point, however much thinning dropped
    assert choose_method(500, 100, 1).method == "exact"
    large = choose_method(9000, 3000, 2)
    assert large.method == "incremental" and large.incremental_start < large.dense
    assert choose_method(20_000, 5000, 16).method == "incremental"  # beyond the dense limit
    assert dense_seconds(20_000, 16) == np.inf
    assert incremental_seconds(1000, 200) < incremental_seconds(1000, 400)
    assert dense_seconds(2000, 4) < dense_seconds(2000, 1)


def test_auto_runs_exact_on_a_small_scene_and_incremental_on_a_large_one(shell):
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3))
    rhs = rng.normal(size=(200, 4))
    fit = fit_auto(pts, rhs, threads=1)
    assert fit.method == "exact" and fit.converged and fit.n_centers == 200
    sheet = grid_sheet()
    fixed, handle, _ = edit_masks(sheet)
    d = sd.prepare_handle(sheet, fixed, handle, backend="numpy", threads=1)
    assert d.fit.method == "incremental" and d.fit.converged
    assert d.n_kept < d.constraint_idx.size and d.fit.n_centers < d.n_kept
    assert choose_method(d.constraint_idx.size, d.n_kept, 1).method == "incremental"
    # a noisy shell needs nearly a center per kept point: the dense solve through the kept
    # points (plus those it missed) is cheaper; it interpolates every point it went through,
    # and the deformation's kept count says which
    fixed, handle, _ = edit_masks(shell)
    d = sd.prepare_handle(shell, fixed, handle, backend="numpy", threads=1)
    assert d.fit.method == "exact-kept" and d.fit.converged
    assert d.fit.n_centers == d.n_kept < d.constraint_idx.size
    err = point_errors(d.fit, d.constraint_points[d.kept], d.constraint_rhs[d.kept])
    assert err.max() <= 1e-8


def test_auto_switches_to_exact_when_incremental_would_not_converge():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(600, 3))
    rhs = rng.normal(size=(600, 2))  # noise: needs every point as a center
    fit = fit_auto(pts, rhs, tolerance=1e-9, max_centers=20, threads=1)
    assert fit.method == "exact" and fit.converged
    np.testing.assert_allclose(evaluate_field(pts, fit), rhs, atol=1e-7)


def test_exact_matches_scipy_and_the_indefinite_solve():
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(700, 3))
    rhs = rng.normal(size=(700, 3))
    fit = fit_exact(pts, rhs, threads=1)
    q = rng.normal(size=(300, 3))
    oracle = RBFInterpolator(pts, rhs, kernel="cubic", degree=1)(q)
    np.testing.assert_allclose(evaluate_field(q, fit), oracle, atol=1e-7 * np.abs(oracle).max())
    x = fit.normalization.apply(pts)
    a1, w1 = _solve(x, rhs)
    a2, w2 = _solve_indefinite(x, rhs)
    np.testing.assert_allclose(np.vstack([a1, w1]), np.vstack([a2, w2]), rtol=0,
                               atol=1e-7 * np.abs(w2).max())


def test_dense_threads_default_and_overrides(monkeypatch):
    import os

    for name in ("SPLATDEFORM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                 "OMP_NUM_THREADS"):
        monkeypatch.delenv(name, raising=False)
    assert dense_threads() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert dense_threads() == 3
    monkeypatch.setenv("SPLATDEFORM_THREADS", "5")
    assert dense_threads() == 5
    assert dense_threads(2) == 2


# ------------------------------------------------------------------------------ the report

def test_report_counts_kept_and_errors_equal_independent_evaluation(shell, tmp_path):
    save(shell, tmp_path / "shell.ply")
    cfg = {"input": "shell.ply", "output": "out.ply", "backend": "numpy",
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                       "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"rotate": {"axis": [0, 0, 1], "degrees": 25}}},
           "fit": {"method": "incremental", "threads": 1}}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    result = run_edit(load_edit(tmp_path / "e.yaml"), tmp_path, save_output=False)
    d = result.deformation
    text = format_report(result)
    m = re.search(r"constraints ([\d,]+) \(kept ([\d,]+)\)", text)
    assert m, text
    assert int(m.group(1).replace(",", "")) == d.constraint_idx.size
    assert int(m.group(2).replace(",", "")) == d.n_kept < d.constraint_idx.size
    assert result.stats["method"] == "incremental"
    # independent: the reference evaluator over every ring point, found again from the masks
    adj = region_adjacency(result.model, d.fixed, d.moving, 10, 4)
    f_rings, h_rings = boundary_rings(adj, d.fixed, d.moving, 3)
    ring = np.concatenate(f_rings + h_rings)
    target = np.zeros((ring.size, 3))
    hm = d.moving[ring]
    pts = result.model.positions[ring]
    target[hm] = pts[hm] @ result.matrix[:3, :3].T + result.matrix[:3, 3] - pts[hm]
    field = evaluate_field(pts, d.fit) @ result.delta_c
    dist = np.linalg.norm(field - target, axis=1)
    shown = float(re.search(r"over all [\d,]+ ring points: max ([\d.e+-]+)", text).group(1))
    assert shown == pytest.approx(dist.max(), rel=2e-3)  # printed to 3 significant digits
    assert result.stats["constraint_error"] == pytest.approx(dist.max(), rel=1e-9)


def test_reuse_cache_stores_the_kept_subset(shell, shell_def, tmp_path):
    from splatdeform.edit.cache import FORMAT_VERSION, load_deformation, save_deformation

    assert FORMAT_VERSION >= 6
    path = save_deformation(tmp_path / "d.npz", "key", shell_def)
    back = load_deformation(path, "key", shell)
    assert np.array_equal(back.kept, shell_def.kept) and back.n_kept == shell_def.n_kept
    assert back.ring_sizes == shell_def.ring_sizes
    assert back.fit.method == shell_def.fit.method


def test_auto_dense_through_the_kept_points_meets_every_ring_point():
    """Where the dense solve through the thinned points is predicted cheapest, ``auto`` runs it
    ("exact-kept"): it interpolates every point it went through (the thinned subset plus the
    ring points a first solve missed) and misses no ring point by more than 10 tolerances."""
    from splatdeform.rbf.auto import BOUNDARY_FACTOR

    rng = np.random.default_rng(5)
    u = rng.random((3000, 2))
    pts = np.column_stack([u, 0.05 * np.sin(6 * u[:, 0]) + 1e-3 * rng.random(3000)])
    rhs = np.column_stack([np.cos(3 * pts[:, 0]), pts[:, 1] ** 2, pts[:, 0] * pts[:, 1]])
    kept = np.zeros(3000, dtype=bool)
    kept[::4] = True
    choice = choose_method(3000, int(kept.sum()), 1)
    assert choice.dense_kept < choice.dense
    tol = 1e-5
    fit = fit_auto(pts, rhs, kept=kept, tolerance=tol, threads=1, max_centers=20)
    assert fit.method == "exact-kept" and fit.converged
    used = kept if fit.kept is None else fit.kept
    assert np.all(used[kept])  # a superset of the thinned subset
    assert fit.n_centers == int(used.sum()) < 3000
    err = point_errors(fit, pts, rhs)
    assert np.all(err[used] <= 1e-8) and err.max() <= BOUNDARY_FACTOR * tol
    again = fit_auto(pts, rhs, kept=kept, tolerance=tol, threads=1, max_centers=20)
    assert np.array_equal(again.weights, fit.weights)  # deterministic
    two = fit_auto(pts, rhs, kept=kept, tolerance=tol, threads=2, max_centers=20)
    assert (two.method, two.n_centers) == (fit.method, fit.n_centers)  # whatever the threads
    # a tiny scene (the solve through all of it predicted a few ms) goes through every point
    small = fit_auto(pts[:500], rhs[:500], kept=kept[:500], tolerance=tol, threads=1)
    assert small.method == "exact" and small.n_centers == 500
