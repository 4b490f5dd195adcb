"""Triharmonic RBF fitting: kernel table, farthest point sampling, incremental QR fitter."""

from splatdeform.rbf.fit import fit_incremental
from splatdeform.rbf.fps import farthest_point_order, iter_farthest_points
from splatdeform.rbf.kernel import KERNELS, Kernel, kernel_matrix, phi, phi_gradient
from splatdeform.rbf.result import Normalization, RbfFit

__all__ = [
    "KERNELS",
    "Kernel",
    "Normalization",
    "RbfFit",
    "farthest_point_order",
    "fit_incremental",
    "iter_farthest_points",
    "kernel_matrix",
    "phi",
    "phi_gradient",
]
