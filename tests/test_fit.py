"""Incremental QR fitter: properties against independent oracles (affine maps, scipy)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from splatdeform.basis.reference import evaluate_field
from splatdeform.errors import InputError
from splatdeform.rbf import Normalization, farthest_point_order, fit_incremental, kernel_matrix
from splatdeform.rbf import kernel as rbf_kernel
from splatdeform.rbf.exact import distinct_rows, fit_exact, unique_constraints


def bumpy_cylinder(n: int, rng: np.random.Generator, z_lo: float = 0.0, z_hi: float = 1.0):
    """(n, 3) points on a bumpy cylinder of radius ~0.15 along z in [z_lo, z_hi]."""
    t = rng.uniform(0.0, 2 * np.pi, n)
    z = rng.uniform(z_lo, z_hi, n)
    rad = 0.15 * (1.0 + 0.15 * np.sin(5 * t) * np.sin(9 * z))
    return np.column_stack([rad * np.cos(t), rad * np.sin(t), z])


def rotation_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def handle_setup(seed: int = 0, per_band: int = 300):
    """Fixed band (z in [0.15, 0.2]) with zero displacement, handle band (z in [0.8, 0.85]) with a
    rotation + translation; free points in between. Returns (points, disp, free)."""
    rng = np.random.default_rng(seed)
    fixed = bumpy_cylinder(per_band, rng, 0.15, 0.2)
    handle = bumpy_cylinder(per_band, rng, 0.8, 0.85)
    free = bumpy_cylinder(2000, rng, 0.2, 0.8)
    pivot = np.array([0.0, 0.0, 0.825])
    moved = (handle - pivot) @ rotation_x(25.0).T + pivot + np.array([0.1, 0.05, 0.0])
    points = np.vstack([fixed, handle])
    disp = np.vstack([np.zeros_like(fixed), moved - handle])
    return points, disp, free


def bbox_diag(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def test_affine_rhs_needs_no_centers_and_is_reproduced():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(200, 3)) * [1.0, 2.0, 0.5] + [10.0, -3.0, 2.0]
    rhs = np.column_stack([np.ones(len(pts)), pts])  # [1, x, y, z]
    fit = fit_incremental(pts, rhs, tolerance=1e-9)
    assert fit.n_centers == 0 and fit.converged
    assert fit.residuals.shape == (1, 4)
    other = rng.normal(size=(500, 3)) * 3.0
    expected = np.column_stack([np.ones(len(other)), other])
    got = evaluate_field(other, fit)
    assert np.allclose(got, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("selection", ["greedy", "fps"])
def test_tolerance_bounds_the_largest_constraint_error(selection):
    """The contract: after a fit, max_ic |r_ic| <= tolerance, r = rhs - A W measured
    independently (evaluate the field at the constraints); the reported max/RMS are that r."""
    points, disp, _ = handle_setup(seed=2)
    tol = 1e-4 * bbox_diag(points)
    fit = fit_incremental(points, disp, tolerance=tol, selection=selection)
    assert fit.converged
    assert fit.residuals.shape == (1 + fit.n_centers, 3)
    assert np.all(np.diff(fit.residuals, axis=0) <= 0)  # the running 2-norm bound
    r = disp - evaluate_field(points, fit)
    assert np.abs(r).max() <= tol
    assert fit.max_error == pytest.approx(np.abs(r).max(), rel=1e-6)
    assert fit.rms_error == pytest.approx(np.sqrt(np.mean(r * r)), rel=1e-6)
    # not the 2-norm over all constraints: that is ~sqrt(m) stricter and is not met here
    assert np.any(fit.residuals[-1] > tol)


def test_stops_at_the_first_column_that_meets_the_max_norm():
    points, disp, _ = handle_setup(seed=2)
    tol = 3e-4 * bbox_diag(points)
    fit = fit_incremental(points, disp, tolerance=tol, selection="fps", block=1)
    fewer = fit_incremental(points, disp, tolerance=tol, selection="fps", block=1,
                            max_centers=fit.n_centers - 1)
    assert fit.converged and not fewer.converged
    assert np.abs(disp - evaluate_field(points, fewer)).max() > tol


@pytest.mark.parametrize("selection", ["greedy", "fps"])
def test_smaller_tolerance_never_gives_fewer_centers(selection):
    points, disp, _ = handle_setup(seed=11, per_band=250)
    diag = bbox_diag(points)
    counts = [fit_incremental(points, disp, tolerance=t * diag, selection=selection).n_centers
              for t in (3e-3, 1e-3, 3e-4, 1e-4, 3e-5)]
    assert counts == sorted(counts)


def test_fit_limits_the_blas_pool_inside_the_fit(monkeypatch):
    """Thread control: the BLAS pool is limited to one thread while the fit runs (checked from
    inside the fit, not by timing), and restored afterwards."""
    from threadpoolctl import threadpool_info

    import splatdeform.rbf.fit as fit_mod

    seen = []
    real = fit_mod._geqrf

    def spy(a):
        seen.append([p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"])
        return real(a)

    monkeypatch.setattr(fit_mod, "_geqrf", spy)
    points, disp, _ = handle_setup(seed=2, per_band=100)
    fit_incremental(points, disp, tolerance=1e-3 * bbox_diag(points))
    assert seen and all(n == [1] * len(n) and n for n in seen)
    outside = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    fit_incremental(points, disp, tolerance=1e-3 * bbox_diag(points), threads=None)
    assert seen[-1] == outside  # threads=None leaves the pool alone


def test_exact_method_is_scipys_interpolant():
    """fit_exact (fit.method: exact) agrees with scipy's cubic/degree-1 interpolant to 1e-6 of
    the largest move, at the constraints and away from them; duplicates are merged."""
    points, disp, free = handle_setup(seed=12, per_band=200)
    pts = np.vstack([points, points[:10]])
    rhs = np.vstack([disp, disp[:10]])
    fit = fit_exact(pts, rhs)
    assert fit.method == "exact" and fit.n_centers == len(points)
    oracle = RBFInterpolator(points, disp, kernel="cubic", degree=1)
    largest = np.linalg.norm(disp, axis=1).max()
    assert np.abs(evaluate_field(free, fit) - oracle(free)).max() <= 1e-6 * largest
    assert np.abs(evaluate_field(points, fit) - disp).max() <= 1e-6 * largest
    with pytest.raises(InputError, match="different prescribed values"):
        fit_exact(pts, np.vstack([disp, disp[:10] + 1.0]))


def test_exact_method_refuses_too_many_constraints(monkeypatch):
    import splatdeform.rbf.exact as exact_mod

    monkeypatch.setattr(exact_mod, "EXACT_MAX_CONSTRAINTS", 100)
    points, disp, _ = handle_setup(seed=12, per_band=100)
    with pytest.raises(InputError, match="fit.method"):
        fit_exact(points, disp)


def test_residual_equals_least_squares_residual_of_the_chosen_columns():
    """Independent oracle: numpy lstsq on A = [1, x, phi(x, s_j)] with the fit's centers, with
    and without the 4 weighted side-condition rows [0 | lam (1, s_j)] (right-hand side 0)."""
    points, disp, _ = handle_setup(seed=4, per_band=120)
    for lam in (0.0, 1.0):
        fit = fit_incremental(points, disp, tolerance=1e-3 * bbox_diag(points), side_weight=lam)
        x = fit.normalization.apply(points)
        a = np.column_stack([np.ones(len(x)), x, kernel_matrix(x, fit.centers)])
        rhs = disp
        if lam:
            side = np.zeros((4, a.shape[1]))
            side[:, 4:] = lam * np.vstack([np.ones(fit.n_centers), fit.centers.T])
            a, rhs = np.vstack([a, side]), np.vstack([disp, np.zeros((4, disp.shape[1]))])
        w, *_ = np.linalg.lstsq(a, rhs, rcond=None)
        res = a @ w - rhs
        np.testing.assert_allclose(fit.residuals[-1], np.linalg.norm(res, axis=0), rtol=1e-6,
                                   atol=1e-12)
        assert fit.max_error == pytest.approx(np.abs(res[: len(x)]).max(), rel=1e-6)
        np.testing.assert_allclose(fit.weights, w, rtol=1e-6, atol=1e-8 * np.abs(w).max())


def test_all_centers_with_side_conditions_is_scipys_interpolant():
    """With every constraint a center, the fit is the triharmonic interpolant itself: equal to
    scipy's RBFInterpolator(kernel="cubic", degree=1) everywhere, not just at the constraints."""
    points, disp, free = handle_setup(seed=8, per_band=60)
    fit = fit_incremental(points, disp, tolerance=1e-14, max_centers=len(points))
    assert fit.n_centers == len(points)
    ours = evaluate_field(free, fit)
    oracle = RBFInterpolator(points, disp, kernel="cubic", degree=1)(free)
    assert np.abs(ours - oracle).max() <= 1e-6 * np.abs(oracle).max()


def test_max_centers_respected_and_not_converged():
    points, disp, _ = handle_setup(seed=5, per_band=150)
    fit = fit_incremental(points, disp, tolerance=1e-12, max_centers=10)
    assert fit.n_centers == 10
    assert not fit.converged
    assert fit.residuals.shape == (11, 3)
    fit0 = fit_incremental(points, disp, tolerance=1e-12, max_centers=0)
    assert fit0.n_centers == 0 and not fit0.converged


def test_centers_are_constraint_points_in_farthest_point_order():
    points, disp, _ = handle_setup(seed=6, per_band=100)
    fit = fit_incremental(points, disp, tolerance=1e-3 * bbox_diag(points), selection="fps")
    x = fit.normalization.apply(points)
    order = farthest_point_order(x, fit.n_centers)
    np.testing.assert_array_equal(fit.centers, x[order])


def test_given_normalization_is_used():
    points, disp, free = handle_setup(seed=7, per_band=100)
    norm = Normalization(center=np.array([1.0, 2.0, 3.0]), scale=5.0)
    tol = 1e-6 * bbox_diag(points)
    fit = fit_incremental(points, disp, tolerance=tol, normalization=norm)
    assert fit.normalization is norm
    assert np.abs(evaluate_field(points, fit) - disp).max() <= tol


def test_matches_scipy_cubic_interpolant_on_handle_setup():
    points, disp, free = handle_setup(seed=8)
    fit = fit_incremental(points, disp, tolerance=1e-4 * bbox_diag(points))
    assert fit.converged and fit.n_centers < len(points)
    exact = fit_exact(points, disp)
    assert np.abs(evaluate_field(free, exact) - evaluate_field(free, fit)).max() <= 0.03 * (
        np.linalg.norm(disp, axis=1).max())
    scipy_rbf = RBFInterpolator(points, disp, kernel="cubic", degree=1)
    ours = evaluate_field(free, fit)
    theirs = scipy_rbf(free)
    largest = np.linalg.norm(disp, axis=1).max()
    assert np.linalg.norm(ours - theirs, axis=1).max() <= 0.01 * largest


def test_duplicate_points_stop_center_selection():
    rng = np.random.default_rng(9)
    base = rng.normal(size=(12, 3))
    points = np.vstack([base, base])  # every point twice
    rhs = rng.normal(size=(24, 2))
    rhs[12:] = rhs[:12]  # consistent targets at the duplicates
    fit = fit_incremental(points, rhs, tolerance=1e-12)
    assert fit.n_centers <= 12
    assert np.all(np.isfinite(fit.weights))


def test_fps_order_properties():
    rng = np.random.default_rng(10)
    pts = rng.normal(size=(300, 3))
    order = farthest_point_order(pts, 50)
    assert order.shape == (50,) and len(set(order.tolist())) == 50
    assert order[0] == np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1))
    # every pick is the point farthest from the previous picks (brute force)
    for i in range(1, 50):
        d = np.min(np.linalg.norm(pts[:, None] - pts[order[:i]][None], axis=2), axis=1)
        assert d[order[i]] == pytest.approx(d.max())
    dup = np.vstack([pts[:5], pts[:5]])
    assert len(farthest_point_order(dup)) == 5


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"points": np.full((10, 3), np.nan), "rhs": np.zeros((10, 1))}, "points"),
        ({"points": np.zeros((10, 2)), "rhs": np.zeros((10, 1))}, "points"),
        ({"points": np.eye(3), "rhs": np.zeros((3, 1))}, "points"),
        ({"points": np.random.default_rng(0).normal(size=(10, 3)), "rhs": np.zeros((9, 1))}, "rhs"),
        ({"points": np.random.default_rng(0).normal(size=(10, 3)), "rhs": np.zeros(10)}, "rhs"),
        ({"points": np.random.default_rng(0).normal(size=(10, 3)), "rhs": np.full((10, 1), np.inf)},
         "rhs"),
        ({"points": np.column_stack([np.arange(10.0), np.arange(10.0) ** 2, np.zeros(10)]),
          "rhs": np.zeros((10, 1))}, "points"),
    ],
)
def test_bad_inputs_raise_input_error_naming_the_argument(kwargs, name):
    with pytest.raises(InputError, match=name):
        fit_incremental(**kwargs, tolerance=1e-6)


def test_bad_tolerance_and_max_centers():
    pts = np.random.default_rng(0).normal(size=(10, 3))
    with pytest.raises(InputError, match="tolerance"):
        fit_incremental(pts, np.zeros((10, 1)), tolerance=-1.0)
    with pytest.raises(InputError, match="max_centers"):
        fit_incremental(pts, np.zeros((10, 1)), tolerance=1e-6, max_centers=-3)


@pytest.mark.parametrize("block_bytes", [64, 1 << 19])
def test_blocked_kernel_values_match_cdist(monkeypatch, block_bytes):
    from scipy.spatial.distance import cdist

    monkeypatch.setattr(rbf_kernel, "BLOCK_BYTES", block_bytes)  # many blocks, or one
    rng = np.random.default_rng(5)
    x = rng.normal(size=(70, 3)) * 1e3 + 5e3  # far from the origin: no cancellation
    s = rng.normal(size=(33, 3)) * 1e3 + 5e3
    ref = cdist(x, s) ** 3
    got = rbf_kernel.cubed_distances(x, s)
    assert np.allclose(got, ref, rtol=1e-9, atol=1e-9 * ref.max())
    rows = np.zeros(x.shape[0])
    for a, e, blk in rbf_kernel.cubed_distance_rows(x, s):  # the reused buffer
        rows[a:e] = blk.sum(axis=1)
    assert np.allclose(rows, ref.sum(axis=1), rtol=1e-9)
    sym = np.full((70, 70), np.nan)
    for _ in rbf_kernel.cubed_distance_rows(x, x, sym, upper=True):
        pass
    full = cdist(x, x) ** 3
    upper = np.triu_indices(70)
    assert np.allclose(sym[upper], full[upper], rtol=1e-9, atol=1e-9 * full.max())
    assert np.all(np.diag(sym) == 0.0)
    part = np.full((70, 70), np.nan)  # one thread's share of the rows: those rows only
    for a, e, _ in rbf_kernel.cubed_distance_rows(x, x, part, upper=True, rows=(20, 45)):
        assert 20 <= a < e <= 45
    for i in range(20, 45):
        assert np.allclose(part[i, i:], full[i, i:], rtol=1e-9, atol=1e-9 * full.max())
    assert np.isnan(part[:20]).all() and np.isnan(part[45:]).all()
    assert np.isnan(part[20:45, :20]).all()  # left of its first row: the lower triangle


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_kernel_matrix_and_its_product_on_threads(monkeypatch, threads):
    from scipy.spatial.distance import cdist

    from splatdeform.rbf import cholesky, exact

    monkeypatch.setattr(cholesky, "MIN_THREADED", 16)  # several threads on 90 rows
    rng = np.random.default_rng(8)
    x = rng.normal(size=(90, 3))
    v = rng.normal(size=(90, 4))
    y = np.ones((90, 4))
    phi = exact._kernel_times(x, v, y, threads)
    full = cdist(x, x) ** 3
    low = np.tril_indices(90)
    assert phi.flags.f_contiguous
    np.testing.assert_allclose(phi[low], full[low], rtol=1e-9, atol=1e-9 * full.max())
    np.testing.assert_allclose(y, 1.0 + full @ v, rtol=1e-9, atol=1e-9 * np.abs(full @ v).max())


def test_distinct_rows_and_merged_duplicates():
    rng = np.random.default_rng(6)
    pts = rng.integers(0, 3, size=(40, 3)).astype(float)
    first, inverse = distinct_rows(pts)
    assert np.array_equal(pts[first][inverse], pts)
    _, ref_first = np.unique(pts, axis=0, return_index=True)
    assert np.array_equal(first, np.sort(ref_first))  # first occurrences, in order
    b = pts @ np.array([[1.0], [2.0], [3.0]])  # equal values on copies: merged
    pts_u, b_u = unique_constraints(pts, b)
    assert np.array_equal(pts_u, pts[first]) and np.array_equal(b_u, b[first])
    copies = inverse == np.bincount(inverse).argmax()  # a row with copies (40 rows, 27 kinds)
    assert copies.sum() > 1
    b[copies] += np.arange(copies.sum())[:, None]  # copies with different values: refused
    with pytest.raises(InputError, match="duplicate"):
        unique_constraints(pts, b)
