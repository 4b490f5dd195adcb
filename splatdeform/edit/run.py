"""One edit end to end: load -> config to plain data -> rings -> fit -> basis -> apply -> save.

This is what ``splatdeform deform EDIT.yaml`` runs, and the Python API behind it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from splatdeform import deform as df
from splatdeform.edit import plain
from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import hooked
from splatdeform.edit.plain import control_displacement, metaphors, transform_matrix  # noqa: F401
from splatdeform.edit.plan import EditPlan, decide, plan_edit
from splatdeform.edit.result import EditResult, edit_stats, format_report  # noqa: F401
from splatdeform.edit.stream import StreamOptions, run_stream
from splatdeform.errors import InputError, ProcessingError
from splatdeform.io import load, save
from splatdeform.io.options import writing
from splatdeform.model import MAX_COORDINATE, PointModel
from splatdeform.rbf import RbfFit


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
    if positions.size == 0 or not np.abs(positions).max() > MAX_COORDINATE:  # NaN: not far
        return
    far = np.abs(positions).max(axis=1) > MAX_COORDINATE
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise InputError(f"{path}: point {i} at {positions[i].tolist()} is beyond "
                         f"+-{MAX_COORDINATE:g}; the fit would overflow ({int(far.sum())} such "
                         "point(s)); fix or crop the file")


def precompute(cfg: EditConfig, model: PointModel, base_dir: Path, *,
               stored: bool = True) -> df.Deformation:
    """Regions, rings, one fit and one basis for every metaphor of the edit (``stored=False``:
    the basis deferred, for one-shot evaluation by apply):
    :func:`splatdeform.edit.plain.precompute`."""
    return plain.precompute(cfg, model, base_dir, stored=stored)


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


def streams(cfg: EditConfig, in_path: Path, options: StreamOptions, budget: int | None, *,
            reuse: str | Path | None = None, drop_nonfinite: bool = False,
            warn: Callable[[str], None] | None = None) -> bool:
    """True when this edit runs out of core: the pre-flight's decision
    (:func:`splatdeform.edit.plan.decide`, which says when; refusals and warnings there)."""
    return decide(cfg, in_path, options, budget, reuse=reuse, drop_nonfinite=drop_nonfinite,
                  warn=warn)[0]


def run_edit(config: EditPlan | EditConfig | dict | str | Path,
             base_dir: str | Path | None = None, *, output: str | Path | None = None,
             save_output: bool = True, drop_nonfinite: bool = False,
             reuse: str | Path | None = None,
             log: Callable[[str], None] | None = None,
             warn: Callable[[str], None] | None = None,
             stream: StreamOptions | None = None) -> EditResult:
    """Run one edit.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> _ = sd.save(bumpy_bar(3000), "bar.ply")
    >>> edit = {"input": "bar.ply", "output": "bar_bent.ply",
    ...         "regions": {"units": "relative",
    ...                     "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
    ...                     "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
    ...         "handle": {"transform": {"rotate": {"axis": [0, 0, 1], "degrees": 35}}},
    ...         "backend": "numpy"}
    >>> result = sd.run_edit(edit, base_dir=".", log=lambda line: None)
    >>> result.stats["points"], result.stats["converged"]
    (3000, True)
    >>> sd.load("bar_bent.ply").n_points
    3000

    ``config``: an :class:`~splatdeform.edit.plan.EditPlan` (the CLI's and batch's: paths
    checked, stream-or-not decided; the planning arguments below are then not used), or what
    :func:`~splatdeform.edit.plan.plan_edit` plans from: an edit file's path (its relative
    paths resolve against its folder: ``run_edit("path/to/edit.yaml")``), or a mapping or an
    EditConfig whose relative paths resolve against ``base_dir`` (default: the current folder).
    ``output`` overrides ``cfg.output``; ``reuse`` names a precomputed deformation file to
    load when it matches this edit (and to write otherwise). ``warn`` receives the one-line
    warning of a fit that stopped above the tolerance (with ``fit.on_not_converged: error``
    that is a ProcessingError instead, before any output). ``stream``: budget, Dask and quiet
    options of the out-of-core path (:func:`splatdeform.edit.stream.run_stream`), taken when
    the input exceeds the budget or Dask is asked for; only when the output is saved."""
    if isinstance(config, EditPlan):
        plan = config
    else:
        plan = plan_edit(config, base_dir, output=output, save_output=save_output,
                         reuse=reuse, drop_nonfinite=drop_nonfinite, stream=stream, warn=warn)
    cfg, base_dir, in_path, reuse = plan.cfg, plan.base_dir, plan.input, plan.reuse
    drop_nonfinite = plan.drop_nonfinite
    if plan.streamed:
        return run_stream(plan, log=log, check_fit=lambda fit: check_converged(fit, cfg, warn))
    timings: dict[str, float] = {}
    model = prepare_model(cfg, base_dir, timings, drop_nonfinite)
    # the device opens while the rings are built; not beside a dense solve of a kind with its
    # own constraints (up to 3,000 pairs: the two peaks would add)
    if reuse is None and not hooked(cfg, "prepare"):
        from splatdeform.basis import warm_up

        jac = any(a is not None for a in (model.normals, model.axes, model.gaussians))
        warm_up(cfg.backend, cfg.device, 3, jac)  # one-shot: the K = 3 kernel of W delta_c
    deformation = None
    if reuse is not None:   # never a kind that cannot be reused (the plan refused it)
        from splatdeform.edit.cache import edit_key, load_deformation

        key = edit_key(cfg, in_path)
        deformation = load_deformation(reuse, key, model)
        if log and deformation is not None:
            log(f"reused precomputed deformation {reuse}")
    if deformation is None:
        deformation = precompute(cfg, model, base_dir, stored=reuse is not None)  # one-shot
        timings.update(deformation.timings)
        if reuse is not None:
            from splatdeform.edit.cache import save_deformation

            save_deformation(reuse, key, deformation)
    else:
        timings.update({"rings": 0.0, "fit": 0.0, "basis": 0.0})
    from splatdeform.deform.split_surfel import splittable

    if reuse is not None and splittable(model) and cfg.gaussians.split == "auto":
        from splatdeform.deform.split import split_like_oneshot

        split_like_oneshot(deformation, cfg.backend, cfg.device)  # as without --reuse
    check_converged(deformation.fit, cfg, warn)
    if log:
        from splatdeform.edit.selection import counts_of_deformation, format_counts, moving_label

        log(format_counts(counts_of_deformation(deformation, moving_label(cfg))))
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    t0 = time.perf_counter()
    applied: dict = {}
    deformed = df.apply(deformation, model, delta_c, moving_matrix=matrix,  # checks finiteness
                        covariance=cfg.gaussians.covariance, stats=applied,
                        split=cfg.gaussians.split)
    timings["apply"] = time.perf_counter() - t0
    stats = edit_stats(deformation, delta_c, points=model.n_points,
                       free_points=deformation.free_idx.size, diagonal=model.diagonal(),
                       refused_splats=int(applied.get("refused_splats", 0)),
                       **{k: int(v) for k, v in applied.items() if k.startswith("split_")})
    result = EditResult(model, deformed, deformation, delta_c, matrix, None, stats, timings)
    # a kind with constraints of its own: the pairs' residuals (``deform`` prints them,
    # --residuals writes them)
    result.points = plain.report(cfg, model, base_dir, deformation, delta_c)
    if plan.output is not None:
        t0 = time.perf_counter()
        with writing(**cfg.save.model_dump()):   # every save: key (spz_version, sog_order...)
            result.output = save(deformed, plan.output)
        timings["save"] = time.perf_counter() - t0
    return result
