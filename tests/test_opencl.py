"""OpenCL basis backend against the float64 numpy reference, on a real device (PoCL on CPU).

No mocks: when no OpenCL device exists every test here FAILS with the install instruction.
Measured bound (PoCL, double accumulation, float32 storage): deformed positions p + B dC from
the real fits below differ from the float64 reference by < 1e-7 of the bounding-box diagonal
(bunny, 2000 centers, |W| up to 7e3: 8.4e-8; lidar terrain, 600 centers: 7.2e-8); the tests
assert 1e-5. The compensated-float32 path (no fp64) reaches only 1.9e-4 / 1.0e-4 there: its error
is the float32 rounding of each r^3 w term, which Kahan summation cannot remove.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_file

from splatdeform.basis import compute_basis as dispatch
from splatdeform.basis import opencl
from splatdeform.basis.reference import compute_basis as reference
from splatdeform.errors import DeviceError, InputError
from splatdeform.rbf.fit import fit_incremental
from splatdeform.rbf.result import Normalization, RbfFit

INSTALL = (
    "no OpenCL device found: the OpenCL backend tests need one. Install Debian's PoCL CPU driver "
    "(sudo apt-get install pocl-opencl-icd) and check with `clinfo -l`"
)


@pytest.fixture(autouse=True, scope="module")
def _require_device() -> None:
    if not opencl.opencl_available():
        pytest.fail(INSTALL)


def test_device_present() -> None:
    assert opencl.opencl_available(), INSTALL
    text = opencl.describe_device()
    assert text and "[" in text


# ----------------------------------------------------------------------------- helpers


def synthetic_fit(n: int, k: int, *, seed: int = 0, offset: float = 0.0, scale: float = 1.0):
    """A fit with n centers in the unit-diagonal box and large alternating-sign r^3 weights.

    Returns (fit, points (500, 3) model units inside the box)."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-0.3, 0.3, size=(n, 3))
    weights = rng.normal(size=(4 + n, k))
    weights[4:] *= 1e3 * np.where(np.arange(n) % 2, 1.0, -1.0)[:, None]
    center = np.full(3, offset)
    fit = RbfFit(
        centers=centers,
        weights=weights,
        normalization=Normalization(center=center, scale=scale),
        residuals=np.zeros((1, k)),
        converged=True,
        tolerance=0.0,
    )
    points = center + scale * rng.uniform(-0.3, 0.3, size=(500, 3))
    return fit, points


def assert_close(ocl, ref) -> None:
    """float32 results vs float64: relative to the largest magnitude of each array."""
    assert ocl.values.dtype == np.float32 and ocl.values.shape == ref.values.shape
    v_scale = max(np.abs(ref.values).max(), 1e-30)
    np.testing.assert_allclose(ocl.values, ref.values, rtol=1e-5, atol=1e-6 * v_scale)
    if ref.gradients is None:
        assert ocl.gradients is None
        return
    assert ocl.gradients.dtype == np.float32 and ocl.gradients.shape == ref.gradients.shape
    g_scale = max(np.abs(ref.gradients).max(), 1e-30)
    np.testing.assert_allclose(ocl.gradients, ref.gradients, rtol=1e-5, atol=1e-6 * g_scale)


# ----------------------------------------------------------------------------- synthetic fits


@pytest.mark.parametrize(
    ("n_points", "n_centers", "k"),
    [
        (500, 200, 4),  # the handle case
        (1, 30, 4),  # a single point
        (500, 0, 4),  # polynomial only
        (503, 37, 7),  # k >= 7, N not a multiple of the work-group's points
        (131, 65, 12),  # centers not a multiple of the local-memory tile
        (70, 20, 40),  # large K: rolled k loops (accumulators in private memory)
        (97, 5, 1),
    ],
)
def test_matches_reference(n_points: int, n_centers: int, k: int) -> None:
    fit, pts = synthetic_fit(n_centers, k, seed=n_points + k, offset=3.0, scale=7.0)
    rng = np.random.default_rng(n_centers)
    pts = pts[rng.integers(0, len(pts), n_points)]
    assert_close(opencl.compute_basis(pts, fit), reference(pts, fit))


def test_formula_by_hand() -> None:
    """Independent of the reference: b and grad b of a 2-center fit, written out."""
    s = np.array([[0.1, 0.0, 0.0], [-0.2, 0.1, 0.05]])
    w = np.array([[0.5, 1.0], [1.0, 0.0], [0.0, 2.0], [0.0, 0.0], [3.0, -1.0], [-2.0, 4.0]])
    norm = Normalization(center=np.array([1.0, 2.0, 3.0]), scale=2.0)
    fit = RbfFit(s, w, norm, np.zeros((1, 2)), True, 0.0)
    x = np.array([[1.2, 2.4, 2.9], [0.7, 1.9, 3.3]])
    p = (x - norm.center) / norm.scale
    d = p[:, None, :] - s[None]
    r = np.linalg.norm(d, axis=2)
    values = np.hstack([np.ones((2, 1)), p]) @ w[:4] + r**3 @ w[4:]
    grads = (w[1:4].T[None] + 3 * np.einsum("ij,ija,jk->ika", r, d, w[4:])) / norm.scale
    out = opencl.compute_basis(x, fit)
    np.testing.assert_allclose(out.values, values, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(out.gradients, grads, rtol=1e-6, atol=1e-7)


def test_values_only_and_dtypes() -> None:
    fit, pts = synthetic_fit(50, 4, seed=3)
    full = opencl.compute_basis(pts, fit)
    only = opencl.compute_basis(pts.astype(np.float32), fit, gradients=False)
    assert only.gradients is None
    # float32 input rounds the coordinates first: compare relative to the largest value
    np.testing.assert_allclose(only.values, full.values, atol=1e-6 * np.abs(full.values).max())
    ints = opencl.compute_basis(np.zeros((3, 3), dtype=np.int64), fit)
    assert ints.values.shape == (3, 4)


def test_chunking_is_exact() -> None:
    """Chunks change nothing: every point is evaluated by the same instructions."""
    fit, pts = synthetic_fit(40, 5, seed=4)
    pts = np.tile(pts, (3, 1))  # 1500 points
    whole = opencl.compute_basis(pts, fit)
    pieces = opencl.compute_basis(pts, fit, max_chunk_points=70)
    np.testing.assert_array_equal(pieces.values, whole.values)
    np.testing.assert_array_equal(pieces.gradients, whole.gradients)


def test_empty_points() -> None:
    fit, _ = synthetic_fit(10, 4)
    out = opencl.compute_basis(np.empty((0, 3)), fit)
    assert out.values.shape == (0, 4) and out.gradients.shape == (0, 4, 3)


def test_compensated_float_precision() -> None:
    """The no-fp64 path (Kahan float32), forced on this device: close, but looser than double."""
    fit, pts = synthetic_fit(200, 4, seed=5)
    ref = reference(pts, fit)
    out = opencl.compute_basis(pts, fit, precision="float")
    err = np.abs(out.values - ref.values).max() / np.abs(ref.values).max()
    assert err < 1e-5


@pytest.mark.parametrize(("vw", "wg", "tile", "fp64"), [(1, 64, 16, True), (4, 16, 8, False)])
def test_other_kernel_configurations(vw: int, wg: int, tile: int, fp64: bool) -> None:
    """The scalar GPU-style layout (one point per work-item) and a narrow float layout, on PoCL."""
    fit, pts = synthetic_fit(37, 5, seed=8)
    pts = pts[:203]
    dev = opencl._select_device(None)
    config = opencl._Config(k=5, gradients=True, fp64=fp64, vw=vw, wg=wg, tile=tile)
    centers, weights, center, scale = opencl._check_fit(fit)
    out = opencl._run(opencl._state(dev), config, pts, centers, weights, center, scale, 100)
    ref = reference(pts, fit)
    if fp64:
        assert_close(out, ref)
    else:
        assert np.abs(out.values - ref.values).max() < 1e-5 * np.abs(ref.values).max()


def test_device_selection(monkeypatch: pytest.MonkeyPatch) -> None:
    fit, pts = synthetic_fit(20, 4, seed=6)
    base = opencl.compute_basis(pts, fit)
    for spec in ("0:0", "0", opencl._select_device(None).name.split()[0][:6]):
        np.testing.assert_array_equal(
            opencl.compute_basis(pts, fit, device=spec).values, base.values
        )
    monkeypatch.setenv("PYOPENCL_CTX", "0:0")
    np.testing.assert_array_equal(opencl.compute_basis(pts, fit).values, base.values)
    with pytest.raises(DeviceError, match="no OpenCL device matches 'no-such-device'"):
        opencl.compute_basis(pts, fit, device="no-such-device")
    monkeypatch.setenv("PYOPENCL_CTX", "no-such-device")
    with pytest.raises(DeviceError, match="PYOPENCL_CTX"):
        opencl.compute_basis(pts, fit)


# ----------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.array([[0.0, np.nan, 0.0]]), "points: expected finite"),
        (np.array([[0.0, 0.0, np.inf]]), "points: expected finite"),
        (np.zeros((5, 2)), r"points: expected shape \(N, 3\)"),
        (np.zeros(3), r"points: expected shape \(N, 3\)"),
        (np.zeros((2, 3), dtype=complex), "points: expected a real-valued"),
        (np.array([["a", "b", "c"]]), "points: expected a real-valued"),
    ],
)
def test_bad_points(points: np.ndarray, match: str) -> None:
    fit, _ = synthetic_fit(10, 4)
    # device="no-such-device": InputError rather than DeviceError shows validation runs first
    with pytest.raises(InputError, match=match) as info:
        opencl.compute_basis(points, fit, device="no-such-device")
    assert not isinstance(info.value, DeviceError)


def test_bad_fit_and_options() -> None:
    fit, pts = synthetic_fit(10, 4)
    bad_w = RbfFit(fit.centers, fit.weights[:-1], fit.normalization, fit.residuals, True, 0.0)
    with pytest.raises(InputError, match=r"fit.weights: expected shape \(14, k\)"):
        opencl.compute_basis(pts, bad_w)
    nan_w = fit.weights.copy()
    nan_w[7, 1] = np.nan
    with pytest.raises(InputError, match="fit: expected finite"):
        opencl.compute_basis(pts, RbfFit(fit.centers, nan_w, fit.normalization, None, True, 0))
    zero = Normalization(center=np.zeros(3), scale=0.0)
    with pytest.raises(InputError, match="fit.normalization.scale"):
        opencl.compute_basis(pts, RbfFit(fit.centers, fit.weights, zero, None, True, 0))
    with pytest.raises(InputError, match="fit: expected an RbfFit"):
        opencl.compute_basis(pts, object())
    with pytest.raises(InputError, match="max_chunk_points"):
        opencl.compute_basis(pts, fit, max_chunk_points=0)
    with pytest.raises(InputError, match="precision"):
        opencl.compute_basis(pts, fit, precision="half")


# ----------------------------------------------------------------------------- dispatcher


def test_dispatcher(monkeypatch: pytest.MonkeyPatch) -> None:
    fit, pts = synthetic_fit(30, 4, seed=7)
    ref = dispatch(pts, fit, backend="numpy")
    assert ref.values.dtype == np.float64
    ocl = dispatch(pts, fit, backend="opencl")
    assert ocl.values.dtype == np.float32
    assert_close(ocl, ref)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # auto with a device: OpenCL, no warning
        assert dispatch(pts, fit).values.dtype == np.float32
    with pytest.raises(InputError, match="backend: expected one of auto, numpy, opencl"):
        dispatch(pts, fit, backend="cuda")
    # make the real device unreachable through the documented environment variable
    monkeypatch.setenv("PYOPENCL_CTX", "no-such-device")
    with pytest.warns(RuntimeWarning, match="using the numpy reference") as record:
        fallback = dispatch(pts, fit, backend="auto")
    assert len(record) == 1 and fallback.values.dtype == np.float64
    with pytest.raises(DeviceError):
        dispatch(pts, fit, backend="opencl")


# ----------------------------------------------------------------------------- real scans


def handle_fit(positions: np.ndarray, axis: int, *, m: int, max_centers: int):
    """Fixed band at 15-25 % and handle band at 70-80 % of the extent along ``axis``; rhs = the
    affine coordinates of the handle points w.r.t. a 4-point frame (rows 0 for fixed points).

    Returns (fit, frame C (4, 3), bounding-box diagonal)."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    t = (positions[:, axis] - lo[axis]) / (hi[axis] - lo[axis])
    fixed, handle = (t > 0.15) & (t < 0.25), (t > 0.70) & (t < 0.80)
    rng = np.random.default_rng(11)
    cons = rng.choice(np.flatnonzero(fixed | handle), m, replace=False)
    h = positions[handle]
    frame = np.vstack([h.mean(axis=0), h.mean(axis=0) + np.diag(h.std(axis=0))])
    homog = np.hstack([positions[cons], np.ones((m, 1))])
    rhs = homog @ np.linalg.inv(np.hstack([frame, np.ones((4, 1))]))
    rhs[~handle[cons]] = 0.0
    fit = fit_incremental(positions[cons], rhs, tolerance=1e-9, max_centers=max_centers)
    return fit, frame, float(np.linalg.norm(hi - lo))


def delta_frame(frame: np.ndarray, diag: float) -> np.ndarray:
    """dC for a 30 degree turn about z through the frame's origin plus a 0.1-diagonal lift."""
    a = np.deg2rad(30.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    moved = (frame - frame[0]) @ rot.T + frame[0] + np.array([0.0, 0.0, 0.1 * diag])
    return moved - frame


def load_positions(relative: str) -> np.ndarray:
    from splatdeform.io import load

    return load(shared_file(relative)).positions


@pytest.mark.parametrize(
    ("relative", "axis", "m", "max_centers", "n_eval"),
    [
        ("scans/bunny.ply", 1, 2050, 2000, 8000),
        ("scans/lidar_terrain_522k.ply", 0, 1500, 600, 8000),  # UTM offset: ~5.4e6 m
    ],
)
def test_real_scan_deformation(
    relative: str, axis: int, m: int, max_centers: int, n_eval: int
) -> None:
    positions = load_positions(relative)
    fit, frame, diag = handle_fit(positions, axis, m=m, max_centers=max_centers)
    assert fit.n_centers == max_centers  # tolerance 1e-9 is out of reach: uses every center
    rng = np.random.default_rng(2)
    pts = positions[rng.choice(len(positions), n_eval, replace=False)]
    ref = reference(pts, fit)
    ocl = opencl.compute_basis(pts, fit)
    assert_close(ocl, ref)
    d_c = delta_frame(frame, diag)
    moved_ref = pts + ref.values @ d_c
    moved_ocl = pts + ocl.values.astype(np.float64) @ d_c
    assert np.abs(moved_ocl - moved_ref).max() <= 1e-5 * diag


def test_real_scan_all_points_bounded() -> None:
    """All 522k terrain points in float32 UTM coordinates, in small chunks: finite, shaped."""
    positions = load_positions("scans/lidar_terrain_522k.ply").astype(np.float32)
    fit, _, _ = handle_fit(positions.astype(np.float64), 0, m=400, max_centers=100)
    out = opencl.compute_basis(positions, fit, max_chunk_points=100_000)
    assert out.values.shape == (len(positions), 4)
    assert np.isfinite(out.values).all() and np.isfinite(out.gradients).all()
    sample = np.arange(0, len(positions), 97)
    assert_close(
        type(out)(out.values[sample], out.gradients[sample]), reference(positions[sample], fit)
    )
