"""A fitted deformation as a file (``deform --save-field FIELD.npz``) and its use on any model
(``splatdeform apply FIELD.npz MODEL -o OUT``, ``sd.Field.load(path)``).

The file is an ``.npz`` (no pickles), kilobytes, independent of the model's size; its members
and the JSON ``meta`` are listed, with their bounds, in :mod:`splatdeform.field_schema`, which
reads a field as untrusted input (every member checked before use, one line naming the file
and the member for anything else):

- ``centers`` (n, 3) normalised, ``weights`` (4 + n, k): rows [1, x, y, z, phi_j];
  ``norm_center`` (3,), ``norm_scale`` (): model -> normalised coordinates;
- ``delta_c`` (k, 3): the applied control displacement (the field is d(x) = b(x) delta_c);
- ``frames`` (h, 4, 4) / ``inverses`` (h, 4, 4) / ``matrices`` (h, 4, 4): each handle's affine
  frame (rows 0..3 of ``frames`` hold C (4, 3) in columns 0..2) and its 4x4 transform;
- ``support`` (2, 3): the box of the fit's constraints and of the model it was fitted on
  (model units: where the field was fitted and ``deform`` evaluated it); ``apply`` counts
  the points it moves outside it and refuses a model entirely outside (unless
  ``--extrapolate``; :mod:`splatdeform.field_apply`);
- ``meta``: JSON: format, version, the regions' selectors in model units stored by kind name
  (:mod:`splatdeform.edit.selectors.stored`; relative units resolved: boxes and planes carry
  their frame), each handle's name, columns and selectors, the basis backend and the splat
  settings (``gaussians``); an ``indices`` selector (which does not transfer) is stored as its
  region's indices (``fixed_idx`` / ``handle_idx_<j>``, never a file name) with the point
  count and a digest of the saved model's positions.

Why not the ``--reuse`` cache's format: the cache holds the per-point basis of one model (size
grows with the model) keyed by the edit; a field holds only what re-evaluates on any model.
Both are ``.npz`` without pickles written atomically.

Apply (:meth:`Field.apply`): fixed points are copied bit for bit, handle points get their 4x4
transform exactly, every other point (the free region, and a curve band, which is not a
selector) moves by the field; normals, splat axes, covariances and SH follow as in ``deform``
(:func:`splatdeform.deform.apply`), so a field applied to a copy of its model gives the bytes
``deform`` wrote, except in a curve band (``deform`` moves it with the curve; the field meets
the curve within the fit's tolerance).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from splatdeform.errors import InputError
from splatdeform.field_schema import FORMAT, VERSION, read_field
from splatdeform.model import PointModel
from splatdeform.rbf.result import Normalization, RbfFit


def positions_digest(positions: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(positions, dtype=np.float64).tobytes()
                          ).hexdigest()


@dataclasses.dataclass
class SupportStats:
    """What the field met outside its support, added up chunk by chunk: ``points`` seen,
    ``moved`` by the field (neither fixed nor a handle), ``outside`` of those beyond the
    support box, ``distance`` the largest of their distances to it (model units), and the
    model's box ``lo`` / ``hi`` (3,) (None before any point)."""

    points: int = 0
    moved: int = 0
    outside: int = 0
    distance: float = 0.0
    lo: np.ndarray | None = dataclasses.field(default=None, repr=False)
    hi: np.ndarray | None = dataclasses.field(default=None, repr=False)

    def add(self, positions: np.ndarray, moved_idx: np.ndarray, box: np.ndarray) -> None:
        """Count ``positions`` (N, 3), of which ``moved_idx`` (M,) move by the field, against
        the support ``box`` (2, 3)."""
        n = len(positions)
        self.points += n
        if n == 0:
            return
        lo, hi = positions.min(axis=0).astype(np.float64), positions.max(axis=0).astype(
            np.float64)
        self.lo = lo if self.lo is None else np.minimum(self.lo, lo)
        self.hi = hi if self.hi is None else np.maximum(self.hi, hi)
        self.moved += int(moved_idx.size)
        for a in range(0, moved_idx.size, 1 << 20):
            p = positions[moved_idx[a:a + (1 << 20)]].astype(np.float64)
            gap = np.maximum(np.maximum(box[0] - p, p - box[1]), 0.0)
            far = np.einsum("ij,ij->i", gap, gap)
            beyond = far > 0
            self.outside += int(beyond.sum())
            if beyond.any():
                self.distance = max(self.distance, float(np.sqrt(far.max())))

    def overlaps(self, box: np.ndarray) -> bool:
        """Whether the model's box meets the support ``box`` (2, 3) (touching counts)."""
        if self.lo is None:
            return True
        return bool(np.all(self.lo <= box[1]) and np.all(self.hi >= box[0]))



class Field:
    """A saved deformation: ``field(points)`` -> displaced points (M, 3) (the smooth field
    x + d(x), numpy float64, regions not applied), ``field.jacobian(points)`` -> (M, 3, 3),
    ``field.apply(model)`` -> the deformed model as ``deform`` makes it.

    Made by ``splatdeform deform EDIT.yaml --save-field FIELD.npz`` (or
    :func:`field_of_edit`); read with :meth:`Field.load`.

    Parameters
    ----------
    fit : RbfFit
        The fitted RBF (centers, weights, normalisation).
    delta_c : ndarray, shape (k, 3)
        The applied control displacement: the field is d(x) = b(x) delta_c.
    meta : dict
        The regions' selectors, each handle's name and columns, backend and splat settings
        (see the module docstring).
    arrays : dict of ndarray
        ``frames``, ``inverses``, ``matrices`` and any stored indices.
    path : Path, optional
        The file it was loaded from (named in errors).

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from pathlib import Path
    >>> from splatdeform.edit.config import parse_edit
    >>> from splatdeform.field import Field, field_of_edit
    >>> from data_tools.synth import bumpy_bar
    >>> _ = sd.save(bumpy_bar(2000), "bar.ply")
    >>> edit = parse_edit({
    ...     "input": "bar.ply", "output": "bar_bent.ply", "backend": "numpy",
    ...     "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}],
    ...                 "handle": [{"box": {"min": [3, -1, -1], "max": [5, 1, 1]}}]},
    ...     "handle": {"transform": {"translate": [0, 0.5, 0]}}}, "edit")
    >>> result = sd.run_edit(edit, base_dir=".", log=lambda line: None)
    >>> field_of_edit(result, edit, Path(".")).save("lift.npz").name
    'lift.npz'
    >>> field = Field.load("lift.npz")
    >>> field(np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])).round(2)   # x + d(x)
    array([[0. , 0. , 0. ],
           [4. , 0.5, 0. ]])
    >>> other = bumpy_bar(3000, seed=1)              # another scan of the same part
    >>> moved = field.apply(other)
    >>> handle = other.positions[:, 0] >= 3
    >>> np.allclose(moved.positions[handle], other.positions[handle] + [0, 0.5, 0])
    True
    """

    def __init__(self, fit: RbfFit, delta_c: np.ndarray, meta: dict, arrays: dict,
                 path: Path | None = None) -> None:
        self.fit, self.delta_c, self.meta, self.arrays = fit, delta_c, meta, arrays
        self.path = path
        self.support_note = ""  # how the support was found when the file did not store it

    # --- as a function of space
    def __call__(self, points: np.ndarray) -> np.ndarray:
        from splatdeform.basis import compute_basis

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        b = compute_basis(p, self.fit, gradients=False, backend="numpy").values
        return p + b.astype(np.float64) @ self.delta_c

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """(M, 3, 3): I + sum_k delta_c_k (outer) grad b_k at points (M, 3)."""
        from splatdeform.basis import compute_basis

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        g = compute_basis(p, self.fit, gradients=True, backend="numpy").gradients
        return np.eye(3) + np.einsum("kc,mkd->mcd", self.delta_c, g.astype(np.float64))

    # --- the file
    def save(self, path: str | Path) -> Path:
        """Write the field (this version's format, atomically) to ``path`` (.npz)."""
        from splatdeform.io.atomic import atomic_write

        arrays = {"centers": self.fit.centers, "weights": self.fit.weights,
                  "norm_center": self.fit.normalization.center,
                  "norm_scale": np.float64(self.fit.normalization.scale),
                  "delta_c": self.delta_c, "meta": np.array(json.dumps(self.meta)),
                  "support": self.support, **self.arrays}
        with atomic_write(path) as fh:
            np.savez(fh, **arrays)
        return Path(path)

    @staticmethod
    def load(path: str | Path) -> Field:
        """Read a field file, every member checked (:func:`splatdeform.field_schema.read_field`);
        FormatError (one line naming the file and the member) for anything else."""
        path = Path(path)
        arrays, meta = read_field(path)
        centers, weights = arrays.pop("centers"), arrays.pop("weights")
        delta = arrays.pop("delta_c")
        norm = Normalization(arrays.pop("norm_center"), float(arrays.pop("norm_scale")))
        fit = RbfFit(centers=centers, weights=weights, normalization=norm,
                     residuals=np.zeros((1, weights.shape[1])), converged=True,
                     tolerance=0.0, method=meta["method"])
        return Field(fit, delta, meta, arrays, path)

    @property
    def support(self) -> np.ndarray:
        """(2, 3) float64: the low and high corner of the box of the fit's constraints and of
        the model it was fitted on (model units), where the field was fitted. A field that did
        not store it (version 1) gives the cube its normalisation spans, which holds that box
        (:attr:`support_note` says so)."""
        if "support" not in self.arrays:
            norm = self.fit.normalization
            half = float(norm.scale) / 2.0
            self.arrays["support"] = np.vstack([np.asarray(norm.center) - half,
                                                np.asarray(norm.center) + half])
            self.support_note = " (a version 1 field: the cube of its normalisation)"
        return self.arrays["support"]

    # --- on a model
    def _regions(self, model: PointModel) -> tuple[np.ndarray, list[np.ndarray]]:
        """(fixed (N,) bool, one (N,) bool per handle) re-evaluated on ``model``; a region with
        an indices selector is the indices the field stores (never a file it names)."""
        from splatdeform.edit.selectors import select, stored

        name = self.path or "field"
        n = model.n_points
        if not self.meta.get("transferable", True):
            same = n == self.meta.get("n_points") and \
                positions_digest(model.positions) == self.meta.get("digest")
            if not same:
                raise InputError(f"{name}: its regions use indices selectors, which do not "
                                 "transfer to another model; apply it to the model it was saved "
                                 "from, or use box/sphere/plane/property selectors")

        def mask(selectors: list, member: str, key: str) -> np.ndarray:
            if member in self.arrays:
                m = np.zeros(n, dtype=bool)
                m[self.arrays[member]] = True
                return m
            sels = stored.decode(selectors, key)
            if stored.has_indices(sels):
                raise InputError(f"field {name}: member {member!r}: missing (its region has an "
                                 "indices selector)")
            return select(model, sels, "model") if sels else np.zeros(n, dtype=bool)

        fixed = mask(self.meta["fixed"], "fixed_idx", "fixed")
        handles = [mask(h["selectors"], f"handle_idx_{j}", f"handles[{j}].selectors")
                   for j, h in enumerate(self.meta["handles"])]
        return fixed, handles

    def deformation(self, model: PointModel, backend: str | None = None):
        """The :class:`~splatdeform.deform.Deformation` of this field on ``model`` (its basis
        deferred: :class:`~splatdeform.basis.oneshot.DeferredBasis`)."""
        from splatdeform.basis.oneshot import deferred_basis
        from splatdeform.deform.deformation import Deformation
        from splatdeform.deform.handle import AffineFrame
        from splatdeform.deform.regions import Group

        fixed, handles = self._regions(model)
        handles = [h & ~fixed for h in handles]  # fixed wins where they overlap on MODEL
        n, k = model.n_points, self.delta_c.shape[0]
        moving = np.zeros(n, dtype=bool)
        for h in handles:
            moving |= h
        moving_idx = np.flatnonzero(moving)
        lookup = np.full(n, -1, dtype=np.int64)
        lookup[moving_idx] = np.arange(moving_idx.size)
        coords = np.zeros((moving_idx.size, k))
        grads = np.zeros((moving_idx.size, k, 3))
        groups = []
        for j, (h, info) in enumerate(zip(handles, self.meta["handles"], strict=True)):
            frame = AffineFrame(self.arrays["frames"][j][:4, :3].copy(),
                                self.arrays["inverses"][j].copy())
            idx = np.flatnonzero(h)
            rows = lookup[idx]
            a, b = info["columns"]
            coords[rows, a:b] = frame.coordinates(model.positions[idx])
            grads[rows, a:b] = frame.coordinate_gradients()
            groups.append(Group(info["name"], (a, b), rows, frame))
        free_idx = np.flatnonzero(~(fixed | moving))
        # deferred: apply evaluates it one-shot, as ``deform`` does (the same bytes)
        basis = deferred_basis(model.positions[free_idx], self.fit, gradients=True,
                               backend=backend or self.meta.get("backend", "auto"))
        empty = np.empty(0, dtype=np.int64)
        return Deformation(n_points=n, fixed=fixed, moving=moving, free_idx=free_idx,
                           moving_idx=moving_idx, moving_coords=coords, moving_gradients=grads,
                           constraint_idx=empty, constraint_points=np.empty((0, 3)),
                           constraint_rhs=np.empty((0, k)), control_points=np.zeros((k, 3)),
                           fit=self.fit, basis=basis, groups=groups)

    def apply(self, model: PointModel, backend: str | None = None,
              support: SupportStats | None = None, split: str | None = None) -> PointModel:
        """The deformed copy of ``model`` (as ``deform`` makes it; see the module);
        ``support``: counts the points the field moves outside :attr:`support` (adds to it);
        ``split``: ``gaussians.split`` (None: the field's own, default ``auto``; a streamed
        apply passes ``off``: chunks keep their row counts)."""
        from splatdeform import deform as df
        from splatdeform.deform.split import DEFAULT_SPLIT

        deformation = self.deformation(model, backend)
        if support is not None:
            support.add(model.positions, deformation.free_idx, self.support)
        matrices = list(self.arrays["matrices"]) if self.meta["handles"] else None
        meta = self.meta.get("gaussians", {})
        return df.apply(deformation, model, self.delta_c, moving_matrix=matrices,
                        covariance=meta.get("covariance", "jacobian"),
                        split=meta.get("split", DEFAULT_SPLIT) if split is None else split)


def field_of_edit(result, cfg, base_dir: Path) -> Field:
    """The field of an in-memory edit result (``deform --save-field``)."""
    from splatdeform.basis import resolve_backend
    from splatdeform.edit.metaphors import Context
    from splatdeform.edit.metaphors.handle import entries as handle_entries
    from splatdeform.edit.selectors.stored import encode, has_indices

    model, deformation = result.model, result.deformation
    if model is None:
        raise InputError("--save-field: the edit streamed; save a field from an in-memory run "
                         "(raise --memory-budget)")
    ctx = Context.of(cfg, model, base_dir)

    def plain(selector_cfgs: list) -> list:
        return [s.to_selector().in_units(ctx.units, ctx.frame) for s in selector_cfgs]

    fixed_sel = plain(cfg.regions.fixed)
    handles, arrays = [], {}
    hgroups = deformation.handle_groups()
    entries = handle_entries(cfg)
    frames, inverses = [], []
    for j, ((_key, entry), group) in enumerate(zip(entries, hgroups, strict=True)):
        sels = plain(entry[1])
        handles.append({"name": group.name, "columns": list(group.columns),
                        "selectors": [encode(sel) for sel in sels]})
        frame = np.zeros((4, 4))
        frame[:4, :3] = group.frame.control_points
        frames.append(frame)
        inverses.append(group.frame.inverse)
        if has_indices(sels):
            arrays[f"handle_idx_{j}"] = deformation.moving_idx[group.rows]
    matrix = result.matrix
    matrices = [] if matrix is None else [matrix] if isinstance(matrix, np.ndarray) and \
        matrix.shape == (4, 4) else list(matrix)
    arrays["frames"] = np.array(frames).reshape(-1, 4, 4)
    arrays["inverses"] = np.array(inverses).reshape(-1, 4, 4)
    arrays["matrices"] = np.array(matrices, dtype=np.float64).reshape(-1, 4, 4)
    arrays["support"] = support_box(deformation.constraint_points, model.positions)
    transferable = not (has_indices(fixed_sel) or any(f"handle_idx_{j}" in arrays
                                                      for j in range(len(handles))))
    if has_indices(fixed_sel):
        arrays["fixed_idx"] = np.flatnonzero(deformation.fixed)
    meta = {"format": FORMAT, "version": VERSION, "fixed": [encode(sel) for sel in fixed_sel],
            "handles": handles, "backend": resolve_backend(cfg.backend, cfg.device),
            "gaussians": cfg.gaussians.model_dump(), "method": deformation.fit.method,
            "transferable": transferable, "input": str(cfg.input)}
    if not transferable:
        meta.update(n_points=model.n_points, digest=positions_digest(model.positions))
    return Field(deformation.fit, np.asarray(result.delta_c, dtype=np.float64), meta, arrays)


def support_box(constraints: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(2, 3) float64, low corner then high corner: the box of the fit's constraint points
    (m, 3) and of the model's points (N, 3) it was fitted on (the box its normalisation
    spans), in model units: where the field was fitted and ``deform`` evaluated it."""
    lows, highs = [], []
    for pts in (constraints, positions):
        pts = np.asarray(pts).reshape(-1, 3)
        if len(pts):
            lows.append(pts.min(axis=0).astype(np.float64))
            highs.append(pts.max(axis=0).astype(np.float64))
    if not lows:
        return np.zeros((2, 3))
    return np.vstack([np.min(lows, axis=0), np.max(highs, axis=0)])
