"""The per-component cofactor product and the round-surfel radius shortcut against the
definitions they replace (np.cross of J's columns; surfel axes through J)."""

from __future__ import annotations

import numpy as np
import pytest

from splatdeform.deform import arrays as ap
from splatdeform.deform.model_apply import _all_within


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_cofactor_apply_same_bits_as_cross(dtype):
    rng = np.random.default_rng(5)
    jac = rng.normal(size=(2000, 3, 3)).astype(dtype)
    n = rng.normal(size=(2000, 3)).astype(dtype)
    c0, c1, c2 = jac[:, :, 0], jac[:, :, 1], jac[:, :, 2]
    want = (n[:, 0:1] * np.cross(c1, c2) + n[:, 1:2] * np.cross(c2, c0)
            + n[:, 2:3] * np.cross(c0, c1))
    got = ap.cofactor_apply(jac, n)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, want)
    # and it is det(J) J^-T n
    j64 = jac.astype(np.float64)
    inv_t = np.linalg.inv(j64).transpose(0, 2, 1)
    ref = np.linalg.det(j64)[:, None] * np.einsum("nab,nb->na", inv_t, n.astype(np.float64))
    np.testing.assert_allclose(got, ref, rtol=1e-3 if dtype == np.float32 else 1e-9,
                               atol=1e-3 if dtype == np.float32 else 1e-9)


def test_round_surfel_radius_matches_axes_path():
    rng = np.random.default_rng(6)
    jac = rng.normal(size=(3000, 3, 3))
    normals = rng.normal(size=(3000, 3)) * rng.uniform(0.1, 7.0, size=(3000, 1))
    normals[:2] = 0.0  # zero normals give radius 0 on both paths
    radius = rng.uniform(0.01, 2.0, 3000)
    axes = ap.transform_axes(jac, ap.radius_to_axes(normals, radius))
    want = ap.axes_to_radius(axes)
    got = ap.round_surfel_radius(radius, normals, ap.cofactor_apply(jac, normals))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-300)
    assert (got[:2] == 0).all()


def test_all_within_flags_nan_inf_and_range():
    ok = np.ones((100, 3))
    assert _all_within(ok, 1.0) and _all_within(np.zeros((0, 3)), 1.0)
    for bad in (np.nan, np.inf, -np.inf, -2.0):
        a = ok.copy()
        a[57, 1] = bad
        assert not _all_within(a, 1.0), bad
    assert not _all_within(np.full((4, 3), np.inf), np.inf)
