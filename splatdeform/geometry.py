"""Geometry helpers shared by deform/, render/ and the editor (numpy only, float64 maths):
quaternions (w, x, y, z, the 3DGS convention), symmetric 3x3 matrices packed as their upper
triangle (xx, xy, xz, yy, yz, zz), and real spherical harmonics of 3D Gaussian splats with their
rotation.

Spherical harmonics: basis, constants and signs are those of the reference 3DGS
``sh_utils.eval_sh``: the colour seen along the unit direction d (from the camera to the splat) is
``0.5 + sum_i c_i Y_i(d)`` with Y_0 = C0, band 1 = (-C1 y, C1 z, -C1 x), bands 2 and 3 as below.
Within a band the functions are orthonormal on the sphere.

``f_rest_*`` is stored channel-major: the first (deg+1)^2 - 1 values are the red channel's
coefficients of bands 1..deg, then green, then blue (3DGS ``save_ply`` flattens
``features_rest.transpose(1, 2)``).

Rotation. For a rotation R every band l has an orthogonal (2l+1)x(2l+1) matrix D_l(R) with
Y_l(R d) = D_l(R) Y_l(d). The coefficients c'_l = D_l(R) c_l then satisfy
colour_out(R d) = colour_in(d) for every d. D_1 is R itself with rows and columns reordered
(band 1 is C1 (-y, z, -x)); D_2 and D_3 are built exactly (to rounding) for a batch of rotations by
evaluating Y_l at a fixed set of well-spread directions P and solving once:
D_l(R) = Y_l(R P) Y_l(P)^+ (the pseudo-inverse of the fixed (2l+1, K) matrix is precomputed).
"""

from __future__ import annotations

import numpy as np

from splatdeform.errors import InputError

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892,
      0.10578554691520431, -0.6690465435572892, 0.47308734787878004, -1.7701307697799304,
      0.6258357354491761)

#: the highest band renders evaluate (3DGS's degree 3)
MAX_DEGREE = 3
#: the highest band a file may hold and a deformation rotates (SPZ v4, 72 f_rest_* values)
MAX_FILE_DEGREE = 4
REST_COUNTS = {3 * ((d + 1) ** 2 - 1): d for d in range(1, MAX_FILE_DEGREE + 1)}  # 9 .. 72
_CHUNK = 32768  # rotations per block (bounds the (M, K, 15) temporary)
TRIU = np.array([0, 1, 2, 4, 5, 8])  # the upper triangle of a flattened 3x3


# -- quaternions ------------------------------------------------------------------------
#: rows per block in :func:`bounds` (a reduction over a (N, 3) array's first axis runs 3 wide,
#: one over (N / B, 3 B) blocks runs 3 B wide: the same exact minima, about 9x faster)
_BOUNDS_BLOCK = 256


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo (D,), hi (D,)) per-column minima and maxima of ``points`` (N, D), exactly as
    ``points.min(axis=0), points.max(axis=0)`` (NaN propagates, the input's dtype), in one fast
    pass over rows grouped in blocks. An empty array raises ValueError like numpy.

    >>> lo, hi = bounds(np.array([[0.0, 5.0, 1.0], [2.0, -1.0, 1.0], [1.0, 0.0, 3.0]]))
    >>> lo.tolist(), hi.tolist()
    ([0.0, -1.0, 1.0], [2.0, 5.0, 3.0])
    """
    pts = np.asarray(points)
    n, d = pts.shape
    m = (n // _BOUNDS_BLOCK) * _BOUNDS_BLOCK
    if m == 0:
        return pts.min(axis=0), pts.max(axis=0)
    blocks = pts[:m].reshape(-1, d * _BOUNDS_BLOCK)
    lo = blocks.min(axis=0).reshape(_BOUNDS_BLOCK, d).min(axis=0)
    hi = blocks.max(axis=0).reshape(_BOUNDS_BLOCK, d).max(axis=0)
    if m < n:
        lo = np.minimum(lo, pts[m:].min(axis=0))
        hi = np.maximum(hi, pts[m:].max(axis=0))
    return lo, hi


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(M, 4) quaternions (w, x, y, z), any length -> (M, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.divide(q, norm, out=np.tile([1.0, 0, 0, 0], (q.shape[0], 1)), where=norm > 0)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(M, 3, 3) proper rotations -> (M, 4) unit quaternions (w, x, y, z), w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    t = np.einsum("mii->m", m)
    cands = np.stack([
        np.stack([1 + t, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                  m[:, 1, 0] - m[:, 0, 1]], -1),
        np.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                  m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
        np.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0],
                  1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
        np.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                  1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
    ], axis=1)  # (M, 4 candidates, 4); pick the numerically largest
    best = np.argmax(np.stack([1 + t, 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                               1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                               1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1), axis=1)
    q = cands[np.arange(m.shape[0]), best]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a b of (M, 4) quaternions (w, x, y, z) -> (M, 4); rotation b, then a."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


# -- symmetric 3x3 packing ----------------------------------------------------------------
def triu6(cov: np.ndarray) -> np.ndarray:
    """(N, 3, 3) symmetric -> (N, 6) float32 upper triangle (xx, xy, xz, yy, yz, zz)."""
    return np.ascontiguousarray(cov.reshape(-1, 9)[:, TRIU], dtype=np.float32)


def full_from_triu6(c6: np.ndarray) -> np.ndarray:
    """(N, 6) upper triangle -> (N, 3, 3) symmetric, same dtype."""
    c6 = np.asarray(c6)
    xx, xy, xz, yy, yz, zz = c6.T
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                     np.stack([xz, yz, zz], -1)], axis=1)


# -- spherical harmonics ------------------------------------------------------------------
def sh_degree(n_rest: int) -> int:
    """SH degree (1 to 4) from the number of ``f_rest_*`` values (9, 24, 45 or 72); 0 for 0."""
    if n_rest == 0:
        return 0
    if n_rest not in REST_COUNTS:
        raise InputError(f"f_rest_*: expected 9, 24, 45 or 72 values per splat (SH degree 1-4, "
                         f"3 colour channels), got {n_rest}; cannot rotate view-dependent colour")
    return REST_COUNTS[n_rest]


def _band_basis(d: np.ndarray, band: int) -> np.ndarray:
    """Real SH of one band (1..4) at directions (..., 3) float64 -> (..., 2 band + 1).
    Band 4 is the reference ``eval_sh``'s, made homogeneous (1 = x^2 + y^2 + z^2 on the unit
    sphere)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    if band == 1:
        out = [-C1 * y, C1 * z, -C1 * x]
    elif band == 2:
        xx, yy, zz = x * x, y * y, z * z
        out = [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
               C2[4] * (xx - yy)]
    elif band == 4:
        xx, yy, zz = x * x, y * y, z * z
        rr = xx + yy + zz
        out = [C4[0] * x * y * (xx - yy), C4[1] * y * z * (3 * xx - yy),
               C4[2] * x * y * (7 * zz - rr), C4[3] * y * z * (7 * zz - 3 * rr),
               C4[4] * (zz * (35 * zz - 30 * rr) + 3 * rr * rr), C4[5] * x * z * (7 * zz - 3 * rr),
               C4[6] * (xx - yy) * (7 * zz - rr), C4[7] * x * z * (xx - 3 * yy),
               C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))]
    else:
        xx, yy, zz = x * x, y * y, z * z
        out = [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
               C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
               C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=-1)


def sh_basis(dirs: np.ndarray, degree: int = MAX_DEGREE) -> np.ndarray:
    """Real SH of bands 1..degree at directions (..., 3) -> (..., (degree+1)^2 - 1) float64.

    Homogeneous polynomials of 3DGS ``eval_sh`` (exact on unit vectors); band 0 is left out.
    """
    d = np.asarray(dirs, dtype=np.float64)
    return np.concatenate([_band_basis(d, b) for b in range(1, degree + 1)], axis=-1)


def _band(band: int) -> slice:
    """Columns of band ``band`` (1..3) in the bands-1..deg coefficient vector."""
    return slice(band * band - 1, (band + 1) * (band + 1) - 1)


def _sample_directions(k: int) -> np.ndarray:
    """(k, 3) unit vectors on a Fibonacci spiral (deterministic, well spread)."""
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# Band 1 is R itself in the (-y, z, -x) order: Y_1(d) = C1 P d, so D_1 = P R P^T.
_P1 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
# Bands 2 to 4 from samples: 6, 8 and 16 spiral directions (Y_l(P) of full row rank; band 4
# least squares over 16 directions, exact to rounding since Y_4(R P) = D_4 Y_4(P) holds exactly).
_DIRS = {2: _sample_directions(6), 3: _sample_directions(8), 4: _sample_directions(16)}
_PINV = {b: np.linalg.pinv(_band_basis(p, b).T) for b, p in _DIRS.items()}  # (K, 2b+1)


def band_rotations(rot: np.ndarray, degree: int = MAX_DEGREE) -> list[np.ndarray]:
    """Per-band SH rotation matrices for rotations (M, 3, 3) float64 (degree up to 4).

    Returns [D_1, ..., D_degree], D_l (M, 2l+1, 2l+1) float64 with Y_l(R d) = D_l(R) Y_l(d).
    """
    r = np.asarray(rot, dtype=np.float64)
    out = [_P1 @ r @ _P1.T]
    for b in range(2, degree + 1):
        rotated = np.matmul(r[:, None], _DIRS[b][None, :, :, None])[..., 0]  # R p_k, (M, K, 3)
        out.append(np.matmul(_band_basis(rotated, b).transpose(0, 2, 1), _PINV[b]))
    return out


def rotate_sh_rest(sh_rest: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """SH bands 1..deg rotated by R: colour_out(R d) = colour_in(d).

    sh_rest: (M, 3 * ((deg+1)^2 - 1)) channel-major ``f_rest_*``; rot: (M, 3, 3) proper
    rotations. Returns (M, same) in sh_rest's dtype (computed in float64).
    """
    rest = np.asarray(sh_rest)
    degree = sh_degree(rest.shape[1])
    out = rest.copy()
    if degree == 0:
        return out
    n = (degree + 1) ** 2 - 1
    for start in range(0, rest.shape[0], _CHUNK):
        block = slice(start, start + _CHUNK)
        coeffs = rest[block].astype(np.float64).reshape(-1, 3, n)  # (M, channel, coefficient)
        new = np.empty_like(coeffs)
        r = rot[block]
        same = bool((r == r[:1]).all())  # one rotation for the whole block (a rigid handle)
        for b, d in enumerate(band_rotations(r[:1] if same else r, degree), start=1):
            new[:, :, _band(b)] = np.matmul(coeffs[:, :, _band(b)], d.transpose(0, 2, 1))
        out[block] = new.reshape(-1, 3 * n).astype(rest.dtype)
    return out
