"""geometry.bounds: the same minima and maxima as numpy's axis-0 reductions, in one fast pass."""

from __future__ import annotations

import numpy as np
import pytest

from splatdeform.geometry import bounds


@pytest.mark.parametrize("n", [1, 3, 255, 256, 257, 1000, 70_001])
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32])
def test_bounds_equal_numpy(n, dtype):
    rng = np.random.default_rng(n)
    pts = (rng.normal(size=(n, 3)) * 1000).astype(dtype)
    lo, hi = bounds(pts)
    assert lo.dtype == pts.dtype and hi.dtype == pts.dtype
    np.testing.assert_array_equal(lo, pts.min(axis=0))
    np.testing.assert_array_equal(hi, pts.max(axis=0))


def test_bounds_nan_propagates_and_views():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(5000, 3))
    pts[4321, 1] = np.nan  # in the tail beyond the last full block too: 5000 = 19 * 256 + 136
    lo, hi = bounds(pts)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and np.isfinite(lo[[0, 2]]).all()
    wide = rng.normal(size=(3000, 7))
    view = wide[::2, 1:4]  # not contiguous
    np.testing.assert_array_equal(bounds(view)[0], view.min(axis=0))
    np.testing.assert_array_equal(bounds(view)[1], view.max(axis=0))


def test_bounds_empty_raises_like_numpy():
    with pytest.raises(ValueError):
        bounds(np.zeros((0, 3)))
