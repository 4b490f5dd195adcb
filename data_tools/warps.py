"""The known smooth warp of a drifted scan (rubber-sheeting tests, benchmark and example): a
drift growing along y plus two broad bumps (metres), laid out on a bounding box. It ships in the
package (:mod:`splatdeform.examples.terrain`, for ``splatdeform example rubber_sheet``)."""

from __future__ import annotations

from splatdeform.examples.terrain import drift_warp

__all__ = ["drift_warp"]
