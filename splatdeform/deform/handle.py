"""The handle metaphor: affine frame, affine coordinates and the handle transform.

Frame C (4, 3): the handle's centroid plus its principal axes scaled by its extent. Every point
h has affine coordinates m(h) (4,) with sum 1 and h = m(h)^T C, so for any affine T,
T(h) - h = m(h)^T (T(C) - C) = m(h)^T delta_c.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.errors import InputError, RegionError


@dataclass(frozen=True)
class AffineFrame:
    """control_points: (4, 3) float64 frame C. inverse: (4, 4) float64 with
    m(h) = inverse[:, :3] @ h + inverse[:, 3]."""

    control_points: np.ndarray
    inverse: np.ndarray

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """Affine coordinates (M, 4) float64 of points (M, 3)."""
        return points @ self.inverse[:, :3].T + self.inverse[:, 3]

    def coordinate_gradients(self) -> np.ndarray:
        """(4, 3) float64: d m_k / d h (constant)."""
        return self.inverse[:, :3].copy()


def handle_frame(points: np.ndarray, name: str = "regions.handle") -> AffineFrame:
    """Affine frame of the handle points (M, 3).

    Raises RegionError when the handle is degenerate (a single point or collinear points): an
    affine map is not determined by such a handle. A planar handle is fine: its third axis is the
    plane normal, scaled like the largest extent.
    """
    pts = np.asarray(points, dtype=np.float64)
    centroid = pts.mean(axis=0)
    centred = pts - centroid
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    if sv.size < 2 or sv[0] <= 0 or sv[1] <= 1e-6 * sv[0]:
        raise RegionError.at(f"{name}", "the handle points are (nearly) collinear or a single "
                          "point; an affine handle needs points spanning at least a plane")
    extent = np.abs(centred @ vt.T).max(axis=0)
    extent = np.where(extent > 1e-3 * extent[0], extent, extent[0])
    axes = vt * extent[:, None]
    if np.linalg.det(vt) < 0:
        axes[2] *= -1
    control = np.vstack([centroid, centroid + axes])
    system = np.vstack([control.T, np.ones(4)])  # (4, 4): system @ m = [h; 1]
    return AffineFrame(control_points=control, inverse=np.linalg.inv(system))


def rotation_matrix(axis, degrees: float) -> np.ndarray:
    """(3, 3) rotation by ``degrees`` about ``axis`` (right-handed)."""
    a = np.asarray(axis, dtype=np.float64)
    norm = np.linalg.norm(a)
    if not norm > 0:
        raise InputError.at("handle.transform.rotate.axis", "expected a non-zero vector")
    x, y, z = a / norm
    t = np.radians(degrees)
    c, s, C = np.cos(t), np.sin(t), 1 - np.cos(t)
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def compose_transform(*, pivot: np.ndarray, scale=1.0, axis=(0.0, 0.0, 1.0),
                      degrees: float = 0.0, translate=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 matrix: scale, then rotate, then translate, about ``pivot`` (3,).

    Parameters
    ----------
    pivot : array_like, shape (3,)
        The point that scaling and rotation keep in place (model units).
    scale : float or array_like, shape (3,)
        Uniform or per-axis scale factors (non-zero).
    axis : array_like, shape (3,)
        The rotation axis (any non-zero length).
    degrees : float
        The rotation angle about ``axis`` (right-handed).
    translate : array_like, shape (3,)
        The move applied last (model units).

    Returns
    -------
    ndarray of float64, shape (4, 4)
        The affine map, for :func:`delta_for` and ``apply(..., moving_matrix=)``.

    Raises
    ------
    InputError
        A zero scale factor or a zero rotation axis.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> m = sd.compose_transform(pivot=(4, 0, 0), axis=(0, 0, 1), degrees=90,
    ...                          translate=(0, 0.5, 0))
    >>> m.shape
    (4, 4)
    >>> np.allclose(m @ [4, 0, 0, 1], [4, 0.5, 0, 1])    # the pivot only moves by translate
    True
    >>> np.allclose(m @ [5, 0, 0, 1], [4, 1.5, 0, 1])    # +x turns to +y about the pivot
    True
    """
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    if np.any(s == 0):
        raise InputError.at("handle.transform.scale", "expected non-zero scale factors")
    linear = rotation_matrix(axis, degrees) @ np.diag(s) if degrees else np.diag(s)
    pivot = np.asarray(pivot, dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = pivot + np.asarray(translate, dtype=np.float64) - linear @ pivot
    return m


def apply_affine(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (M, 3) mapped by a 4x4 affine matrix."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def delta_for_transform(control_points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """delta_c (4, 3) = T(C) - C for a 4x4 affine matrix T.

    Parameters
    ----------
    control_points : ndarray, shape (4, 3)
        One handle's affine frame C (``Deformation.control_points`` for a single handle).
    matrix : ndarray, shape (4, 4)
        The affine map T, e.g. from :func:`compose_transform`.

    Returns
    -------
    ndarray of float64, shape (4, 3)
        How far each control point moves (model units); :func:`delta_for` does this per
        handle of a deformation.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> frame = np.array([[4, 0, 0], [5, 0, 0], [4, 1, 0], [4, 0, 1]], dtype=float)
    >>> up = sd.compose_transform(pivot=(4, 0, 0), translate=(0, 0.5, 0))
    >>> sd.delta_for_transform(frame, up)
    array([[0. , 0.5, 0. ],
           [0. , 0.5, 0. ],
           [0. , 0.5, 0. ],
           [0. , 0.5, 0. ]])
    >>> turn = sd.compose_transform(pivot=(4, 0, 0), axis=(0, 0, 1), degrees=90)
    >>> np.allclose(sd.delta_for_transform(frame, turn)[1], [-1, 1, 0])   # (5,0,0) -> (4,1,0)
    True
    """
    return apply_affine(matrix, control_points) - control_points
