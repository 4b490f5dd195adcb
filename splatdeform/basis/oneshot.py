"""One-shot evaluation: the displacement d(x) and its gradient straight from the centers and the
combined weights W delta_c, chunk by chunk, for an edit whose basis is used once.

The stored basis B (N, k) with gradients (N, k, 3) is what the interactive loop needs (a new
pose = one product). A one-shot edit needs only, per point,

    d(x)     = [1, p, |p - s_j|^3] . (W delta_c)                          (3,) model units
    grad d   = [0, I3, 3 |p - s_j| (p - s_j)] . (W delta_c) / scale        (3, 3), J = I + grad d

which is the basis of a fit with the k = 3 columns W delta_c ((4 + n, 3)): the same kernel
(``kernels/basis.cl`` built for K = 3, accumulated in double or compensated float32) or the
same float64 numpy reference, evaluated a chunk at a time so that nothing of size N x k is ever
stored. ``grad[:, a, b]`` = d d_a / d x_b, i.e. J - I in the layout of
:func:`splatdeform.deform.arrays.jacobians`.

:class:`DeferredBasis` is what ``basis_settings(..., stored=False)`` makes: the free points and
the fit, with the stored basis computed only if something asks for ``values`` / ``gradients``
(the editor, ``--reuse``, rendering, ``deform_frame``); :func:`splatdeform.deform.apply`
evaluates one-shot instead while it has not been.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..rbf.result import RbfFit
from .checks import check_fit, check_points
from .result import Basis

#: points per one-shot chunk of the numpy path: bounds the float64 Jacobians and the apply's
#: temporaries (262,144 points: 19 MB of J)
ONESHOT_CHUNK = 1 << 18
#: the same for OpenCL: 65,536 points (its two host slots and device buffers ~11 MB) keep
#: kernel launches few; 262,144 cost the 5M-point bend 40-60 MB more peak for no less time
OPENCL_ONESHOT_CHUNK = 1 << 16
#: the numpy path's (rows, centers) float64 temporaries per block, on one BLAS thread (the
#: reference's own default is 256 MB; 16 MB measured 30 % less CPU and a lower peak; with the
#: default thread pool the many small products ran 2x slower than the stored basis, busy box)
NUMPY_TEMP_BYTES = 16 << 20
#: OpenCL chunks per block of points gathered by index (``rows``): 4 x 65,536 points (6 MB of
#: float64), pipelined by the kernel's two host slots within the block
GATHER_CHUNKS = 4


def combined_fit(fit: RbfFit, delta_c: np.ndarray) -> RbfFit:
    """``fit`` with its weights (4 + n, k) replaced by W delta_c (4 + n, 3): the field whose
    three basis columns are the displacement's x, y, z. delta_c: (k, 3)."""
    _, weights, _, _ = check_fit(fit)
    delta = np.asarray(delta_c, dtype=np.float64)
    if delta.shape != (weights.shape[1], 3):
        raise InputError(f"delta_c: expected shape ({weights.shape[1]}, 3) for a "
                         f"{weights.shape[1]}-column basis, got {delta.shape}")
    return replace(fit, weights=weights @ delta)


def oneshot_chunks(points: np.ndarray, fit: RbfFit, delta_c: np.ndarray, *,
                   gradients: bool = True, backend: str = "auto", device: str | None = None,
                   chunk: int | None = None, rows: np.ndarray | None = None
                   ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray | None]]:
    """d(x) and grad d(x) at ``points`` (N, 3) model units for control displacements
    ``delta_c`` (k, 3), ``chunk`` points at a time (default :data:`ONESHOT_CHUNK`,
    :data:`OPENCL_ONESHOT_CHUNK` on OpenCL, where a point's values do not depend on it).
    ``rows`` (M,) int: evaluate at ``points[rows]`` instead (yielded rows index ``rows``),
    gathered a block at a time (:data:`GATHER_CHUNKS` chunks) rather than copied whole.

    Yields (start, stop, displacement (m, 3), grad (m, 3, 3) or None) for rows start:stop:
    float64 from the numpy backend, float32 from OpenCL (accumulated in double or compensated
    float32), possibly views of a buffer the next step reuses. ``grad[:, a, b]`` =
    d d_a / d x_b in model units (J - I). ``backend``: numpy | opencl | auto.

    Examples
    --------
    >>> import numpy as np
    >>> from splatdeform.basis.reference import compute_basis
    >>> from splatdeform.rbf import fit_incremental
    >>> rng = np.random.default_rng(0)
    >>> pts = rng.uniform(size=(200, 3))
    >>> fit = fit_incremental(pts, rng.uniform(size=(200, 4)), tolerance=0.0, max_centers=20)
    >>> delta = rng.uniform(size=(4, 3))
    >>> (lo, hi, d, g), = oneshot_chunks(pts, fit, delta, backend="numpy")
    >>> b = compute_basis(pts, fit)
    >>> bool(np.allclose(d, b.values @ delta)), g.shape
    (True, (200, 3, 3))
    """
    from . import resolve_backend

    arr = check_points(points) if rows is None else check_rows(points, rows)
    both = combined_fit(fit, delta_c)
    n = arr.shape[0] if rows is None else rows.shape[0]
    if resolve_backend(backend, device) == "opencl":
        from . import opencl

        chunk = max(1, int(OPENCL_ONESHOT_CHUNK if chunk is None else chunk))
        if rows is None:
            yield from opencl.chunks(arr, both, gradients=gradients, device=device,
                                     max_chunk_points=chunk)
            return
        step = chunk * GATHER_CHUNKS   # the kernel pipelines the chunks of one gathered block
        for lo in range(0, n, step):
            block = arr[rows[lo:lo + step]]
            for s, e, d, g in opencl.chunks(block, both, gradients=gradients, device=device,
                                            max_chunk_points=chunk):
                yield lo + s, lo + e, d, g
        return
    from ..blas import blas_threads
    from .reference import compute_basis

    chunk = max(1, int(ONESHOT_CHUNK if chunk is None else chunk))
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        part = arr[lo:hi] if rows is None else arr[rows[lo:hi]]
        with blas_threads(1):  # many small products: an unlimited pool spins on a busy machine
            b = compute_basis(part, both, gradients=gradients,
                              max_chunk_bytes=NUMPY_TEMP_BYTES)
        yield lo, hi, b.values, b.gradients


def check_rows(points: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``points`` (N, 3) (returned as given) after the checks :func:`check_points` makes of
    ``points[rows]`` (the same refusal), a block at a time: ``rows`` (M,) int in 0..N-1."""
    arr, idx = np.asarray(points), np.asarray(rows)
    if idx.ndim != 1 or (idx.size and idx.dtype.kind not in "iu"):
        raise InputError(f"rows: expected a 1-D integer array, got {idx.dtype} {idx.shape}")
    if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] != 3:
        check_points(arr[idx])   # raises: the same line as for the gathered points
    if idx.size and (int(idx.min()) < 0 or int(idx.max()) >= arr.shape[0]):
        raise InputError(f"rows: expected indices in 0..{arr.shape[0] - 1}")
    if arr.dtype.kind == "f":
        step = ONESHOT_CHUNK
        for lo in range(0, idx.size, step):
            if not np.isfinite(arr[idx[lo:lo + step]]).all():
                check_points(arr[idx])   # raises, naming the row as the gathered points'
    return arr


@dataclass
class DeferredBasis:
    """A basis not computed yet: the free points (N, 3) and the fit, evaluated one-shot by
    :func:`splatdeform.deform.apply` (:func:`oneshot_chunks`), or stored on first use of
    ``values`` / ``gradients`` (the editor, ``--reuse``, ``full_basis``, rendering), which
    then behave as :class:`Basis`'s.

    positions: the free points (N, 3), or with ``rows`` (N,) int the array (M, 3) they are
    rows of (the model's positions: no copy of the free points is kept). backend: the
    concrete backend (numpy | opencl), resolved when it was made.
    """

    positions: np.ndarray
    fit: RbfFit
    backend: str
    device: str | None = None
    with_gradients: bool = True
    stored: Basis | None = None
    rows: np.ndarray | None = None

    @property
    def points(self) -> np.ndarray:
        """(N, 3) the free points (gathered from ``positions`` when ``rows`` is given)."""
        return self.positions if self.rows is None else self.positions[self.rows]

    def store(self) -> Basis:
        """The stored basis (computed once, then kept)."""
        if self.stored is None:
            from . import compute_basis

            self.stored = compute_basis(self.points, self.fit, gradients=self.with_gradients,
                                        backend=self.backend, device=self.device)
        return self.stored

    @property
    def values(self) -> np.ndarray:
        """(N, k) b(p), computed and kept on first use."""
        return self.store().values

    @property
    def gradients(self) -> np.ndarray | None:
        """(N, k, 3) grad b(p) in model units (None without gradients), computed on first use."""
        return self.store().gradients

    @property
    def n_points(self) -> int:
        return int((self.positions if self.rows is None else self.rows).shape[0])

    @property
    def k(self) -> int:
        return int(np.shape(self.fit.weights)[1])


def deferred_basis(points: np.ndarray, fit: RbfFit, *, gradients: bool = True,
                   backend: str = "auto", device: str | None = None,
                   rows: np.ndarray | None = None) -> DeferredBasis:
    """A :class:`DeferredBasis` of ``fit`` at ``points`` (N, 3), or at ``points[rows]``
    (``rows`` (N,) int: the points are read from ``points`` as needed, never copied whole):
    the backend resolved and the inputs checked now (the same errors as
    :func:`splatdeform.basis.compute_basis`, at the same stage), the evaluation left to
    apply."""
    from . import resolve_backend

    if rows is None:
        check_points(points)
    else:
        check_rows(points, rows)
    check_fit(fit)
    chosen = resolve_backend(backend, device)
    return DeferredBasis(points, fit, chosen, device, bool(gradients),
                         rows=None if rows is None else np.asarray(rows))
