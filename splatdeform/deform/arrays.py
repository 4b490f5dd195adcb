"""The per-frame path: apply control displacements delta_c to a precomputed basis.

Pure array math, no bookkeeping of regions (that is :mod:`splatdeform.deform`):

    p' = p + B delta_c                          (N, 3)
    J  = I + sum_k outer(delta_c[k], grad b_k)  (N, 3, 3)
    n' = |n| normalize(cof(J) n)                cof(J) = det(J) J^-T, no inverse needed
    u' = J u,  v' = J v                         tangent axes
    Sigma' = J Sigma J^T                        Gaussian covariances (6 upper-triangle entries)
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from splatdeform.blas import blas_threads
from splatdeform.errors import InputError


def _check_delta(delta_c: np.ndarray, k: int) -> np.ndarray:
    d = np.asarray(delta_c)
    if d.shape != (k, 3):
        raise InputError(f"delta_c: expected shape ({k}, 3) for a {k}-column basis, got {d.shape}")
    return d


def displace(positions: np.ndarray, values: np.ndarray, delta_c: np.ndarray) -> np.ndarray:
    """Deformed positions ``positions + values @ delta_c``.

    positions: (N, 3); values: (N, k); delta_c: (k, 3). Returns (N, 3) in the positions' dtype
    (float32 stays float32: the fast per-frame path).
    """
    d = _check_delta(delta_c, values.shape[1]).astype(values.dtype, copy=False)
    out = values @ d
    out += positions
    return out.astype(positions.dtype, copy=False)


def jacobians(gradients: np.ndarray, delta_c: np.ndarray) -> np.ndarray:
    """J = I + sum_k outer(delta_c[k], gradients[:, k]).

    gradients: (N, k, 3); delta_c: (k, 3). Returns (N, 3, 3), J[n, a, b] = d x'_a / d x_b.
    Computed as one (N, 3k) @ (3k, 9) product.
    """
    n, k, _ = gradients.shape
    d = _check_delta(delta_c, k).astype(gradients.dtype, copy=False)
    # J[n, a, b] = delta_ab + sum_k d[k, a] * g[n, k, b]  ->  mixing matrix over (k, b) x (a, b').
    mix = np.einsum("ka,bc->kbac", d, np.eye(3, dtype=gradients.dtype)).reshape(3 * k, 9)
    jac = (gradients.reshape(n, 3 * k) @ mix).reshape(n, 3, 3)
    jac[:, 0, 0] += 1
    jac[:, 1, 1] += 1
    jac[:, 2, 2] += 1
    return jac


def cofactor_apply(jac: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """cof(J) n = det(J) J^-T n for each point, without an inverse.

    With the columns c0, c1, c2 of J: cof(J) n = n0 (c1 x c2) + n1 (c2 x c0) + n2 (c0 x c1),
    written out per component on contiguous rows of J's nine entries (the same products and
    sums as three ``np.cross`` calls, so the same bits, in half the time).
    jac: (N, 3, 3); vectors: (N, 3). Returns (N, 3), not normalised.
    """
    a, b, c, d, e, f, g, h, i = np.ascontiguousarray(np.reshape(jac, (-1, 9)).T)
    x, y, z = np.ascontiguousarray(np.asarray(vectors).T)
    out = np.empty((3, x.shape[0]), dtype=np.result_type(jac, vectors))
    out[0] = x * (e * i - h * f) + y * (f * g - i * d) + z * (d * h - g * e)
    out[1] = x * (h * c - b * i) + y * (i * a - c * g) + z * (g * b - a * h)
    out[2] = x * (b * f - e * c) + y * (c * d - f * a) + z * (a * e - d * b)
    return out.T


def cofactor_apply_one(jac: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """:func:`cofactor_apply` for one J (3, 3) shared by every vector (a rigid handle's
    points): the same products and sums, the J terms computed once, so the same bits.
    jac: (3, 3); vectors: (N, 3). Returns (N, 3), not normalised."""
    a, b, c, d, e, f, g, h, i = np.asarray(jac).reshape(9)
    x, y, z = np.ascontiguousarray(np.asarray(vectors).T)
    out = np.empty((3, x.shape[0]), dtype=np.result_type(jac, vectors))
    for row, (p, q, r) in zip(out, ((e * i - h * f, f * g - i * d, d * h - g * e),
                                    (h * c - b * i, i * a - c * g, g * b - a * h),
                                    (b * f - e * c, c * d - f * a, a * e - d * b)), strict=True):
        np.multiply(x, p, out=row)
        row += y * q
        row += z * r
    return out.T


def normalize_rows(v: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero. (N, 3) -> (N, 3)."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v), where=length > 0)


def transform_normals(jac: np.ndarray, normals: np.ndarray,
                      cofactor: np.ndarray | None = None) -> np.ndarray:
    """Deformed normals: cof(J) n rescaled to each input normal's length (unit in, unit out; a
    scan's 6.28-long normals stay 6.28 long). jac (N, 3, 3), normals (N, 3) -> (N, 3);
    ``cofactor``: cof(J) n (N, 3) when already at hand."""
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    cof = cofactor_apply(jac, normals) if cofactor is None else cofactor
    return normalize_rows(cof) * length


def round_surfel_radius(radius: np.ndarray, normals: np.ndarray,
                        cofactor: np.ndarray) -> np.ndarray:
    """Area-preserving radius of round surfels after J: (N,) radii, (N, 3) normals and their
    cof(J) n (N, 3) -> (N,). A disc of radius r spanned by u, v (u x v = r^2 n/|n|) maps to
    J u, J v with J u x J v = cof(J)(u x v), so r' = |r| sqrt(|cof(J) n| / |n|) (0 for a zero
    normal), the value :func:`axes_to_radius` gives for :func:`radius_to_axes`' axes."""
    length = np.linalg.norm(normals, axis=1)
    area = np.divide(np.linalg.norm(cofactor, axis=1), length, out=np.zeros_like(length),
                     where=length > 0)
    return np.abs(np.asarray(radius, dtype=np.float64)) * np.sqrt(area)


def transform_axes(jac: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Tangent axes mapped by J. jac (N, 3, 3), axes (N, 2, 3) -> (N, 2, 3)."""
    return np.einsum("nab,nkb->nka", jac, axes)


def radius_to_axes(normals: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Tangent axes of round surfels: u perpendicular to n, v = n x u, |u| = |v| = r.

    normals: (N, 3) unit; radius: (N,). Returns (N, 2, 3) float64. Deterministic choice of u:
    the cross product of n with the coordinate axis least aligned with it.
    """
    n = normalize_rows(np.asarray(normals, dtype=np.float64))
    helper = np.zeros_like(n)
    helper[np.arange(n.shape[0]), np.argmin(np.abs(n), axis=1)] = 1.0
    u = normalize_rows(np.cross(n, helper))
    v = np.cross(n, u)
    r = np.asarray(radius, dtype=np.float64)[:, None]
    return np.stack([u * r, v * r], axis=1)


def axes_to_radius(axes: np.ndarray) -> np.ndarray:
    """Area-preserving radius sqrt(|u x v|) of (N, 2, 3) axes -> (N,)."""
    return np.sqrt(np.linalg.norm(np.cross(axes[:, 0], axes[:, 1]), axis=1))


#: points per block of the per-frame path (its scratch, ~20 rows of this, stays in L2)
FRAME_CHUNK = 16384
_FRAME_POOL: ThreadPoolExecutor | None = None
_FRAME_POOL_LOCK = threading.Lock()


def _frame_pool(workers: int) -> ThreadPoolExecutor:
    """One persistent pool for the per-frame row blocks (starting threads every frame costs)."""
    global _FRAME_POOL
    with _FRAME_POOL_LOCK:
        if _FRAME_POOL is None or _FRAME_POOL._max_workers < workers:
            _FRAME_POOL = ThreadPoolExecutor(workers, thread_name_prefix="deform-frame")
        return _FRAME_POOL


def _frame_threads() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _frame_rows(lo: int, hi: int, chunk: int, positions: np.ndarray,
                normals: np.ndarray | None, values: np.ndarray, gradients: np.ndarray | None,
                d: np.ndarray, mix_t: np.ndarray | None, out_p: np.ndarray,
                out_n: np.ndarray | None) -> None:
    """Rows lo:hi of :func:`deform_frame`, block by block, into preallocated scratch (no
    temporaries): J - I from one (9, 3k) @ (3k, n) product as component rows, then
    cof(J) n = c0 x v + nx (c1 x c2), v = nz c1 - ny c2 (columns c_b of J; from
    n = e0 x (nz e1 - ny e2) + e1 x (nx e2) and cof(J) (x x y) = Jx x Jy): 33 products and
    sums instead of 42. (Whole (3, n) calls on strided row views measured slower.)"""
    dt = out_p.dtype
    k = values.shape[1]
    m = max(0, min(chunk, hi - lo))
    if out_n is not None:
        jb = np.empty((9, m), dt)     # J, rows (a, b) row-major
        nb = np.empty((3, m), dt)     # normals as components
        vb = np.empty((3, m), dt)
        ob = np.empty((3, m), dt)
        t0 = np.empty(m, dt)
        t1 = np.empty(m, dt)
        sub = np.finfo(dt).smallest_subnormal
    for s in range(lo, hi, chunk):
        e = min(s + chunk, hi)
        c = e - s
        p = out_p[s:e]
        np.matmul(values[s:e], d, out=p)  # the same product and sum as before: bit-identical
        p += positions[s:e]
        if out_n is None:
            continue
        if c != m:
            jb, nb, vb, ob, t0, t1 = (x[..., :c] for x in (jb, nb, vb, ob, t0, t1))
            m = c
        np.matmul(mix_t, gradients[s:e].reshape(c, 3 * k).T, out=jb)  # J - I
        jb[0::4] += 1
        j00, j01, j02, j10, j11, j12, j20, j21, j22 = jb
        np.copyto(nb, normals[s:e].T)
        nx, ny, nz = nb
        vx, vy, vz = vb
        ox, oy, oz = ob
        # v = nz c1 - ny c2
        np.multiply(nz, j01, out=vx)
        vx -= np.multiply(ny, j02, out=t0)
        np.multiply(nz, j11, out=vy)
        vy -= np.multiply(ny, j12, out=t0)
        np.multiply(nz, j21, out=vz)
        vz -= np.multiply(ny, j22, out=t0)
        # o = c0 x v
        np.multiply(j10, vz, out=ox)
        ox -= np.multiply(j20, vy, out=t0)
        np.multiply(j20, vx, out=oy)
        oy -= np.multiply(j00, vz, out=t0)
        np.multiply(j00, vy, out=oz)
        oz -= np.multiply(j10, vx, out=t0)
        # o += nx (c1 x c2)
        for o, (a0, b0, a1, b1) in zip(ob, ((j11, j22, j21, j12), (j21, j02, j01, j22),
                                            (j01, j12, j11, j02)), strict=True):
            np.multiply(a0, b0, out=t0)
            t0 -= np.multiply(a1, b1, out=t1)
            t0 *= nx
            o += t0
        # rescaled to the input normal's length: sqrt(n.n) / sqrt(o.o); o = 0 stays 0
        np.multiply(nx, nx, out=t0)
        t0 += np.multiply(ny, ny, out=t1)
        t0 += np.multiply(nz, nz, out=t1)
        np.sqrt(t0, out=t0)
        np.multiply(ox, ox, out=t1)
        t1 += np.multiply(oy, oy, out=vx)
        t1 += np.multiply(oz, oz, out=vx)
        np.maximum(t1, sub, out=t1)
        np.sqrt(t1, out=t1)
        t0 /= t1
        np.multiply(ob, t0, out=out_n[s:e].T)


#: ``deform_frame`` backends: numpy (below), opencl (``kernels/frame.cl``, float32), auto
#: (opencl for float32 input where a device exists, else numpy)
FRAME_BACKENDS = ("numpy", "opencl", "auto")


def deform_frame(positions: np.ndarray, normals: np.ndarray | None, values: np.ndarray,
                 gradients: np.ndarray | None, delta_c: np.ndarray, *,
                 chunk: int = FRAME_CHUNK, threads: int | None = None,
                 backend: str = "numpy", device: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """The fast per-frame path: deformed positions and normals (input length kept) in one
    cache-blocked pass over row blocks, on ``threads`` Python threads (default: the usable
    cores; BLAS limited to one thread inside). ``backend``: one of :data:`FRAME_BACKENDS`;
    ``opencl`` runs :func:`splatdeform.basis.frame_cl.deform_frame_opencl` on ``device`` (1M
    points with normals: 4.8 ms against 19 ms here on 2 cores, ``benchmarks/bench_frame.py``).

    positions (N, 3), normals (N, 3) or None, values (N, k), gradients (N, k, 3) (needed with
    normals), delta_c (k, 3). Works in the dtype of ``values`` (float32 for the real-time path).
    Per block of points: one (n, k) @ (k, 3) product for the displacements (the same product
    and sum as :func:`displace`), one (9, 3k) @ (3k, n) product for J - I as component rows,
    then the cofactor-times-normal formula on those rows into per-thread scratch; blocks stay
    in cache and nothing of size N is allocated besides the two outputs.
    """
    if backend not in FRAME_BACKENDS:
        raise InputError(f"backend: expected one of {', '.join(FRAME_BACKENDS)}, "
                         f"got {backend!r}")
    if backend == "opencl" or (backend == "auto" and values.dtype == np.float32):
        from splatdeform.basis.frame_cl import deform_frame_opencl
        from splatdeform.errors import DeviceError

        try:
            return deform_frame_opencl(positions, normals, values, gradients, delta_c,
                                       device=device)
        except DeviceError:
            if backend == "opencl":
                raise
    n, k = values.shape
    dt = values.dtype
    d = _check_delta(delta_c, k).astype(dt)
    out_p = np.empty((n, 3), dtype=dt)
    out_n = None if normals is None else np.empty((n, 3), dtype=dt)
    mix_t = None
    if normals is not None:
        if gradients is None:
            raise InputError("gradients: required to transform normals")
        # (J - I)[a, b] = sum_k d[k, a] g[k, b]: rows (a, b), columns (k, b')
        mix_t = np.ascontiguousarray(
            np.einsum("ka,bc->kbac", d, np.eye(3, dtype=dt)).reshape(3 * k, 9).T)
    chunk = max(1, int(chunk))
    workers = _frame_threads() if threads is None else int(threads)
    workers = max(1, min(workers, n // chunk))
    args = (chunk, positions, normals, values, gradients, d, mix_t, out_p, out_n)
    if workers == 1:
        _frame_rows(0, n, *args)
        return out_p, out_n
    bounds = [n * i // workers for i in range(workers + 1)]
    with blas_threads(1):  # one BLAS thread per row block: no oversubscription
        futures = [_frame_pool(workers - 1).submit(_frame_rows, bounds[i], bounds[i + 1], *args)
                   for i in range(1, workers)]
        try:
            _frame_rows(bounds[0], bounds[1], *args)
        finally:
            for f in futures:
                f.result()
    return out_p, out_n


_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))   # upper triangle, row-major


def covariance_frame(gradients: np.ndarray, delta_c: np.ndarray, cov6: np.ndarray, *,
                     chunk: int = 4096) -> np.ndarray:
    """Deformed covariances J Sigma J^T, J = I + sum_k outer(delta_c[k], gradients[:, k]), the
    editor's per-frame path: cache-blocked like :func:`deform_frame`, on the 6 upper-triangle
    entries (xx, xy, xz, yy, yz, zz), never a (M, 3, 3) temporary.

    gradients: (M, k, 3) float32; delta_c: (k, 3); cov6: (M, 6) upper triangles.
    Returns (M, 6) float32.
    """
    m, k, _ = gradients.shape
    dt = np.float32
    d = np.asarray(delta_c, dtype=dt)
    mix = np.einsum("ka,bc->kbac", d, np.eye(3, dtype=dt)).reshape(3 * k, 9)
    out = np.empty((m, 6), dtype=dt)
    flat = gradients.reshape(m, 3 * k)
    for s in range(0, m, chunk):
        e = min(s + chunk, m)
        j = np.ascontiguousarray((flat[s:e] @ mix).T)  # (9, n): J - I, row-major (a, b)
        j[0] += 1
        j[4] += 1
        j[8] += 1
        c = np.ascontiguousarray(cov6[s:e].T)
        sig = ((c[0], c[1], c[2]), (c[1], c[3], c[4]), (c[2], c[4], c[5]))
        # A = J Sigma, then Sigma'_ab = sum_c A_ac J_bc
        a = [[j[3 * r] * sig[0][col] + j[3 * r + 1] * sig[1][col] + j[3 * r + 2] * sig[2][col]
              for col in range(3)] for r in range(3)]
        block = np.empty((6, e - s), dtype=dt)
        for i, (r, q) in enumerate(_PAIRS):
            block[i] = a[r][0] * j[3 * q] + a[r][1] * j[3 * q + 1] + a[r][2] * j[3 * q + 2]
        out[s:e] = block.T
    return out
