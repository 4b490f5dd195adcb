"""Numpy reference basis: values and model-unit gradients against independent oracles."""

from __future__ import annotations

import numpy as np
import pytest

from splatdeform.basis.reference import compute_basis, evaluate_field
from splatdeform.errors import InputError
from splatdeform.rbf import Normalization, RbfFit, fit_incremental


def random_fit(seed: int = 0, n: int = 30, k: int = 4) -> RbfFit:
    """A fit with arbitrary weights: the basis must evaluate any W, not only fitted ones."""
    rng = np.random.default_rng(seed)
    return RbfFit(
        centers=rng.uniform(-0.5, 0.5, (n, 3)),
        weights=rng.normal(size=(4 + n, k)),
        normalization=Normalization(center=np.array([2.0, -1.0, 0.5]), scale=3.0),
        residuals=np.zeros((1, k)),
        converged=True,
        tolerance=0.0,
    )


def direct_field(points: np.ndarray, fit: RbfFit) -> np.ndarray:
    """Oracle: a plain per-point loop over centers, b(p) = [1, p, |p - s|^3] . W."""
    p = fit.normalization.apply(points)
    out = np.empty((len(p), fit.k))
    for i, q in enumerate(p):
        r = np.sqrt(((q - fit.centers) ** 2).sum(axis=1))
        out[i] = fit.weights[0] + q @ fit.weights[1:4] + (r**3) @ fit.weights[4:]
    return out


def test_values_match_direct_loop():
    fit = random_fit(1)
    pts = np.random.default_rng(2).uniform(0.0, 4.0, (50, 3))
    np.testing.assert_allclose(compute_basis(pts, fit).values, direct_field(pts, fit), rtol=1e-12,
                               atol=1e-12)


def test_affine_fit_reproduces_values_and_gradients():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(150, 3)) * [0.3, 1.0, 2.0] + [5.0, 5.0, -5.0]
    lin = np.array([[0.5, -1.0, 2.0], [1.5, 0.25, 0.0], [-0.75, 0.0, 1.0], [0.1, 0.2, 0.3]])
    rhs = np.column_stack([np.ones(len(pts)), pts]) @ lin  # (m, 3) affine map of [1, x]
    fit = fit_incremental(pts, rhs, tolerance=1e-10)
    other = rng.normal(size=(400, 3)) * 4.0
    basis = compute_basis(other, fit)
    expected = np.column_stack([np.ones(len(other)), other]) @ lin
    assert np.abs(basis.values - expected).max() <= 1e-9 * np.abs(expected).max()
    # grad of column c is lin[1:4, c]; gradients is (N, k, 3)
    np.testing.assert_allclose(basis.gradients, np.broadcast_to(lin[1:].T, basis.gradients.shape),
                               rtol=1e-9, atol=1e-9)


def test_gradients_match_central_differences():
    fit = random_fit(4, n=40, k=3)
    pts = np.random.default_rng(5).uniform(0.5, 3.5, (60, 3))
    grads = compute_basis(pts, fit).gradients
    h = 1e-5
    fd = np.empty_like(grads)
    for d in range(3):
        step = np.zeros(3)
        step[d] = h
        fd[:, :, d] = (evaluate_field(pts + step, fit) - evaluate_field(pts - step, fit)) / (2 * h)
    scale = np.abs(fd).max()
    assert np.abs(grads - fd).max() <= 1e-6 * scale


def test_chunking_gives_the_same_result():
    fit = random_fit(6, n=25)
    pts = np.random.default_rng(7).uniform(0.0, 4.0, (333, 3))
    one = compute_basis(pts, fit)
    tiny = compute_basis(pts, fit, max_chunk_bytes=1)  # one row per chunk
    small = compute_basis(pts, fit, max_chunk_bytes=20_000)
    for other in (tiny, small):
        np.testing.assert_allclose(other.values, one.values, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(other.gradients, one.gradients, rtol=1e-13, atol=1e-13)


def test_empty_and_single_point():
    fit = random_fit(8, k=5)
    empty = compute_basis(np.zeros((0, 3)), fit)
    assert empty.values.shape == (0, 5) and empty.gradients.shape == (0, 5, 3)
    assert compute_basis(np.zeros((0, 3)), fit, gradients=False).gradients is None
    one = compute_basis(np.array([[1.0, 2.0, 3.0]]), fit)
    assert one.values.shape == (1, 5) and one.gradients.shape == (1, 5, 3)
    np.testing.assert_allclose(one.values, direct_field(np.array([[1.0, 2.0, 3.0]]), fit),
                               rtol=1e-12, atol=1e-12)


def test_zero_centers_fit():
    fit = random_fit(9, n=0, k=2)
    pts = np.random.default_rng(10).normal(size=(7, 3))
    basis = compute_basis(pts, fit)
    np.testing.assert_allclose(basis.values, direct_field(pts, fit), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(basis.gradients[0], fit.weights[1:4].T / fit.normalization.scale)


def test_float32_points_accepted_and_output_float64():
    fit = random_fit(11)
    pts = np.random.default_rng(12).uniform(0.0, 4.0, (20, 3)).astype(np.float32)
    basis = compute_basis(pts, fit)
    assert basis.values.dtype == np.float64 and basis.gradients.dtype == np.float64
    np.testing.assert_allclose(basis.values, direct_field(pts.astype(np.float64), fit), rtol=1e-12,
                               atol=1e-12)


@pytest.mark.parametrize("bad", [np.zeros((4, 2)), np.zeros(3), np.array([["a", "b", "c"]])])
def test_bad_points_raise_input_error(bad):
    with pytest.raises(InputError, match="points"):
        compute_basis(bad, random_fit())
