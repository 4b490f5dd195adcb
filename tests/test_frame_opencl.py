"""The OpenCL per-frame apply (kernels/frame.cl on PoCL) against the float64 definitions
(positions + values @ delta_c; cof(J) n rescaled to |n|) and the numpy per-frame path."""

from __future__ import annotations

import numpy as np
import pytest

from splatdeform.basis.frame_cl import deform_frame_opencl
from splatdeform.deform import arrays as ap
from splatdeform.errors import InputError


def _case(n: int, k: int, seed: int):
    rng = np.random.default_rng(seed)
    pos = (rng.normal(size=(n, 3)) * 10).astype(np.float32)
    nrm = (rng.normal(size=(n, 3)) * rng.uniform(0.5, 7.0, size=(n, 1))).astype(np.float32)
    nrm[: min(n, 3)] = 0.0  # zero normals stay zero
    values = rng.normal(size=(n, k)).astype(np.float32)
    grads = (rng.normal(size=(n, k, 3)) * 0.2).astype(np.float32)
    delta = (rng.normal(size=(k, 3)) * 0.3).astype(np.float32)
    return pos, nrm, values, grads, delta


def _oracle(pos, nrm, values, grads, delta):
    p64 = pos.astype(np.float64) + values.astype(np.float64) @ delta.astype(np.float64)
    jac = ap.jacobians(grads.astype(np.float64), delta.astype(np.float64))
    n64 = ap.transform_normals(jac, nrm.astype(np.float64))
    return p64, n64


@pytest.mark.parametrize("n, k", [(1, 1), (63, 4), (1000, 4), (4097, 8), (777, 13)])
def test_frame_opencl_matches_float64_definition(n, k):
    pos, nrm, values, grads, delta = _case(n, k, seed=n + k)
    p, nn = deform_frame_opencl(pos, nrm, values, grads, delta)
    assert p.dtype == np.float32 and nn.dtype == np.float32
    p64, n64 = _oracle(pos, nrm, values, grads, delta)
    scale = np.abs(p64).max() + 1
    np.testing.assert_allclose(p, p64, atol=1e-5 * scale * k, rtol=0)
    np.testing.assert_allclose(nn, n64, atol=2e-5 * np.abs(n64).max() * k, rtol=0)
    assert (nn[: min(n, 3)] == 0).all()
    # lengths kept: unit in, unit out; 6.28 in, 6.28 out
    keep = np.linalg.norm(nrm, axis=1) > 0
    np.testing.assert_allclose(np.linalg.norm(nn[keep], axis=1),
                               np.linalg.norm(nrm[keep], axis=1), rtol=1e-5)


def test_frame_backends_agree_and_positions_only():
    pos, nrm, values, grads, delta = _case(20_000, 4, seed=3)
    p_np, n_np = ap.deform_frame(pos, nrm, values, grads, delta, backend="numpy")
    p_cl, n_cl = ap.deform_frame(pos, nrm, values, grads, delta, backend="opencl")
    p_auto, _ = ap.deform_frame(pos, nrm, values, grads, delta, backend="auto")
    np.testing.assert_allclose(p_cl, p_np, atol=1e-5 * (np.abs(p_np).max() + 1), rtol=0)
    np.testing.assert_allclose(n_cl, n_np, atol=1e-5 * np.abs(n_np).max(), rtol=0)
    np.testing.assert_array_equal(p_auto, p_cl)  # auto takes the device for float32 input
    p_only, none = ap.deform_frame(pos, None, values, None, delta, backend="opencl")
    assert none is None
    np.testing.assert_array_equal(p_only, p_cl)
    empty, _ = deform_frame_opencl(pos[:0], nrm[:0], values[:0], grads[:0], delta)
    assert empty.shape == (0, 3)


def test_frame_bad_arguments_name_the_argument():
    pos, nrm, values, grads, delta = _case(10, 4, seed=1)
    with pytest.raises(InputError, match="backend"):
        ap.deform_frame(pos, nrm, values, grads, delta, backend="cuda")
    with pytest.raises(InputError, match="delta_c"):
        deform_frame_opencl(pos, nrm, values, grads, delta[:2])
    with pytest.raises(InputError, match="gradients"):
        deform_frame_opencl(pos, nrm, values, None, delta)
    with pytest.raises(InputError, match="positions"):
        deform_frame_opencl(pos[:5], nrm, values, grads, delta)
