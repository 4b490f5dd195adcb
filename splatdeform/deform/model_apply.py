"""Apply delta_c to a whole :class:`PointModel` with a precomputed deformation: positions,
normals (cof(J) n), tangent axes (J u), radius-only surfels and 3DGS covariances and SH.

Fixed points are copied (bit-exact), moving points move by their control coordinates (or a
handle's 4x4 verbatim), free points through the basis. The per-point arithmetic is
:mod:`splatdeform.deform.arrays`, the same the shader and the editor use.
"""

from __future__ import annotations

import numpy as np

from splatdeform.basis.oneshot import DeferredBasis
from splatdeform.deform import arrays as ap
from splatdeform.deform.deformation import Deformation
from splatdeform.deform.gaussians import DEFAULT_COVARIANCE
from splatdeform.deform.handle import apply_affine
from splatdeform.deform.regions import Group
from splatdeform.deform.split import DEFAULT_SPLIT
from splatdeform.errors import InputError
from splatdeform.model import PointModel

#: rows per block of the moving points' positions and of every point's attribute work (J,
#: cof(J) n, the normals' lengths): its temporaries stay in cache, the peak near input + output
APPLY_ROWS = 1 << 15


def _deform_gaussians(model: PointModel, out: PointModel, idx: np.ndarray,
                      jac: np.ndarray, covariance: str, stats: dict | None) -> None:
    """Covariances of 3DGS splats ``idx`` by the ``covariance`` mode (``jacobian``: J Sigma J^T,
    similarities composed directly, else J R S re-factored by a relatively accurate SVD) and SH
    bands 1..3 rotated by the polar R of J. Splats whose J is exactly I are left bit-identical
    (see :mod:`splatdeform.deform.gaussians`). ``stats["refused_splats"]`` counts splats whose
    covariance ``rotation`` refused (det J <= 0)."""
    from splatdeform.deform.gaussians import deform_gaussians

    g = model.gaussians
    sh_rest = None if g.sh_rest is None else g.sh_rest[idx]
    new = deform_gaussians(g.scale_log[idx], g.rotation[idx], sh_rest, jac, covariance)
    if stats is not None:
        stats["refused_splats"] = stats.get("refused_splats", 0) + new.refused
    out.gaussians.scale_log[idx] = new.scale_log
    out.gaussians.rotation[idx] = new.rotation
    if new.sh_rest is not None:
        out.gaussians.sh_rest[idx] = new.sh_rest


def _transform_attributes(model: PointModel, out: PointModel, idx: np.ndarray,
                          jac: np.ndarray, covariance: str = DEFAULT_COVARIANCE,
                          stats: dict | None = None, constant: bool = False) -> None:
    """Normals, axes, radii and splats of points ``idx`` (M,) by their J (M, 3, 3);
    ``constant``: every row of ``jac`` is the same (a rigid handle), cof(J) formed once."""
    cof = None
    if model.normals is not None:
        normals = model.normals[idx]
        cof = (ap.cofactor_apply_one(jac[0], normals) if constant
               else ap.cofactor_apply(jac, normals))
        out.normals[idx] = ap.transform_normals(jac, normals, cofactor=cof)
    if model.axes is not None:
        out.axes[idx] = ap.transform_axes(jac, model.axes[idx])
    elif model.radius is not None and cof is not None:
        out.radius[idx] = ap.round_surfel_radius(model.radius[idx], normals, cof)
    if model.gaussians is not None:
        _deform_gaussians(model, out, idx, jac, covariance, stats)


def handle_matrices(deformation: Deformation, moving_matrix
                    ) -> list[tuple[Group, np.ndarray]]:
    """Pair the handle groups with their 4x4 maps: ``moving_matrix`` is None (every moving
    point by its coordinates), one (4, 4) matrix (exactly one handle), or a sequence with one
    matrix (or None) per handle, in the deformation's handle order."""
    if moving_matrix is None:
        return []
    groups = deformation.handle_groups()
    if isinstance(moving_matrix, np.ndarray) and moving_matrix.shape == (4, 4):
        if len(groups) != 1:
            raise InputError(f"moving_matrix: one 4x4 matrix given for {len(groups)} handles; "
                             "pass one matrix (or None) per handle")
        return [(groups[0], moving_matrix)]
    matrices = list(moving_matrix)
    if len(matrices) != len(groups):
        raise InputError(f"moving_matrix: expected {len(groups)} matrices (one per handle), "
                         f"got {len(matrices)}")
    return [(g, np.asarray(m, dtype=np.float64)) for g, m in zip(groups, matrices, strict=True)
            if m is not None]


def apply(deformation: Deformation, model: PointModel, delta_c: np.ndarray, *,
          moving_matrix=None, covariance: str = DEFAULT_COVARIANCE, stats: dict | None = None,
          split: str = DEFAULT_SPLIT) -> PointModel:
    """The deformed copy of ``model`` for control displacements delta_c (k, 3).

    Positions, normals (cof(J) n), tangent axes (J u), radius-only surfels (area-preserving
    radius) and 3DGS covariances follow. moving_matrix: the handles' 4x4 affine maps (one
    matrix for a single handle, or one per handle), used verbatim for handle points (else they
    move by their coordinates, m . delta_c). covariance: how 3DGS covariances deform
    (:data:`splatdeform.deform.gaussians.COVARIANCE_MODES`); ``stats``, when given, receives
    ``refused_splats`` (splats whose covariance the ``rotation`` mode kept, det J <= 0).
    split: ``auto`` (default) replaces free-region splats one Gaussian cannot follow by
    children appended after the originals (:mod:`splatdeform.deform.split`; surfel discs with
    tangent axes alike, :mod:`splatdeform.deform.split_surfel`; ``stats`` then receives
    split_splats, split_children, split_capped); ``off`` keeps the point count.

    Parameters
    ----------
    deformation : Deformation
        What :func:`prepare_handle` (or ``prepare_handles`` / ``prepare_metaphors``) made for
        this model.
    model : PointModel
        The model it was prepared for (same points); never modified.
    delta_c : ndarray, shape (k, 3)
        The control displacement, e.g. :func:`delta_for` of the handle's 4x4 matrix.
    moving_matrix : ndarray (4, 4) or list of them, optional
        The handles' maps, applied verbatim to handle points.
    covariance : {"jacobian", "rotation", "limited"}
        How 3D Gaussian covariances deform (default ``limited``).
    stats : dict, optional
        Receives ``refused_splats`` (and the ``split_*`` counts).
    split : {"auto", "off"}
        Split free-region splats one Gaussian cannot follow, and surfel discs with tangent
        axes one disc cannot follow (``auto``, the default; other models are never split).

    Returns
    -------
    PointModel
        The deformed copy: fixed points bit for bit, handle points by their 4x4 map.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_handle(bar, fixed, handle, backend="numpy")
    >>> lift = sd.compose_transform(pivot=(4, 0, 0), axis=(0, 0, 1), degrees=0,
    ...                             translate=(0, 0.5, 0))
    >>> bent = sd.apply(d, bar, sd.delta_for(d, lift), moving_matrix=lift)
    >>> bool((bent.positions[fixed] == bar.positions[fixed]).all())    # bit for bit
    True
    >>> np.allclose(bent.positions[handle], bar.positions[handle] + [0, 0.5, 0])
    True
    >>> free = d.free_idx                            # between the two: a smooth blend
    >>> bool(0 < (bent.positions[free] - bar.positions[free])[:, 1].mean() < 0.5)
    True
    """
    if model.n_points != deformation.n_points:
        raise InputError(f"model: expected {deformation.n_points} points, got "
                         f"{model.n_points}")
    delta = np.asarray(delta_c, dtype=np.float64)
    if split != "off":
        from splatdeform.deform.split import check_mode

        check_mode(split)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = _apply(deformation, model, delta, moving_matrix, covariance, stats, split)
    check_finite(model, out)
    return out


def _apply(deformation: Deformation, model: PointModel, delta: np.ndarray,
           moving_matrix: np.ndarray | None, covariance: str, stats: dict | None,
           split: str = "off") -> PointModel:
    out = model.copy()
    free = deformation.free_idx
    needs_jac = any(a is not None for a in (model.normals, model.axes, model.gaussians))
    oneshot = isinstance(deformation.basis, DeferredBasis) and deformation.basis.stored is None
    if oneshot:  # d(x) and J(x) from the centers and W delta_c, chunk by chunk
        jac_free = _apply_oneshot(deformation, model, out, delta, needs_jac, covariance,
                                  stats, keep_jac=split == "auto" and _splittable(model))
    else:
        values = deformation.basis.values.astype(np.float64, copy=False)
        out.positions[free] = ap.displace(model.positions[free], values, delta)
    mov = deformation.moving_idx
    pairs = handle_matrices(deformation, moving_matrix)
    covered = np.zeros(mov.size, dtype=bool)
    for group, _ in pairs:
        covered[group.rows] = True
    if not covered.all():  # rows no 4x4 map overwrites below move by their coordinates
        coords = deformation.moving_coords
        for s in range(0, mov.size, APPLY_ROWS):
            rows = mov[s:s + APPLY_ROWS]
            out.positions[rows] = model.positions[rows] + coords[s:s + APPLY_ROWS] @ delta
    for group, matrix in pairs:
        for s in range(0, group.rows.size, APPLY_ROWS):
            rows = mov[group.rows[s:s + APPLY_ROWS]]
            out.positions[rows] = apply_affine(matrix, model.positions[rows])
    if needs_jac:
        if not oneshot:
            if deformation.basis.gradients is None:
                raise InputError("deformation: basis has no gradients; normals/axes need them")
            grads = deformation.basis.gradients.astype(np.float64, copy=False)
            jac_free = ap.jacobians(grads, delta)
            _transform_attributes(model, out, free, jac_free, covariance, stats)
        _moving_attributes(deformation, model, out, delta, covariance, stats)
        if split == "auto" and _splittable(model):  # issues 37, 46: splats, surfel discs
            from splatdeform.deform.split import fit_field
            from splatdeform.deform.split_surfel import split_points

            out = split_points(model, out, free, jac_free, fit_field(deformation, delta),
                               moved=int(model.n_points - np.count_nonzero(deformation.fixed)),
                               covariance=covariance, transform=_transform_attributes,
                               stats=stats)
    return out


def _splittable(model: PointModel) -> bool:
    """True when ``gaussians.split`` may split points of ``model`` (splats, surfel axes)."""
    from splatdeform.deform.split_surfel import splittable

    return splittable(model)


def _moving_attributes(deformation: Deformation, model: PointModel, out: PointModel,
                       delta: np.ndarray, covariance: str, stats: dict | None) -> None:
    """Normals, axes, radii and splats of the moving points, APPLY_ROWS at a time. A handle's
    gradients are one (k, 3) row broadcast (a stride-0 view): J is then the same for every
    point, formed once from one block's product (whose rows all agree) and cof(J) once."""
    mov = deformation.moving_idx
    grads = deformation.moving_gradients
    shared = None
    if mov.size and grads.strides[0] == 0:
        block = ap.jacobians(np.ascontiguousarray(grads[:min(APPLY_ROWS, mov.size)]), delta)
        if (block == block[:1]).all():
            shared = block
    for s in range(0, mov.size, APPLY_ROWS):
        rows = mov[s:s + APPLY_ROWS]
        if shared is not None:
            jac = shared[:rows.size]
        else:
            jac = ap.jacobians(np.ascontiguousarray(grads[s:s + APPLY_ROWS]), delta)
        _transform_attributes(model, out, rows, jac, covariance, stats,
                              constant=shared is not None)


def _apply_oneshot(deformation: Deformation, model: PointModel, out: PointModel,
                   delta: np.ndarray, needs_jac: bool, covariance: str, stats: dict | None,
                   keep_jac: bool) -> np.ndarray | None:
    """Free points of ``out`` (positions, and the attributes J moves) by one-shot evaluation of
    d(x) and J(x) = I + grad d(x), a chunk at a time (:mod:`splatdeform.basis.oneshot`): the
    same arithmetic downstream as the stored basis (float64 positions + d, J in float64), so
    both paths agree to float32 rounding. Returns the free points' J (Nf, 3, 3) when
    ``keep_jac`` (the splat split needs them all), else None."""
    from splatdeform.basis.oneshot import oneshot_chunks

    basis = deformation.basis
    if needs_jac and not basis.with_gradients:
        raise InputError("deformation: basis has no gradients; normals/axes need them")
    free = deformation.free_idx
    jac_all = np.empty((free.size, 3, 3)) if keep_jac and needs_jac else None
    size = min(APPLY_ROWS, free.size)
    moved_buf = np.empty((size, 3))  # float64 scratch, reused: no chunk-sized allocations
    jac_buf = np.empty((size, 3, 3)) if needs_jac else None
    for lo, hi, disp, grad in oneshot_chunks(basis.positions, basis.fit, delta,
                                             gradients=needs_jac, backend=basis.backend,
                                             device=basis.device, rows=basis.rows):
        for s in range(0, hi - lo, APPLY_ROWS):  # cache-sized blocks of the device chunk
            e = min(s + APPLY_ROWS, hi - lo)
            rows = free[lo + s:lo + e]
            moved = moved_buf[:e - s]
            np.copyto(moved, disp[s:e])  # float32 -> float64 as astype
            moved += model.positions[rows]
            out.positions[rows] = moved
            if jac_buf is None:
                continue
            jac = jac_buf[:e - s]
            np.copyto(jac, grad[s:e])
            jac[:, 0, 0] += 1
            jac[:, 1, 1] += 1
            jac[:, 2, 2] += 1
            _transform_attributes(model, out, rows, jac, covariance, stats)
            if jac_all is not None:
                jac_all[lo + s:lo + e] = jac
    return jac_all


_F32_MAX = float(np.finfo(np.float32).max)


def _stored_limit(model: PointModel, fields: tuple[str, ...], default: float) -> float:
    """The largest magnitude the output can hold for ``fields``: a PLY source keeps each
    field's type (float32 unless it was double); new models write positions as double."""
    vertex = None if model.source is None else model.source.element("vertex")
    names = () if vertex is None else (vertex.data.dtype.names or ())
    dtypes = [vertex.data.dtype[f] for f in fields if f in names]
    if not dtypes:
        return default
    return min(float(np.finfo(d).max) if d.kind == "f" else _F32_MAX for d in dtypes)


def check_finite(model: PointModel, out: PointModel) -> None:
    """Guard after a deformation: every float it writes (positions, normals,
    axes, radii, 3DGS scales and rotations) is finite and fits the output's number type, for
    every point whose input value was finite. Raises InputError naming the attribute."""
    from splatdeform.errors import InputError

    xyz = ("x", "y", "z")
    checks = [("positions", model.positions, out.positions, xyz, np.inf if model.source is None
               else _F32_MAX)]
    if out.normals is not None and model.normals is not None:
        checks.append(("normals", model.normals, out.normals, ("nx", "ny", "nz"), _F32_MAX))
    if out.axes is not None and model.axes is not None:
        checks.append(("surfel axes", model.axes, out.axes,
                       ("ux", "uy", "uz", "vx", "vy", "vz"), _F32_MAX))
    if out.radius is not None and model.radius is not None:
        checks.append(("radii", model.radius, out.radius, ("radius", "surfel_radius"),
                       _F32_MAX))
    g, g_in = out.gaussians, model.gaussians
    if g is not None and g_in is not None:
        checks.append(("gaussian scales", g_in.scale_log, g.scale_log,
                       ("scale_0", "scale_1", "scale_2"), _F32_MAX))
        checks.append(("gaussian rotations", g_in.rotation, g.rotation,
                       ("rot_0", "rot_1", "rot_2", "rot_3"), _F32_MAX))
    for what, before, after, fields, default in checks:
        limit = _stored_limit(model, fields, default)
        if _all_within(after, limit):  # one flat pass: nothing to attribute to rows
            continue
        rows_in = np.isfinite(before).reshape(before.shape[0], -1).all(axis=1)
        # split children (gaussians.split) come after the originals, from finite parents only
        rows_in = np.concatenate([rows_in, np.ones(after.shape[0] - rows_in.size, bool)])
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(after) & (np.abs(after) <= limit)
        ok = ok.reshape(after.shape[0], -1).all(axis=1)
        bad = int(np.count_nonzero(rows_in & ~ok))
        if bad:
            raise InputError(f"the deformation produced non-finite or out-of-range {what} for "
                             f"{bad:,} points; check the regions and the transform (a move "
                             "that large cannot be stored)")


def _all_within(values: np.ndarray, limit: float) -> bool:
    """Every value finite with |value| <= limit, from one pass over the flat array (a NaN
    makes the maximum NaN, so it fails like an infinity)."""
    if values.size == 0:
        return True
    flat = np.asarray(values).reshape(-1)
    largest = max(float(flat.max()), -float(flat.min()))
    return bool(np.isfinite(largest) and largest <= limit)


def full_basis(deformation: Deformation) -> tuple[np.ndarray, np.ndarray]:
    """Basis for every point, for one-draw-call rendering: values (N, k) float32 and
    gradients (N, k, 3) float32; 0 for fixed points, control coordinates for moving points.

    Parameters
    ----------
    deformation : Deformation
        From :func:`prepare_handle`, :func:`prepare_handles` or :func:`prepare_metaphors`.

    Returns
    -------
    values : ndarray of float32, shape (N, k)
        Each point's displacement is ``values @ delta_c``.
    gradients : ndarray of float32, shape (N, k, 3)
        d values / d x, for the normals and splat axes.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_handle(bar, fixed, handle, backend="numpy")
    >>> values, gradients = sd.full_basis(d)
    >>> values.shape, values.dtype, gradients.shape
    ((2000, 4), dtype('float32'), (2000, 4, 3))
    >>> bool((values[fixed] == 0).all()), np.allclose(values[handle].sum(axis=1), 1)
    (True, True)
    """
    n, k = deformation.n_points, deformation.k
    values = np.zeros((n, k), dtype=np.float32)
    grads = np.zeros((n, k, 3), dtype=np.float32)
    values[deformation.free_idx] = deformation.basis.values
    if deformation.basis.gradients is not None:
        grads[deformation.free_idx] = deformation.basis.gradients
    values[deformation.moving_idx] = deformation.moving_coords
    grads[deformation.moving_idx] = deformation.moving_gradients
    return values, grads
