"""Issue 38: the default fit on the stand-ins of three real scans (``data_tools/standins.py``).

Mesh rings (one vertex wide) and the coarse rings of a small SH3 splat tile are thinned now;
whatever the thinning drops, ``fit.method: auto`` still meets every ring point within its
boundary factor of tolerances. The small-m dense path is the same interpolant as scipy's
``RBFInterpolator(kernel="cubic", degree=1)``. Everything is deterministic.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_file
from scipy.interpolate import RBFInterpolator

from splatdeform.basis.reference import evaluate_field
from splatdeform.deform.rings import boundary_rings, region_adjacency
from splatdeform.deform.thin import SPACING_FLOOR, thin_rings
from splatdeform.model import PointModel
from splatdeform.rbf.auto import BOUNDARY_FACTOR, fit_auto, point_errors
from splatdeform.rbf.defaults import DEFAULT_TOLERANCE
from splatdeform.rbf.exact import fit_exact
from splatdeform.rbf.result import Normalization


def sheet_mesh(nx: int = 300, ny: int = 200) -> PointModel:
    """A bumpy triangulated sheet (nx * ny vertices (N, 3), 2 (nx-1)(ny-1) faces (F, 3)),
    vertices jittered (seeded) by a fifth of the grid step: a scanned mesh's irregularity."""
    x, y = np.meshgrid(np.linspace(0, 3, nx), np.linspace(0, 1, ny), indexing="ij")
    rng = np.random.default_rng(38)
    step = 3.0 / (nx - 1)
    x = x + 0.2 * step * rng.uniform(-1, 1, x.shape)
    y = y + 0.2 * step * rng.uniform(-1, 1, y.shape)
    z = 0.1 * np.sin(2 * x) * np.cos(3 * y)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return PointModel(positions=np.stack([x.ravel(), y.ravel(), z.ravel()], 1), faces=faces,
                      kind="mesh")


def edit_constraints(model: PointModel, neighbors: int = 10, fixed_end: float = 0.3,
                     handle_start: float = 0.8):
    """(ring index arrays, constraint points (m, 3), rhs (m, 2)) of a two-region edit along the
    longest axis: rhs columns are the fixed (0) and handle (1) indicator, as the basis M."""
    pos = model.positions
    lo, hi = pos.min(0), pos.max(0)
    axis = int(np.argmax(hi - lo))
    t = (pos[:, axis] - lo[axis]) / (hi[axis] - lo[axis])
    fixed, handle = t <= fixed_end, t >= handle_start
    adj = region_adjacency(model, fixed, handle, neighbors, 4)
    f_rings, h_rings = boundary_rings(adj, fixed, handle, 3)
    rings = f_rings + h_rings
    idx = np.concatenate(rings)
    rhs = np.stack([fixed[idx], handle[idx]], 1).astype(np.float64)
    return rings, pos[idx], rhs


def check_every_ring_point(model: PointModel, neighbors: int = 10, **edit):
    """The thinned default fit of the edit: (kept mask (m,), fit, largest |r| / tolerance over
    every ring point)."""
    rings, pts, rhs = edit_constraints(model, neighbors, **edit)
    kept = thin_rings(model.positions, rings, neighbors, 1.0)
    fit = fit_auto(pts, rhs, kept=kept, tolerance=DEFAULT_TOLERANCE,
                   normalization=Normalization.of(model.positions), threads=1)
    err = point_errors(fit, pts, rhs)
    assert err.shape == (pts.shape[0],)
    return kept, fit, float(err.max()) / DEFAULT_TOLERANCE


def test_mesh_rings_are_thinned_and_still_met_at_every_ring_point():
    model = sheet_mesh()
    kept, fit, worst = check_every_ring_point(model)
    m = kept.size
    # one vertex wide rings keep about one point in SPACING_FLOOR (they used to keep ~all)
    assert kept.sum() < 0.75 * m
    assert kept.sum() > m / (2.0 * SPACING_FLOOR ** 2)
    assert fit.converged
    assert worst <= BOUNDARY_FACTOR


def test_thinning_and_the_thinned_fit_are_deterministic():
    model = sheet_mesh(150, 200)
    rings, pts, rhs = edit_constraints(model)
    k1 = thin_rings(model.positions, rings, 10, 1.0)
    k2 = thin_rings(model.positions, [r.copy() for r in rings], 10, 1.0)
    assert np.array_equal(k1, k2)
    f1 = fit_auto(pts, rhs, kept=k1, threads=1)
    f2 = fit_auto(pts, rhs, kept=k2, threads=2)
    assert np.array_equal(f1.centers, f2.centers)
    assert np.allclose(f1.weights, f2.weights, rtol=0, atol=1e-9 * np.abs(f1.weights).max())


@pytest.mark.parametrize("m", [12, 60, 200, 724])
def test_small_dense_path_is_scipys_interpolant(m):
    rng = np.random.default_rng(m)
    pts = rng.normal(size=(m, 3)) * [3.0, 1.0, 0.5] + [100.0, -20.0, 5.0]
    rhs = rng.random((m, 2))
    with_scipy = RBFInterpolator(pts, rhs, kernel="cubic", degree=1)
    probe = np.vstack([pts[: min(m, 50)], rng.normal(size=(200, 3)) * [3.0, 1.0, 0.5]
                       + [100.0, -20.0, 5.0]])
    want = with_scipy(probe)
    scale = np.abs(want).max()
    for fit in (fit_exact(pts, rhs, threads=1), fit_auto(pts, rhs, threads=1)):
        got = evaluate_field(probe, fit)
        assert np.abs(got - want).max() <= 1e-8 * scale
        assert np.abs(evaluate_field(pts, fit) - rhs).max() <= 1e-8


def test_small_dense_path_merges_duplicates_as_before():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(80, 3))
    rhs = rng.random((80, 1))
    dup_p = np.vstack([pts, pts[:5]])
    dup_b = np.vstack([rhs, rhs[:5]])
    fit = fit_auto(dup_p, dup_b, threads=1)
    assert fit.n_centers == 80
    assert np.allclose(fit.weights, fit_exact(pts, rhs, threads=1).weights, atol=1e-10)


# --------------------------------------------------------- the stand-ins (../shared/data)

@pytest.fixture(scope="module")
def standins():
    shared_file("splats/tile_3dgs_sh3.ply")
    from data_tools import standins as module

    return module


def test_sh3_tile_standin_coarse_rings_are_thinned_and_met(standins):
    make, neighbors, fixed_end, handle_start = standins.STANDINS["standin SH3 tile 14k"]
    model = make()
    assert 13_000 <= model.n_points <= 14_000
    kept, fit, worst = check_every_ring_point(model, neighbors, fixed_end=fixed_end,
                                              handle_start=handle_start)
    assert 2_000 <= kept.size <= 2_400  # near the real tile's 2,196
    assert kept.sum() < 0.5 * kept.size
    assert fit.method == "exact-kept"
    went = fit.kept if fit.kept is not None else kept
    assert went.sum() < 0.6 * kept.size  # far from the solve through all 2,187
    assert worst <= BOUNDARY_FACTOR


def test_mesh_standin_rings_are_thinned_and_met(standins):
    make, neighbors, fixed_end, handle_start = standins.STANDINS["standin mesh 134k"]
    model = make()
    assert model.n_points == 134_345 and model.n_faces > 0
    kept, fit, worst = check_every_ring_point(model, neighbors, fixed_end=fixed_end,
                                              handle_start=handle_start)
    assert kept.size == 2_754
    assert kept.sum() < 0.6 * kept.size  # was 2,248 kept with cells of one spacing
    assert worst <= BOUNDARY_FACTOR
