"""The metaphor interface: what one handle or one curve contributes to an edit.

A metaphor is plain model-unit data: the points it moves, its control points C (k, 3), and for
each of its points the control coordinates m (k,) with displacement m . delta_c, and their
gradients. The deformation, the cache, the renderer and batch only see these columns (k of
them, stacked over every metaphor of the edit) and delta_c, never "handle or curve":

- handle: k = 4 affine frame coordinates (``handle.handle_frame``), constant gradients; its
  points get the 4x4 transform T itself.
- curve: k = number of control points, spline basis values at each band point's parameter
  (``curve.curve_metaphor``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.deform.handle import AffineFrame, handle_frame
from splatdeform.errors import RegionError


@dataclass
class Metaphor:
    """One metaphor's part of an edit.

    name: where it came from, for messages (``regions.handle``, ``handles[1]``, ``curve``).
    idx: (Nm,) int64 sorted indices of the points it moves.
    control_points: (k, 3) float64 C.
    coords: (Nm, k) float64 control coordinates of those points (rows in ``idx`` order).
    gradients: (Nm, k, 3) float64 d coords / d x.
    frame: the affine frame of a handle (None for a curve).
    """

    name: str
    idx: np.ndarray
    control_points: np.ndarray
    coords: np.ndarray
    gradients: np.ndarray
    frame: AffineFrame | None = None

    @property
    def k(self) -> int:
        return int(self.control_points.shape[0])


def handle_metaphor(positions: np.ndarray, mask: np.ndarray, name: str = "regions.handle"
                    ) -> Metaphor:
    """The handle metaphor for the points ``mask`` (N,) bool of ``positions`` (N, 3)."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        what = "the handle region" if name == "regions.handle" else "it"
        raise RegionError.at(f"{name}", f"selects no point; widen {what}")
    points = positions[idx]  # gathered once for the frame and the coordinates
    frame = handle_frame(points, name)
    grads = np.broadcast_to(frame.coordinate_gradients(), (idx.size, 4, 3))
    return Metaphor(name=name, idx=idx, control_points=frame.control_points,
                    coords=frame.coordinates(points), gradients=grads, frame=frame)
