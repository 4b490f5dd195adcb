"""The dense solve's threaded Cholesky: against LAPACK's own factor and numpy's solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator
from scipy.linalg import LinAlgError, cholesky

from splatdeform.basis.reference import evaluate_field
from splatdeform.rbf import cholesky as ch
from splatdeform.rbf.exact import fit_exact


def spd(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(n, n))
    return np.asfortranarray(m @ m.T + n * np.eye(n))


@pytest.mark.parametrize("n", [5, ch.PANEL * 2 + 1, ch.PANEL * 3 - 7, 1100])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_factor_is_lapacks_and_solves(monkeypatch, n, threads):
    monkeypatch.setattr(ch, "MIN_THREADED", 0)  # the blocked path from 2 panels on
    a = spd(n, n)
    upper = np.triu(a, 1).copy()
    want = cholesky(a, lower=True)
    low = ch.factor_lower(a.copy(order="F"), threads)
    np.testing.assert_allclose(np.tril(low), want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert np.array_equal(np.triu(low, 1), upper)  # only the lower triangle is touched
    b = np.random.default_rng(1).normal(size=(n, 3))
    x = ch.solve_lower(low, b)
    np.testing.assert_allclose(a @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())


def test_the_blocked_path_runs_on_several_threads_with_the_same_factor(monkeypatch):
    monkeypatch.setattr(ch, "MIN_THREADED", 0)
    calls = []
    real = ch._blocked
    monkeypatch.setattr(ch, "_blocked", lambda *args: calls.append(args[1]) or real(*args))
    a = spd(3 * ch.PANEL + 10, 3)
    two = ch.factor_lower(a.copy(order="F"), 2)
    three = ch.factor_lower(a.copy(order="F"), 3)
    one = ch.factor_lower(a.copy(order="F"), 1)
    assert calls == [2, 3]  # one thread: one dpotrf
    monkeypatch.setattr(ch, "MIN_THREADED", a.shape[0] + 1)
    ch.factor_lower(a.copy(order="F"), 2)
    assert calls == [2, 3]  # a small matrix: one dpotrf too
    np.testing.assert_allclose(np.tril(two), np.tril(one), rtol=0, atol=1e-12 * np.abs(one).max())
    np.testing.assert_allclose(np.tril(three), np.tril(one), rtol=0,
                               atol=1e-12 * np.abs(one).max())


@pytest.mark.parametrize("threads", [1, 2])
def test_not_positive_definite_raises_naming_the_minor(monkeypatch, threads):
    monkeypatch.setattr(ch, "MIN_THREADED", 0)
    a = spd(2 * ch.PANEL + 40, 5)
    bad = 2 * ch.PANEL + 7  # in the last panel of the blocked path
    a[bad, bad] = -1.0
    with pytest.raises(LinAlgError, match=f"leading minor {bad + 1}"):
        ch.factor_lower(a, threads)


def test_refuses_arrays_it_cannot_factor_in_place():
    with pytest.raises(ValueError, match="Fortran-ordered float64"):
        ch.factor_lower(np.ascontiguousarray(spd(20, 1)), 2)
    with pytest.raises(ValueError, match="square"):
        ch.factor_lower(np.zeros((3, 4), order="F"), 2)


def test_exact_fit_on_several_threads_is_scipys_interpolant(monkeypatch):
    monkeypatch.setattr(ch, "MIN_THREADED", 0)
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(3 * ch.PANEL + 50, 3))
    rhs = rng.normal(size=(pts.shape[0], 3))
    q = rng.normal(size=(200, 3))
    oracle = RBFInterpolator(pts, rhs, kernel="cubic", degree=1)(q)
    for threads in (1, 2):
        fit = fit_exact(pts, rhs, threads=threads)
        np.testing.assert_allclose(evaluate_field(q, fit), oracle, rtol=0,
                                   atol=1e-7 * np.abs(oracle).max())
