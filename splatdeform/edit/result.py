"""What one edit produced, in memory or streamed: :class:`EditResult`, the one builder of its
figures (:func:`edit_stats`, and :func:`fit_stats` for the fit alone, which the editor shows)
and the report ``splatdeform deform`` prints (:func:`format_report`).

Imports nothing of :mod:`splatdeform.edit.run` or :mod:`splatdeform.edit.stream` (both build
their results here).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from splatdeform import deform as df
from splatdeform.basis import compute_basis
from splatdeform.model import PointModel

Stats = dict[str, float | int | str]


@dataclass
class EditResult:
    """What one edit produced: the deformed model, the precomputed deformation, the control
    displacement delta_c (k, 3), the handle matrix (4x4, handle edits), the figures printed.
    A streamed edit has ``model``/``deformed`` None (never whole in memory) and the border
    set's deformation. ``points``: what a kind with constraints of its own reported (the
    control-point pairs' residuals: :class:`~splatdeform.edit.metaphors.points.PointsReport`),
    else None."""

    model: PointModel | None
    deformed: PointModel | None
    deformation: df.Deformation
    delta_c: np.ndarray
    matrix: np.ndarray | None
    output: Path | None
    stats: Stats = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    points: object | None = None


def fit_stats(deformation: df.Deformation, points: int, free_points: int) -> Stats:
    """The counts and fit figures of a precomputed deformation: points, free_points,
    constraints, kept, centers, residual (largest |r|), residual_rms, tolerance, method,
    converged."""
    fit = deformation.fit
    return {
        "points": int(points),
        "free_points": int(free_points),
        "constraints": int(deformation.constraint_idx.size),
        "kept": deformation.n_kept,
        "centers": fit.n_centers,
        "residual": fit.max_error,
        "residual_rms": fit.rms_error,
        "tolerance": fit.tolerance,
        "method": fit.method,
        "converged": bool(fit.converged),
    }


def edit_stats(deformation: df.Deformation, delta_c: np.ndarray, *, points: int,
               free_points: int, diagonal: float, **extra: float | int | str) -> Stats:
    """:func:`fit_stats` plus the constraint error of this transform (delta_c (k, 3)) over all
    constraint points (max, RMS, and max relative to the model's ``diagonal``), then ``extra``
    (the in-memory path's refused_splats, the streaming path's border_points and chunk)."""
    err, err_rms = df.constraint_errors(deformation, delta_c,
                                        partial(compute_basis, gradients=False,
                                                backend="numpy"))
    return {
        **fit_stats(deformation, points, free_points),
        "constraint_error": err,
        "constraint_error_rms": err_rms,
        "constraint_error_rel": err / max(diagonal, 1e-300),
        **extra,
    }


def format_report(result: EditResult) -> str:
    """The lines ``splatdeform deform`` prints: counts, fit figures, per-stage timings."""
    s = result.stats
    lines = [
        f"points {s['points']:,}  free {s['free_points']:,}  constraints {s['constraints']:,} "
        f"(kept {s.get('kept', s['constraints']):,})  centers {s['centers']}",
        f"fit ({s['method']}): largest |r| {s['residual']:.3g}, RMS {s['residual_rms']:.3g} "
        f"over {'the kept' if s['method'] != 'exact' else 'all'} constraints (tolerance "
        f"{s['tolerance']:.3g}, converged: {str(s['converged']).lower()})",
        f"constraint error for this transform over all {s['constraints']:,} ring points: max "
        f"{s['constraint_error']:.3g}, RMS {s['constraint_error_rms']:.3g} model units "
        f"({s['constraint_error_rel']:.2e} of the diagonal)",
    ]
    if s.get("refused_splats"):
        lines.append(f"gaussians.covariance rotation: {s['refused_splats']:,} splats folded "
                     "(det J <= 0) kept their covariance")
    if s.get("split_splats") or s.get("split_capped"):
        lines.append(f"gaussians.split: {s.get('split_splats', 0):,} splats split, "
                     f"{s.get('split_children', 0):,} children written"
                     + (f" ({s['split_capped']:,} more kept whole by the growth cap)"
                        if s.get("split_capped") else ""))
    if s.get("split_note"):
        lines.append(str(s["split_note"]))
    for stage in ("load", "rings", "fit", "basis", "apply", "save", "render"):
        if stage in result.timings:
            lines.append(f"{stage:<7}{result.timings[stage]:9.3f} s")
    if result.output is not None:
        lines.append(f"wrote {result.output}")
    return "\n".join(lines)
