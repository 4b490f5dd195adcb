"""The editor's state as values (no web imports): a handle (its selectors and pose), a
:class:`Snapshot` of everything editable (undo / redo), the pose check, the limits, and the
error an action raises when it needs a fresh fit. :mod:`.controller` owns the state and changes
it through its methods; :mod:`.saving` and :mod:`.history` read it through them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from splatdeform.edit.selectors import Selector

from ..errors import InputError
from .curve import CurveState

ROLES = ("fixed", "handle")
FREE, FIXED, HANDLE = 0, 1, 2
MAX_HANDLES = 64        # handles one edit may have in the editor
MAX_SELECTORS = 1000    # selectors over the fixed region and all handles together
#: a pose's 3x3 part: smallest singular value, absolute (docs/guides/editor.md)
MIN_SINGULAR = 1e-6
MIN_CONDITION = 1e-9    # ... and relative to the largest


def check_pose(matrix: Any, key: str) -> np.ndarray:
    """``matrix`` as a (4, 4) float64 affine pose, or InputError naming ``key``: non-finite
    entries, a last row other than 0 0 0 1, or a 3x3 part that is singular or nearly so
    (smallest singular value below :data:`MIN_SINGULAR` or :data:`MIN_CONDITION` of the
    largest: the handle's points would collapse onto a plane, a line or a point)."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise InputError(f"{key}: expected a finite 4x4 affine matrix (last row 0 0 0 1)")
    s = np.linalg.svd(m[:3, :3], compute_uv=False)
    if not s[-1] >= MIN_SINGULAR or not s[-1] >= MIN_CONDITION * s[0]:
        raise InputError(f"{key}: the 3x3 part is singular or nearly so (singular values "
                         f"{s[0]:.3g} .. {s[-1]:.3g}; expected the smallest at least "
                         f"{MIN_SINGULAR:g} and {MIN_CONDITION:g} of the largest): it would "
                         "collapse the handle's points")
    return m


class StaleFitError(InputError):
    """An action needs a fit that matches the current regions (none yet, or regions changed)."""


@dataclass
class HandleState:
    """One handle: its region (a union of selectors) and its pose, a (4, 4) float64 affine
    matrix in model coordinates (identity = not moved)."""

    selectors: list[Selector] = field(default_factory=list)
    matrix: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass(frozen=True, eq=False)
class Snapshot:
    """The controller's editable state as a value (:meth:`EditorController.snapshot`): the
    fixed selectors, per handle its selectors and (4, 4) pose, the curve (immutable, its moved
    points included), the Gaussians' covariance mode and the control-point pairs (the
    ``points:`` config: replaced on a change, never changed in place). Selectors are immutable
    values. Compare two with :meth:`same`."""

    fixed: tuple[Selector, ...]
    handles: tuple[tuple[tuple[Selector, ...], np.ndarray], ...]
    curve: CurveState | None
    covariance: str
    points: Any = None

    def same(self, other: Snapshot | None) -> bool:
        """True when ``other`` holds the same state (poses compared exactly)."""
        if other is None or self.fixed != other.fixed or self.curve != other.curve or \
                self.covariance != other.covariance or self.points != other.points or \
                len(self.handles) != len(other.handles):
            return False
        return all(sa == sb and np.array_equal(ma, mb)
                   for (sa, ma), (sb, mb) in zip(self.handles, other.handles, strict=True))
