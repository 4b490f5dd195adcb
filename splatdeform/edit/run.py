"""One edit end to end: load -> config to plain data -> rings -> fit -> basis -> apply -> save.

This is what ``splatdeform deform EDIT.yaml`` runs, and the Python API behind it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from splatdeform import deform as df
from splatdeform.basis import compute_basis
from splatdeform.edit import plain
from splatdeform.edit.config import EditConfig, input_paths
from splatdeform.edit.plain import control_displacement, metaphors, transform_matrix  # noqa: F401
from splatdeform.errors import InputError, ProcessingError
from splatdeform.io import SUPPORTED, extension_of, load, save
from splatdeform.io.atomic import check_io_paths
from splatdeform.model import MAX_COORDINATE, PointModel
from splatdeform.rbf import RbfFit


@dataclass
class EditResult:
    """What one edit produced: the deformed model, the precomputed deformation, the control
    displacement delta_c (k, 3), the handle matrix (4x4, handle edits), the figures printed."""

    model: PointModel
    deformed: PointModel
    deformation: df.Deformation
    delta_c: np.ndarray
    matrix: np.ndarray | None
    output: Path | None
    stats: dict[str, float | int | str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


def not_converged_message(fit: RbfFit, cfg: EditConfig) -> str | None:
    """One line when the fit stopped at fit.max_centers above fit.tolerance, else None."""
    if fit.converged:
        return None
    return (f"fit: did not converge: largest constraint error {fit.max_error:.3g} > "
            f"fit.tolerance {fit.tolerance:.3g} after {fit.n_centers} centers "
            f"(fit.max_centers {cfg.fit.max_centers}); raise fit.max_centers or fit.tolerance, "
            "or use fit.method: exact or auto")


def prepare_model(cfg: EditConfig, base_dir: Path, timings: dict[str, float],
                  drop_nonfinite: bool = False) -> PointModel:
    """Load the input (and estimate normals if asked)."""
    t0 = time.perf_counter()
    model = load(base_dir / cfg.input, drop_nonfinite=drop_nonfinite)
    if cfg.normals == "estimate" and model.normals is None:
        from splatdeform.deform.normals import estimate_normals

        model = estimate_normals(model, cfg.boundary.neighbors)
        model.path = str(base_dir / cfg.input)
    check_fit_range(model.positions, base_dir / cfg.input)
    timings["load"] = time.perf_counter() - t0
    return model


def check_fit_range(positions: np.ndarray, path: Path) -> None:
    """Refuse coordinates (N, 3) the fit cannot work with (|x| > 1e15, e.g. float32's 3.4e38),
    naming the first such point."""
    far = np.abs(positions).max(axis=1) > MAX_COORDINATE if positions.size else None
    if far is not None and far.any():
        i = int(np.flatnonzero(far)[0])
        raise InputError(f"{path}: point {i} at {positions[i].tolist()} is beyond "
                         f"+-{MAX_COORDINATE:g}; the fit would overflow ({int(far.sum())} such "
                         "point(s)); fix or crop the file")


def precompute(cfg: EditConfig, model: PointModel, base_dir: Path) -> df.Deformation:
    """Regions, rings, one fit and one basis for every handle and curve of the edit."""
    return df.prepare_metaphors(model, plain.fixed_mask(cfg, model, base_dir),
                                plain.metaphors(cfg, model, base_dir),
                                fit_fn=plain.fit_fn(cfg, model), basis_fn=plain.basis_fn(cfg),
                                continuity=cfg.boundary.continuity,
                                neighbors=cfg.boundary.neighbors)


def check_converged(fit: RbfFit, cfg: EditConfig,
                    warn: Callable[[str], None] | None) -> None:
    """Never a silent miss: warn (or raise, ``fit.on_not_converged: error``) when the fit
    stopped at ``fit.max_centers`` above the tolerance."""
    message = not_converged_message(fit, cfg)
    if message is None:
        return
    if cfg.fit.on_not_converged == "error":
        raise ProcessingError(message)
    if warn is not None:
        warn(message)


def run_edit(cfg: EditConfig, base_dir: str | Path = ".", *, output: str | Path | None = None,
             save_output: bool = True, drop_nonfinite: bool = False,
             reuse: str | Path | None = None,
             log: Callable[[str], None] | None = None,
             warn: Callable[[str], None] | None = None,
             stream: dict | None = None) -> EditResult:
    """Run one edit. ``output`` overrides ``cfg.output``; ``reuse`` names a precomputed
    deformation file to load when it matches this edit (and to write otherwise). ``warn``
    receives the one-line warning of a fit that stopped above the tolerance (with
    ``fit.on_not_converged: error`` that is a ProcessingError instead, before any output).
    ``stream``: {budget, scheduler, workers, quiet} for the out-of-core path
    (:mod:`splatdeform.edit.stream`), taken when the input exceeds the budget or Dask is asked
    for."""
    base_dir = Path(base_dir)
    out_path = Path(output) if output is not None else base_dir / cfg.output
    in_path = base_dir / cfg.input
    if save_output:
        if extension_of(out_path) not in SUPPORTED:  # a SOG folder's meta.json too
            raise InputError(f"{out_path}: unknown output extension {out_path.suffix!r}; "
                             f"expected one of {', '.join(SUPPORTED)}")
        check_io_paths(input_paths(cfg, base_dir),
                       [("output", out_path), ("reuse cache", reuse)])
        from splatdeform.edit.stream import (
            maybe_stream,  # out of core / on Dask when asked or too big
        )

        streamed = maybe_stream(cfg, base_dir, out_path, reuse=reuse, log=log,
                                drop_nonfinite=drop_nonfinite,
                                check_fit=lambda fit: check_converged(fit, cfg, warn),
                                **(stream or {}))
        if streamed is not None:
            return streamed
    timings: dict[str, float] = {}
    model = prepare_model(cfg, base_dir, timings, drop_nonfinite)
    deformation = None
    if reuse is not None:
        from splatdeform.edit.cache import edit_key, load_deformation

        key = edit_key(cfg, in_path)
        deformation = load_deformation(reuse, key, model)
        if log and deformation is not None:
            log(f"reused precomputed deformation {reuse}")
    if deformation is None:
        deformation = precompute(cfg, model, base_dir)
        timings.update(deformation.timings)
        check_converged(deformation.fit, cfg, warn)
        if reuse is not None:
            from splatdeform.edit.cache import save_deformation

            save_deformation(reuse, key, deformation)
    else:
        timings.update({"rings": 0.0, "fit": 0.0, "basis": 0.0})
        check_converged(deformation.fit, cfg, warn)
    if log:
        from splatdeform.edit.selection import counts_of_deformation, format_counts, moving_label

        log(format_counts(counts_of_deformation(deformation, moving_label(cfg))))
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    t0 = time.perf_counter()
    applied: dict = {}
    deformed = df.apply(deformation, model, delta_c, moving_matrix=matrix,  # checks finiteness
                        covariance=cfg.gaussians.covariance, stats=applied)
    timings["apply"] = time.perf_counter() - t0
    err, err_rms = df.constraint_errors(deformation, delta_c,
                                        partial(compute_basis, gradients=False,
                                                backend="numpy"))
    fit = deformation.fit
    stats = {
        "points": model.n_points,
        "free_points": int(deformation.free_idx.size),
        "constraints": int(deformation.constraint_idx.size),
        "kept": deformation.n_kept,
        "centers": fit.n_centers,
        "residual": fit.max_error,
        "residual_rms": fit.rms_error,
        "tolerance": fit.tolerance,
        "method": fit.method,
        "converged": bool(fit.converged),
        "constraint_error": err,
        "constraint_error_rms": err_rms,
        "constraint_error_rel": err / max(model.diagonal(), 1e-300),
        "refused_splats": int(applied.get("refused_splats", 0)),
    }
    result = EditResult(model, deformed, deformation, delta_c, matrix, None, stats, timings)
    if save_output:
        t0 = time.perf_counter()
        result.output = save(deformed, out_path)
        timings["save"] = time.perf_counter() - t0
    return result


def format_report(result: EditResult) -> str:
    """The lines ``splatdeform deform`` prints: counts, fit figures, per-stage timings."""
    s = result.stats
    lines = [
        f"points {s['points']:,}  free {s['free_points']:,}  constraints {s['constraints']:,} "
        f"(kept {s.get('kept', s['constraints']):,})  centers {s['centers']}",
        f"fit ({s['method']}): largest |r| {s['residual']:.3g}, RMS {s['residual_rms']:.3g} "
        f"over the {'kept' if s['method'] != 'exact' else 'all'} constraints (tolerance "
        f"{s['tolerance']:.3g}, converged: {str(s['converged']).lower()})",
        f"constraint error for this transform over all {s['constraints']:,} ring points: max "
        f"{s['constraint_error']:.3g}, RMS {s['constraint_error_rms']:.3g} model units "
        f"({s['constraint_error_rel']:.2e} of the diagonal)",
    ]
    if s.get("refused_splats"):
        lines.append(f"gaussians.covariance rotation: {s['refused_splats']:,} splats folded "
                     "(det J <= 0) kept their covariance")
    for stage in ("load", "rings", "fit", "basis", "apply", "save", "render"):
        if stage in result.timings:
            lines.append(f"{stage:<7}{result.timings[stage]:9.3f} s")
    if result.output is not None:
        lines.append(f"wrote {result.output}")
    return "\n".join(lines)
