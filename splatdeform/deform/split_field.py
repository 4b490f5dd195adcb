"""The deformation field the splat split evaluates at sigma points and children
(:mod:`splatdeform.deform.split`), through the backend the centres use.

For an RBF fit the displacement is d(x) = [1, p] . (W delta_c)[:4] + r(x), r(x) = sum_j
|p - s_j|^3 (W delta_c)_j the RBF part (p = (x - c) / scale). The polynomial part is affine, so
the split's second-order term along a sigma step h is r(x + h) + r(x - h) - 2 r(x): exactly 0
when the RBF weights W delta_c are 0 (an affine field never splits, whatever the backend's
rounding), and its first-order term is h + A h + (r(x + h) - r(x - h)) / 2 with A the
polynomial part's linear map. One-shot (d and J from W delta_c a chunk at a time, OpenCL
float32 with double accumulation or the float64 numpy reference, :mod:`splatdeform.basis.
oneshot`); for a deformation with a stored basis the sigma points' k-column RBF basis is kept
once per fit (pose-independent) and each pose is one product.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

SIGMA_EXTENT = 2.0  # sigma points at +- this many standard deviations
SIGMA_BLOCK = 1 << 16  # splats per block of sigma points (bounds the temporaries)
_STORE_ATTR = "_split_sigma_basis"  # (sigma points (7M, 3), RBF basis (7M, k)) on the store
_ONESHOT_ATTR = "_split_oneshot"  # (backend, device) of a stored-basis deformation's split

# rest points (M, 3) -> deformed positions (M, 3), and the Jacobians (M, 3, 3) when asked
Field = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]


def sigma_steps(sigma: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(M, 3 axes, 3 xyz) the steps h_k = :data:`SIGMA_EXTENT` s_k a_k to the sigma points."""
    return (rot * (SIGMA_EXTENT * sigma)[:, None, :]).transpose(0, 2, 1)


def sigma_points(centers: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(M * 7, 3) the sigma points x, x + h_k, x - h_k (k = 0..2) of M splats, splat-major."""
    c = np.asarray(centers, np.float64)[:, None, :]
    return np.concatenate([c, c + steps, c - steps], axis=1).reshape(-1, 3)


def ratio(second: np.ndarray, first: np.ndarray) -> np.ndarray:
    """(M, 3) second / first (0 where the first-order term is 0)."""
    return np.divide(second, first, out=np.zeros_like(second), where=first > 0)


class FitField:
    """The deformation x + d(x) of an RBF ``fit`` under control displacements ``delta_c``
    (k, 3) at any rest points, through the backend the centres use (:func:`oneshot_chunks`:
    OpenCL float32 with double accumulation, or the float64 numpy reference), a chunk at a time
    from the combined weights W delta_c; with ``store`` (a deformation whose basis is stored)
    the sigma points' RBF basis is kept on it and reused for every pose.

    Called as a :data:`Field`: (M, 3) rest points -> float64 (M, 3) positions and (M, 3, 3)
    Jacobians I + grad d when asked. :meth:`curvature` is the rule's bend test from the RBF
    part alone."""

    #: True: the split tests the splats with this field's J at their centres, not the
    #: caller's (a stored basis's J, rounded otherwise): see :func:`split_like_oneshot`
    own_jacobians = False

    def __init__(self, fit, delta_c: np.ndarray, *, backend: str = "numpy",
                 device: str | None = None, store: object | None = None) -> None:
        from splatdeform.basis.oneshot import combined_fit

        self.fit, self.delta = fit, np.asarray(delta_c, np.float64)
        self.backend, self.device, self.store = backend, device, store
        combined = combined_fit(fit, self.delta).weights  # (4 + n, 3)
        # the polynomial part [1, p] . W delta_c is affine: d d_a / d x_b = W[1 + b, a] / scale
        self.linear = combined[1:4].T / float(fit.normalization.scale)  # (3, 3)
        rbf = np.array(fit.weights, np.float64)
        rbf[:4] = 0.0  # the RBF part alone: sum_j |p - s_j|^3 (W delta_c)_j
        self._rbf_basis_fit = replace(fit, weights=rbf)  # k columns: for a stored basis
        self._rbf_fit = self._rbf_basis_fit

    def _chunks(self, fit, points: np.ndarray, gradients: bool):
        from splatdeform.basis.oneshot import oneshot_chunks

        return oneshot_chunks(points, fit, self.delta, gradients=gradients,
                              backend=self.backend, device=self.device)

    def _stored_rbf(self, centers: np.ndarray, sigma: np.ndarray, rot: np.ndarray
                    ) -> np.ndarray:
        """(M * 7, k) the RBF part's basis at the sigma points (pose-independent): computed
        once per fit and splat set, kept on ``store`` (a deformation with a stored basis) and
        reused while the sigma points are the same."""
        from splatdeform.basis import compute_basis

        points = sigma_points(centers, sigma_steps(sigma, rot))
        kept = getattr(self.store, _STORE_ATTR, None)
        if kept is not None and kept[0].shape == points.shape and np.array_equal(kept[0], points):
            return kept[1]
        values = compute_basis(points, self._rbf_basis_fit, gradients=False,
                               backend=self.backend, device=self.device).values
        setattr(self.store, _STORE_ATTR, (points, values))
        return values

    def __call__(self, points: np.ndarray, gradients: bool
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        pts = np.asarray(points, np.float64)
        moved = pts.copy()
        jac = np.empty((pts.shape[0], 3, 3)) if gradients else None
        for lo, hi, disp, grad in self._chunks(self.fit, pts, gradients):
            moved[lo:hi] += disp
            if jac is not None:
                jac[lo:hi] = grad
        if jac is not None:
            jac[:, [0, 1, 2], [0, 1, 2]] += 1.0
        return moved, jac

    def curvature(self, centers: np.ndarray, sigma: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(M, 3) the rule's e_k / l_k from the RBF part r(x) at the 7 sigma points: the
        affine part's second difference is zero, so e_k = |r(x + h) + r(x - h) - 2 r(x)| / 2
        (exactly 0 when the RBF weights W delta_c are 0: an affine field never splits, whatever
        the backend's rounding), l_k = |h + A h + (r(x + h) - r(x - h)) / 2| with A the
        polynomial part's linear map."""
        m = centers.shape[0]
        out = np.zeros((m, 3))
        if m == 0 or not np.any(self._rbf_fit.weights[4:] @ self.delta):
            return out  # no RBF part: the field is affine, e_k = 0 exactly
        stored = self._stored_rbf(centers, sigma, rot) if self.store is not None else None
        for lo in range(0, m, SIGMA_BLOCK):  # bounded temporaries: 7 points per splat
            hi = min(m, lo + SIGMA_BLOCK)
            steps = sigma_steps(sigma[lo:hi], rot[lo:hi])
            if stored is not None:  # the pose-independent basis, times this pose
                r = stored[lo * 7:hi * 7].astype(np.float64) @ self.delta
            else:  # one-shot: W delta_c at the sigma points
                r = np.empty(((hi - lo) * 7, 3))
                for a, b, disp, _ in self._chunks(self._rbf_fit, sigma_points(
                        centers[lo:hi], steps), False):
                    r[a:b] = disp
            r = r.reshape(hi - lo, 7, 3)
            plus, minus = r[:, 1:4], r[:, 4:7]
            second = np.linalg.norm(plus + minus - 2 * r[:, :1], axis=2) / 2
            first = np.linalg.norm(steps + steps @ self.linear.T + (plus - minus) / 2, axis=2)
            out[lo:hi] = ratio(second, first)
        return out


def fit_field(deformation, delta_c: np.ndarray) -> FitField:
    """The :class:`FitField` of a deformation: a one-shot basis's backend, one-shot per pose;
    a stored basis (the editor, ``--reuse``, poses applied in turn): OpenCL where a device
    exists, else the numpy reference, with the sigma points' basis kept on the deformation
    (computed once per fit, each pose then one product)."""
    from splatdeform.basis.oneshot import DeferredBasis

    basis = deformation.basis
    if isinstance(basis, DeferredBasis) and basis.stored is None:
        return FitField(deformation.fit, delta_c, backend=basis.backend, device=basis.device)
    oneshot = getattr(deformation, _ONESHOT_ATTR, None)
    if oneshot is not None:  # split_like_oneshot: as a run without the stored basis
        field = FitField(deformation.fit, delta_c, backend=oneshot[0], device=oneshot[1])
        field.own_jacobians = True
        return field
    from splatdeform.basis import opencl

    backend = "opencl" if opencl.opencl_available(None) else "numpy"
    return FitField(deformation.fit, delta_c, backend=backend, store=deformation)


def split_like_oneshot(deformation, backend: str, device: str | None) -> None:
    """Make ``deformation`` (a stored basis: ``deform --reuse``) split exactly as a one-shot
    run with ``backend`` / ``device`` would: the split test's J at the centres, the sigma
    points and the children all one-shot through that backend (the same decisions and the
    same children bytes as without ``--reuse``; the stored basis still moves the unsplit
    points). The sigma points' basis is not kept: 7 x free splats x centres floats (6 GB for
    150k splats and 1,500 centres) to save one evaluation per run."""
    from splatdeform.basis import resolve_backend

    setattr(deformation, _ONESHOT_ATTR, (resolve_backend(backend, device), device))


def basis_field(fit, delta_c: np.ndarray) -> Field:
    """The deformation of ``fit`` through the float64 numpy reference (:class:`FitField` on
    ``numpy``): deterministic whatever backend made the points' own basis (the benchmark's
    reference uses it)."""
    return FitField(fit, delta_c, backend="numpy")
