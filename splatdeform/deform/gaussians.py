"""3D Gaussian splat covariance helpers (3DGS conventions: log scales, quaternion w first).

Deforming a splat by the Jacobian J of the deformation (:func:`deform_gaussians`):
- J exactly I: nothing changes (bit-exact).
- J a similarity s R (rigid parts, a handle beyond the rings; detected per splat to
  :data:`SIMILARITY_TOL`): rotation and scale compose directly, q' = q_R q and
  log-scale' = log-scale + log s, so thin axes and the axis order are kept exactly.
- Elsewhere Sigma' = J Sigma J^T is re-factored from J R S by a one-sided Jacobi SVD
  (:func:`svd3`): the new rotation is U (made proper), the new scales are the singular values.
  This never forms Sigma' (no squared condition number), keeps the singular values to high
  relative accuracy (J R is well conditioned, S only scales its columns) and keeps each axis in
  its column (no sorting). Scales are never clamped in absolute terms.
- SH bands 1..3 are rotated by R of the polar decomposition J = R U (R proper), see
  :mod:`splatdeform.geometry`.

Covariance modes (``gaussians.covariance``; the same three in ``shaders/covariance.glsl``):
- ``jacobian``: Sigma' = J Sigma J^T as above (exact to first order, but where the field
  stretches strongly one axis outgrows the others: a needle);
- ``rotation``: Sigma' = det(J)^(2/3) R Sigma R^T (R the polar rotation of J): the splat turns
  and scales by det(J)^(1/3) per axis, its shape is kept; a splat with det J <= 0 (folded) is
  refused, keeping its covariance, and counted (``DeformedGaussians.refused``);
- ``limited``: J Sigma J^T, but where the ratio of its largest to smallest axis grew by more
  than :data:`ANISOTROPY_GROWTH` the log-scales are pulled towards their mean (volume kept) until
  the growth is exactly that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.errors import InputError
from splatdeform.geometry import (
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_to_matrix,
    rotate_sh_rest,
)
from splatdeform.model import SH_C0, dc_to_colors, dc_to_rgb  # noqa: F401  (defined with the data)

COVARIANCE_MODES = ("jacobian", "rotation", "limited")
DEFAULT_COVARIANCE = "limited"  # no needles under strong edits: benchmarks/bench_needles.py
ANISOTROPY_GROWTH = 2.0  # ``limited``: largest/smallest axis ratio may grow by this factor
SIMILARITY_TOL = 1e-9  # max |J^T J / s^2 - I| for J = s R to count as a similarity
_JACOBI_SWEEPS = 12  # one-sided Jacobi on 3x3 converges quadratically; ~4-6 sweeps in practice


def scale_rotation_to_factor(scale_log: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(M, 3) log scales and (M, 4) quaternions -> (M, 3, 3) factor R S with Sigma = (RS)(RS)^T."""
    return quaternion_to_matrix(rotation) * np.exp(np.asarray(scale_log, np.float64))[:, None, :]


def svd3(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-sided (Hestenes) Jacobi SVD of (M, 3, 3) matrices: m = u diag(s) v^T.

    Returns u (M, 3, 3) with orthonormal columns (where s > 0), s (M, 3) >= 0 and v (M, 3, 3)
    orthogonal, all float64. Singular values are *not* sorted: column i of u is where column i
    of m went. For m = B D with B well conditioned and D diagonal (a splat's J R S), every
    singular value, the smallest included, comes out to high relative accuracy.
    """
    mat = np.asarray(m, dtype=np.float64)
    n = mat.shape[0]
    a = [np.ascontiguousarray(mat[:, :, i].T) for i in range(3)]  # columns, each (3, M)
    v = [np.zeros((3, n)) for _ in range(3)]
    for i in range(3):
        v[i][i] = 1.0
    eps = np.finfo(np.float64).eps
    for _ in range(_JACOBI_SWEEPS):
        rotated = False
        for i, j in ((0, 1), (0, 2), (1, 2)):
            alpha = np.einsum("km,km->m", a[i], a[i])
            beta = np.einsum("km,km->m", a[j], a[j])
            gamma = np.einsum("km,km->m", a[i], a[j])
            todo = np.abs(gamma) > eps * np.sqrt(alpha * beta)
            if not todo.any():
                continue
            rotated = True
            zeta = (beta - alpha) / (2 * np.where(todo, gamma, 1.0))
            t = np.where(zeta >= 0, 1.0, -1.0) / (np.abs(zeta) + np.hypot(1.0, zeta))
            t[~todo] = 0.0
            c = 1 / np.sqrt(1 + t * t)
            s = c * t
            for x in (a, v):
                xi, xj = x[i], x[j]
                x[i], x[j] = c * xi - s * xj, s * xi + c * xj
        if not rotated:
            break
    a_m = np.stack(a, axis=2).transpose(1, 0, 2)  # (M, 3 rows, 3 columns)
    sigma = np.linalg.norm(a_m, axis=1)  # (M, 3) column norms
    u = np.divide(a_m, sigma[:, None, :], out=np.zeros_like(a_m), where=sigma[:, None, :] > 0)
    return u, sigma, np.stack(v, axis=2).transpose(1, 0, 2)


def _make_proper(u: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Columns of u flipped where det(u) < 0 (the one with the smallest sigma) -> det +1."""
    flip = np.linalg.det(u) < 0
    if flip.any():
        rows = np.flatnonzero(flip)
        col = np.argmin(sigma[rows], axis=1)
        u[rows, :, col] *= -1
    return u


def polar_rotation(jac: np.ndarray) -> np.ndarray:
    """R of the polar decomposition J = R U with R proper (det +1): (M, 3, 3) -> (M, 3, 3).

    For det J < 0 this is the closest proper rotation (the smallest singular direction flipped).
    """
    u, sigma, v = svd3(jac)
    flip = np.linalg.det(u) * np.linalg.det(v) < 0
    if flip.any():
        rows = np.flatnonzero(flip)
        col = np.argmin(sigma[rows], axis=1)
        u[rows, :, col] *= -1
    return u @ v.transpose(0, 2, 1)


def similarity_mask(jac: np.ndarray, tol: float = SIMILARITY_TOL) -> np.ndarray:
    """(M,) bool: J = s R with s > 0 and R a proper rotation, to ``tol`` (relative)."""
    gram = jac.transpose(0, 2, 1) @ jac
    s2 = np.einsum("mii->m", gram) / 3
    dev = np.abs(gram - s2[:, None, None] * np.eye(3)).max(axis=(1, 2))
    return (dev <= tol * s2) & (np.linalg.det(jac) > 0)


@dataclass
class DeformedGaussians:
    """New 3DGS fields for M deformed splats: scale_log (M, 3), rotation (M, 4) and sh_rest
    (M, n) or None, in the input dtypes; rotation_matrix: (M, 3, 3) float64 polar R per splat;
    similarity: (M,) bool, splats whose J was a similarity (composed directly);
    refused: number of splats whose covariance was kept (``rotation`` mode, det J <= 0)."""

    scale_log: np.ndarray
    rotation: np.ndarray
    sh_rest: np.ndarray | None
    rotation_matrix: np.ndarray
    similarity: np.ndarray
    refused: int = 0


def limit_anisotropy(scale_in: np.ndarray, scale_out: np.ndarray,
                     growth: float = ANISOTROPY_GROWTH) -> np.ndarray:
    """(M, 3) log-scales ``scale_out`` whose spread (log of largest / smallest axis) exceeds
    that of ``scale_in`` (M, 3) plus log(growth), pulled towards their mean (the volume is kept)
    so that the spread grew by exactly log(growth); the others unchanged."""
    spread_in = np.ptp(scale_in, axis=1)
    spread_out = np.ptp(scale_out, axis=1)
    allowed = spread_in + np.log(growth)
    shrink = np.where(spread_out > allowed, allowed / np.where(spread_out > 0, spread_out, 1.0),
                      1.0)
    mean = scale_out.mean(axis=1, keepdims=True)
    return mean + (scale_out - mean) * shrink[:, None]


def deform_gaussians(scale_log: np.ndarray, rotation: np.ndarray, sh_rest: np.ndarray | None,
                     jac: np.ndarray, covariance: str = DEFAULT_COVARIANCE) -> DeformedGaussians:
    """Deform M splats by their Jacobians J (M, 3, 3): the covariance by ``covariance`` (one of
    :data:`COVARIANCE_MODES`), SH rotated by the polar R of J. Splats with J exactly I come back
    bit-identical. See the module docstring."""
    if covariance not in COVARIANCE_MODES:
        raise InputError(f"covariance: expected one of {', '.join(COVARIANCE_MODES)}, "
                         f"got {covariance!r}")

    jac = np.asarray(jac, dtype=np.float64)
    scale_log = np.asarray(scale_log)
    rotation = np.asarray(rotation)
    new_scale = scale_log.copy()
    new_rot = rotation.copy()
    new_sh = None if sh_rest is None else np.array(sh_rest, copy=True)
    m = jac.shape[0]
    rot_j = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    similar = np.zeros(m, dtype=bool)
    moved = np.flatnonzero(~(jac == np.eye(3)).all(axis=(1, 2)))
    if moved.size == 0:
        return DeformedGaussians(new_scale, new_rot, new_sh, rot_j, similar)
    jm = jac[moved]
    if (jm == jm[:1]).all():  # one J for all (a rigid handle): factor it once
        r = np.broadcast_to(polar_rotation(jm[:1]), jm.shape)
        sim = np.broadcast_to(similarity_mask(jm[:1]), moved.shape)
    else:
        r = polar_rotation(jm)
        sim = similarity_mask(jm)
    rot_j[moved] = r
    similar[moved] = sim
    q_in = rotation[moved].astype(np.float64)
    q_norm = np.linalg.norm(q_in, axis=1)
    q_in[q_norm == 0] = (1.0, 0.0, 0.0, 0.0)  # a zero quaternion reads as the identity
    q_norm = np.where(q_norm > 0, q_norm, 1.0)
    q_out = np.empty_like(q_in)
    s_out = scale_log[moved].astype(np.float64)
    refused = 0
    if covariance == "rotation":  # turn by R, scale by det(J)^(1/3); det <= 0 refused
        det = np.linalg.det(jm)
        ok = det > 0
        refused = int((~ok).sum())
        q_out[~ok] = q_in[~ok]
        q_out[ok] = quaternion_multiply(matrix_to_quaternion(r[ok]), q_in[ok])
        s_out[ok] += np.log(det[ok])[:, None] / 3
        sim = np.ones_like(sim)  # nothing left for the general path
    if sim.any() and covariance != "rotation":  # J = s R: compose directly (keeps |q|, scales)
        log_s = np.log(np.linalg.det(jm[sim])) / 3
        q_out[sim] = quaternion_multiply(matrix_to_quaternion(r[sim]), q_in[sim])
        s_out[sim] += log_s[:, None]
    gen = ~sim
    s_in = s_out.copy()
    if gen.any():  # factor J R S by a relatively accurate SVD: no Sigma', no clamping
        factor = jm[gen] @ scale_rotation_to_factor(s_out[gen], q_in[gen])
        u, sigma, _ = svd3(factor)
        u = _make_proper(u, sigma)
        # a singular J can zero an axis; keep it finite relative to the splat's largest axis
        sigma = np.maximum(sigma, sigma.max(axis=1, keepdims=True) * 1e-30)
        s_out[gen] = np.log(sigma)
        if covariance == "limited":
            s_out[gen] = limit_anisotropy(s_in[gen], s_out[gen])
        q_out[gen] = matrix_to_quaternion(u) * q_norm[gen][:, None]
    new_scale[moved] = s_out.astype(scale_log.dtype)
    new_rot[moved] = q_out.astype(rotation.dtype)
    if new_sh is not None and new_sh.shape[1]:
        turned = moved[~(r == np.eye(3)).all(axis=(1, 2))]
        if turned.size:
            new_sh[turned] = rotate_sh_rest(new_sh[turned], rot_j[turned])
    return DeformedGaussians(new_scale, new_rot, new_sh, rot_j, similar, refused)
