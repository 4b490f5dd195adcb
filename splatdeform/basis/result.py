"""Plain data produced by the basis precomputation (numpy reference and OpenCL alike)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Basis:
    """The precomputed deformation basis for N points and k control DOFs.

    values:    (N, k) b_k(p): p' = p + values @ delta_c.
    gradients: (N, k, 3) grad b_k(p) in *model* units (already divided by the normalisation
               scale), or None when not requested: J(p) = I + sum_k outer(delta_c[k], grad[k]).
    dtype is float64 from the numpy reference and float32 from OpenCL.
    """

    values: np.ndarray
    gradients: np.ndarray | None

    @property
    def n_points(self) -> int:
        return int(self.values.shape[0])

    @property
    def k(self) -> int:
        return int(self.values.shape[1])
