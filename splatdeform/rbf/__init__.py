"""Triharmonic RBF fitting: kernel table, farthest point sampling, incremental QR fitter, exact
solve, and ``auto`` (the cheapest of the incremental fit, the exact solve through the kept
constraints and through all, by predicted cost).

Names are imported on first use, so that importing the plain result types (``RbfFit``,
``Normalization``) does not load scipy.linalg: ``splatdeform info`` and the CLI's parser start
without it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from splatdeform.lazy import lazy_exports

_LAZY = {
    "fit_incremental": "fit", "fit_exact": "exact", "fit_auto": "auto",
    "dense_threads": "exact",
    "farthest_point_order": "fps", "iter_farthest_points": "fps",
    "KERNELS": "kernel", "Kernel": "kernel", "kernel_matrix": "kernel", "phi": "kernel",
    "phi_gradient": "kernel",
    "Normalization": "result", "RbfFit": "result",
}

if TYPE_CHECKING:  # pragma: no cover
    from .auto import fit_auto
    from .exact import dense_threads, fit_exact
    from .fit import fit_incremental
    from .fps import farthest_point_order, iter_farthest_points
    from .kernel import KERNELS, Kernel, kernel_matrix, phi, phi_gradient
    from .result import Normalization, RbfFit


__getattr__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "KERNELS", "Kernel", "Normalization", "RbfFit", "dense_threads", "farthest_point_order",
    "fit_auto", "fit_exact",
    "fit_incremental", "iter_farthest_points", "kernel_matrix", "phi", "phi_gradient",
]
