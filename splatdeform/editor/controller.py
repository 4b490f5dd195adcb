"""The editor's logic as a plain Python object: no web imports, usable from a notebook.

State: the model, the fixed region and a list of handles (each a list of selectors and its
current 4x4 pose), the fit settings, the precomputed deformation and whether it is stale.
Actions: add / move / resize / remove selectors, :meth:`EditorController.fit`,
:meth:`EditorController.set_pose` (delta_c applied to the precomputed basis, the per-frame path:
:mod:`.frames`) and :meth:`EditorController.save` (deformed model, edit YAML, before/after PNG:
:mod:`.saving`). The state changes only through these public methods (also
:meth:`~EditorController.store_pose`, ``set_covariance``, ``set_points``, ``remove_handle``,
:meth:`~EditorController.snapshot` / :meth:`~EditorController.restore` for undo). Everything
goes through the same pipeline as ``splatdeform deform``: the config models
(:mod:`splatdeform.edit.config`), :func:`splatdeform.edit.precompute` for rings, fit and basis, and
:func:`splatdeform.deform.apply` for the saved model, so the saved YAML reproduces the saved model
byte for byte. One or more handles (``handles:`` in the YAML when there are several): one
fit, one basis, one 4x4 pose per handle; and/or a curve (:mod:`.curve`, ``curve:``), whose pose
is its moved control points. Example: :class:`EditorController` (run as a doctest).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.deform.handle import delta_for_transform
from splatdeform.deform.regions import check_regions
from splatdeform.edit.config import EditConfig, load_edit, parse_edit
from splatdeform.edit.selectors import Selector, select

from .. import deform as df
from ..errors import InputError, RegionError
from ..model import PointModel
from . import frames, saving
from . import selectors as sl
from .curve import CurveState, CurveView, curve_view
from .frames import Frame
from .saving import SaveResult
from .state import (
    FIXED,
    HANDLE,
    MAX_HANDLES,
    MAX_SELECTORS,
    HandleState,
    Snapshot,
    StaleFitError,
    check_pose,
)


class EditorController:
    """Editor state and actions over one model (see the module docstring).

    model: the loaded model (never modified). base_dir: the folder paths in the config are
    relative to. config: the edit's other settings (boundary, fit, normals, backend, device,
    render) as an :class:`EditConfig`; its regions and handle are rebuilt from the editor state
    by :meth:`to_config`. model_path: the input file. config_path: the EDIT.yaml it came from.

    Examples
    --------
    >>> from splatdeform import Box, compose_transform, editor, save
    >>> from data_tools.synth import bumpy_bar
    >>> ed = editor.EditorController.open(save(bumpy_bar(2000), "bar.ply"))
    >>> ed.settings.backend = "numpy"                # the basis on the CPU
    >>> _ = ed.add_selector("fixed", Box((-1, -1, -1), (1, 1, 1)))
    >>> _ = ed.add_selector("handle", Box((3, -1, -1), (5, 1, 1)))
    >>> stats = ed.fit()                             # rings, fit and basis, once
    >>> frame = ed.set_pose(compose_transform(pivot=(4, 0, 0), translate=(0, 0.5, 0)))
    >>> stats["converged"], ed.save(image=False).config.name   # and bar_edited.ply
    (True, 'bar_edit.yaml')
    """

    def __init__(self, model: PointModel, *, model_path: str | Path, base_dir: str | Path,
                 config: EditConfig | None = None, config_path: str | Path | None = None,
                 units: str = "model") -> None:
        self.model = model
        self.model_path = Path(model_path).resolve()
        self.base_dir = Path(base_dir).resolve()
        self.config_path = None if config_path is None else Path(config_path).resolve()
        self.units = units
        self.fixed: list[Selector] = []
        self.handles: list[HandleState] = [HandleState()]
        self.curve: CurveState | None = None  # a curve edit (``curve:``), with or without handles
        self.points: Any = None      # ``points:`` pairs as loaded (arrows; fitted with the rest)
        self.points_fit: Any = None  # the last fit's PointsFit (pairs in model units, g)
        self._curve_cache: tuple[Any, CurveView] | None = None
        self.settings = config if config is not None else parse_edit(
            saving.bare_settings(self.model_path), str(self.model_path))
        lo, hi = model.bbox()
        self.origin = (lo + hi) / 2.0
        self.deformation: df.Deformation | None = None
        self.fit_stats: dict[str, Any] = {}
        self._fit_key: Any = None
        self._frame_data: dict[str, Any] | None = None
        self._masks_cache: tuple[Any, tuple[np.ndarray, list[np.ndarray]]] | None = None

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | Path) -> EditorController:
        """From a model file (empty regions) or an edit YAML (its regions and handle pose)."""
        path = Path(path)
        if path.suffix.lower() in (".yaml", ".yml"):
            return cls.from_config(path)
        from splatdeform.edit.run import prepare_model

        settings = parse_edit(saving.bare_settings(path.resolve()), str(path))
        model = prepare_model(settings, path.resolve().parent, {})
        return cls(model, model_path=path, base_dir=path.resolve().parent, config=settings)

    @classmethod
    def from_config(cls, path: str | Path) -> EditorController:
        """Load an edit YAML (handles, a curve, or both) into the editor state."""
        from splatdeform.edit.plain import transform_matrix
        from splatdeform.edit.run import prepare_model

        path = Path(path)
        cfg = load_edit(path)
        base = path.resolve().parent
        model = prepare_model(cfg, base, {})
        ed = cls(model, model_path=base / cfg.input, base_dir=base, config=cfg,
                 config_path=path, units=cfg.regions.units)
        ed.fixed = [s.to_selector() for s in cfg.regions.fixed]
        from splatdeform.edit.metaphors import handle as handle_kind

        # (key, handle config, region selectors) of every handle (none for a curve alone)
        entries = [(key, h, region) for key, (h, region, _) in handle_kind.entries(cfg)]
        ed.handles = [HandleState([s.to_selector() for s in region])
                      for _, _, region in entries] or [HandleState()]
        ed.curve = None if cfg.curve is None else CurveState.from_config(cfg.curve)
        ed.points = cfg.points
        masks = ed.masks()[1][:len(entries)]
        for (key, h, _), state, mask in zip(entries, ed.handles[:len(entries)], masks,
                                            strict=True):
            if mask.any() or h.matrix is not None:  # a centroid pivot needs points
                try:
                    state.matrix = transform_matrix(h, key, cfg.regions.units, model, mask)
                except InputError as exc:
                    raise type(exc)(f"{path}: {exc}") from exc
        return ed

    # ---- regions -----------------------------------------------------------------------
    def _region(self, role: str, handle: int = 0) -> list[Selector]:
        if role == "fixed":
            return self.fixed
        if role == "handle":
            if not 0 <= handle < len(self.handles):
                raise InputError(f"handle: expected an index below {len(self.handles)}, got "
                                 f"{handle}")
            return self.handles[handle].selectors
        raise InputError(f"role: expected 'fixed' or 'handle', got {role!r}")

    def selectors(self, role: str, handle: int = 0) -> tuple[Selector, ...]:
        """The selectors of the fixed region or of handle ``handle`` (a copy)."""
        return tuple(self._region(role, handle))

    def selector(self, role: str, index: int, *, handle: int = 0) -> Selector:
        """Selector ``index`` of a region (InputError naming the region when there is none)."""
        region = self._region(role, handle)
        self._check_index(region, role, index)
        return region[index]

    def add_selector(self, role: str, selector: Selector | str, *, handle: int = 0,
                     center=None) -> int:
        """Append a selector to the fixed region or to handle ``handle``; a kind name
        ("box", "sphere", "plane") makes a default one at ``center`` (model coordinates).
        Returns its index in that region."""
        region = self._region(role, handle)
        total = len(self.fixed) + sum(len(h.selectors) for h in self.handles)
        if total >= MAX_SELECTORS:
            raise InputError(f"selectors: at most {MAX_SELECTORS} in one edit (fixed and "
                             "handles together); remove some, or combine them with all/not")
        if isinstance(selector, str):
            selector = sl.default_selector(selector, self.model, self.units, center=center)
        region.append(selector)
        return len(region) - 1

    def set_selector(self, role: str, index: int, selector: Selector, *,
                     handle: int = 0) -> None:
        """Replace selector ``index`` of a region."""
        region = self._region(role, handle)
        self._check_index(region, role, index)
        region[index] = selector

    def move_selector(self, role: str, index: int, *, center=None, size=None, normal=None,
                      handle: int = 0) -> Selector:
        """Move / resize selector ``index``: new model-space centre (3,), size (box extent (3,)
        or sphere radius), plane normal (3,). Returns the new selector."""
        region = self._region(role, handle)
        self._check_index(region, role, index)
        if size is not None and np.ndim(size) == 0:
            size = np.full(3, float(size))
        region[index] = sl.with_shape(region[index], self.model, self.units, center=center,
                                      size=size, normal=normal)
        return region[index]

    def resize_selector(self, role: str, index: int, factor: float, *, handle: int = 0
                        ) -> Selector:
        """Scale selector ``index`` about its centre by ``factor`` (> 0)."""
        if not factor > 0:
            raise InputError(f"factor: expected a positive number, got {factor}")
        shape = self.shape(role, index, handle=handle)
        return self.move_selector(role, index, size=shape.size * factor, handle=handle)

    def remove_selector(self, role: str, index: int, *, handle: int = 0) -> None:
        region = self._region(role, handle)
        self._check_index(region, role, index)
        del region[index]

    def shape(self, role: str, index: int, *, handle: int = 0) -> sl.Shape:
        """Model-space shape of selector ``index`` (for gizmos and outlines)."""
        region = self._region(role, handle)
        self._check_index(region, role, index)
        return sl.shape_of(region[index], self.model, self.units)

    @staticmethod
    def _check_index(region: list, role: str, index: int) -> None:
        if not 0 <= index < len(region):
            raise InputError(f"{role}: no selector {index} (the region has {len(region)})")

    def _regions_key(self) -> tuple:
        return (self.units, tuple(self.fixed), tuple(tuple(h.selectors) for h in self.handles),
                None if self.curve is None else self.curve.basis_key(),
                None if self.points is None else self.points.model_dump_json())

    def live_handles(self) -> list[HandleState]:
        """The handles the edit has: all of them, except the one empty handle of a curve edit
        (a curve or pairs alone have no handle columns)."""
        if (self.curve is not None or self.points is not None) and len(self.handles) == 1 \
                and not self.handles[0].selectors:
            return []
        return self.handles

    def curve_view(self) -> CurveView | None:
        """The curve's band and drawn samples (cached per curve), or None without a curve."""
        if self.curve is None:
            return None
        key = (self.units, self.curve.basis_key())
        if self._curve_cache is None or self._curve_cache[0] != key:
            self._curve_cache = (key, curve_view(self.curve, self.model, self.units))
        return self._curve_cache[1]

    def set_curve(self, curve: CurveState | None) -> None:
        """Replace the curve (None: no curve)."""
        self.curve = curve

    def set_points(self, points: Any) -> None:
        """Replace the ``points:`` config (a new PointsCfg; None: no pairs)."""
        self.points = points

    def _moving(self) -> np.ndarray:
        """(N,) bool: the live handles' points and the curve band."""
        _, handles = self.masks()
        live = handles[:len(self.live_handles())]
        view = self.curve_view()
        parts = live + ([view.band] if view is not None else [])
        return np.logical_or.reduce(parts) if parts else np.zeros(self.model.n_points, bool)

    def masks(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """(fixed (N,) bool, [handle (N,) bool per handle]) for the current selectors."""
        key = self._regions_key()
        if self._masks_cache is not None and self._masks_cache[0] == key:
            return self._masks_cache[1]
        fixed = select(self.model, self.fixed, self.units, self.base_dir)
        handles = [select(self.model, h.selectors, self.units, self.base_dir)
                   for h in self.handles]
        self._masks_cache = (key, (fixed, handles))
        return fixed, handles

    def labels(self) -> np.ndarray:
        """(N,) uint8: 0 free, 1 fixed, 2 + i handle i, 2 + (number of live handles) the
        curve band (a point in both shows as fixed)."""
        fixed, handles = self.masks()
        out = np.zeros(self.model.n_points, dtype=np.uint8)
        view = self.curve_view()
        if view is not None:
            out[view.band] = HANDLE + len(self.live_handles())
        for i in reversed(range(len(handles))):
            out[handles[i]] = HANDLE + i
        out[fixed] = FIXED
        return out

    def counts(self) -> dict[str, int]:
        """Point counts: fixed, handle (all handles), free, overlap (in both)."""
        fixed, _ = self.masks()
        moving = self._moving()
        return {"fixed": int(fixed.sum()), "handle": int(moving.sum()),
                "free": int((~(fixed | moving)).sum()), "overlap": int((fixed & moving).sum())}

    def problem(self) -> str | None:
        """The error a fit would stop on for the regions alone (empty, overlapping, no free
        region), as the one line the CLI prints; None when the regions look fine."""
        try:
            self._check_regions()
        except InputError as exc:
            return str(exc)
        return None

    def _check_regions(self) -> None:
        """The region checks ``precompute`` makes before the rings, with its messages (empty,
        collinear or overlapping regions, no free region)."""
        from splatdeform.deform.regions import check_metaphor
        from splatdeform.edit.plain import metaphors

        fixed, handles = self.masks()
        if not fixed.any() and self.points is None:  # pairs need no fixed region
            check_regions(fixed, fixed)  # the CLI's line for an empty fixed region
        view = self.curve_view()
        if view is not None and view.problem is not None:
            raise InputError(view.problem)
        for i, state in enumerate(self.live_handles()):
            if not state.selectors:  # no YAML can say this; the line for an empty region
                one = len(self.handles) == 1
                raise RegionError.at("regions.handle" if one else f"handles[{i}].region",
                                     "selects no point; widen " +
                                     ("the handle region" if one else "it"))
        for mph in metaphors(self.to_config(), self.model, self.base_dir):
            check_metaphor(fixed, mph, self.model.n_points)
        if self.points is None:  # pairs: the fit's own checks (points.check_pairs)
            check_regions(fixed, self._moving())

    def add_handle(self, selectors: list[Selector] | None = None) -> int:
        """A new handle (its own region and pose; one fit for all). Returns its index."""
        if len(self.handles) >= MAX_HANDLES:
            raise InputError(f"handles: at most {MAX_HANDLES} in one edit")
        self.handles.append(HandleState(list(selectors or [])))
        return len(self.handles) - 1

    def remove_handle(self, handle: int) -> None:
        self._region("handle", handle)
        if len(self.handles) == 1:
            raise InputError("handles: an edit needs at least one handle")
        del self.handles[handle]

    # ---- fit and pose ------------------------------------------------------------------
    def _settings_key(self) -> tuple:
        s = self.settings
        return (s.boundary.model_dump_json(), s.fit.model_dump_json(), s.normals, s.backend,
                s.device)

    @property
    def stale(self) -> bool:
        """True when there is no fit or the regions / fit settings changed since it."""
        return self.deformation is None or self._fit_key != (self._regions_key(),
                                                              self._settings_key())

    def fit(self, progress: Callable[[str, float], None] | None = None) -> dict[str, Any]:
        """Rings, fit and basis for the current regions (``splatdeform.edit.precompute``).
        ``progress(stage, fraction)`` is called as stages start. Returns the figures shown
        (counts, centers, residual, seconds per stage). Region errors are the CLI's lines."""
        from splatdeform.edit.result import fit_stats

        report = progress or (lambda stage, fraction: None)
        report("regions", 0.0)
        self._check_regions()
        cfg = self.to_config()
        key = (self._regions_key(), self._settings_key())
        report("rings, fit and basis", 0.1)
        t0 = time.perf_counter()
        deformation, points_fit = saving.precompute(cfg, self.model, self.base_dir)
        report("viewer buffers", 0.9)
        self.deformation, self.points_fit = deformation, points_fit
        self._fit_key = key
        self._frame_data = frames.prepare(self.model, deformation, self.origin)
        self.fit_stats = {
            **fit_stats(deformation, self.model.n_points, deformation.free_idx.size),
            "seconds": time.perf_counter() - t0,
            **{f"{k}_s": v for k, v in deformation.timings.items()},
        }
        report("done", 1.0)
        return dict(self.fit_stats)

    def base_frame(self) -> Frame:
        """The undeformed model as a :class:`Frame` (what the viewer shows before a fit)."""
        return frames.base_frame(self.model, self.origin)

    def delta_c(self) -> np.ndarray:
        """delta_c (k, 3) of the current poses: T_h(C_h) - C_h for every handle h, stacked
        (needs a fit: C_h are the fit's handle frames)."""
        if self.deformation is None:
            raise StaleFitError("fit: no fit yet; fit the regions first")
        groups = self.deformation.handle_groups()
        parts = [delta_for_transform(g.frame.control_points, h.matrix)
                 for g, h in zip(groups, self.live_handles(), strict=True)]
        if self.curve is not None:
            given, moved, _ = self.curve.model_points(self.model, self.units)
            parts.append(moved - given)
        if self.points_fit is not None:  # the pairs' columns come last: g I
            parts.append(self.points_fit.delta())
        return np.vstack(parts)

    def set_pose(self, matrix: np.ndarray, handle: int = 0, *, full: bool = True) -> Frame:
        """Set handle ``handle``'s pose (4, 4) affine and deform: delta_c applied to the
        precomputed basis (:func:`splatdeform.deform.arrays.deform_frame`); returns the new
        positions and normals / axes / covariances of all points, or with ``full=False`` of the
        non-fixed points only (``frame.index``; the viewer's fast path). Raises StaleFitError
        when the fit is stale (:meth:`store_pose`'s checks)."""
        self.store_pose(matrix, handle)
        t0 = time.perf_counter()
        return frames.deform(self._frame_data, self.delta_c(), full=full, t0=t0)

    def pose(self, handle: int = 0) -> np.ndarray:
        """Handle ``handle``'s pose: a copy of its (4, 4) model-space matrix."""
        self._region("handle", handle)
        return self.handles[handle].matrix.copy()

    def store_pose(self, matrix: np.ndarray, handle: int = 0) -> None:
        """Set handle ``handle``'s pose (4, 4) without deforming (the page deforms on its GPU);
        the checks of :meth:`set_pose` (a bad matrix: InputError; a stale fit:
        StaleFitError)."""
        m4 = check_pose(matrix, self.pose_key(handle))
        if self.stale:
            raise StaleFitError("fit: the regions changed since the last fit (or there is none);"
                                " fit again before moving the handle")
        self._region("handle", handle)
        self.handles[handle].matrix = m4.copy()

    def pose_key(self, handle: int) -> str:
        """The YAML key of handle ``handle``'s pose (``handle.matrix``, ``handles[i].matrix``)."""
        one = self.curve is None and len(self.handles) == 1
        return "handle.matrix" if one else f"handles[{handle}].matrix"

    def check_poses(self) -> None:
        """Every live handle's pose passes :func:`check_pose` (InputError naming the first
        that does not)."""
        for i, h in enumerate(self.live_handles()):
            check_pose(h.matrix, self.pose_key(i))

    def reset_pose(self, handle: int = 0) -> None:
        """Back to the identity pose (no deformation)."""
        self._region("handle", handle)
        self.handles[handle].matrix = np.eye(4)

    @property
    def covariance(self) -> str:
        """``gaussians.covariance`` of the edit (jacobian | rotation | limited)."""
        return self.settings.gaussians.covariance

    def set_covariance(self, mode: str) -> None:
        """Set ``gaussians.covariance``: what Save writes and the viewer draws (the fit does not
        depend on it). InputError for another mode."""
        from splatdeform.deform.gaussians import COVARIANCE_MODES

        if mode not in COVARIANCE_MODES:
            raise InputError(f"gaussians.covariance: expected one of "
                             f"{', '.join(COVARIANCE_MODES)}, got {mode!r}")
        self.settings.gaussians.covariance = mode

    # ---- undo ---------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """The editable state as a value (for undo / redo: :mod:`.history`)."""
        return Snapshot(tuple(self.fixed),
                        tuple((tuple(h.selectors), h.matrix.copy()) for h in self.handles),
                        self.curve, self.covariance, self.points)

    def restore(self, snap: Snapshot) -> None:
        """Back to ``snap``'s state. When its regions match the last fit's, that fit is
        current again (the fit compares region keys)."""
        self.fixed = list(snap.fixed)
        self.handles = [HandleState(list(s), m.copy()) for s, m in snap.handles]
        self.curve = snap.curve
        self.settings.gaussians.covariance = snap.covariance
        self.points = snap.points

    # ---- config and save ---------------------------------------------------------------
    def to_config(self, *, output: str | Path | None = None,
                  config_dir: str | Path | None = None) -> EditConfig:
        """The edit config of the current state: regions in the editor's units, the handle pose
        as ``matrix`` rows, the backend as configured (``auto`` unless one was chosen). Paths
        are relative to ``config_dir``
        (default: the editor's base folder) when they are inside it."""
        return parse_edit(self.to_yaml_dict(output=output, config_dir=config_dir),
                          "editor state")

    def to_yaml_dict(self, *, output: str | Path | None = None,
                     config_dir: str | Path | None = None) -> dict[str, Any]:
        """The edit config mapping (what :meth:`save` writes as YAML; :mod:`.saving`)."""
        return saving.to_yaml_dict(self, output=output, config_dir=config_dir)

    def default_paths(self) -> tuple[Path, Path, Path]:
        """(model, yaml, png) Save writes by default (:func:`.saving.default_paths`)."""
        return saving.default_paths(self)

    def deformed_model(self) -> PointModel:
        """The deformed model exactly as ``splatdeform deform`` computes it for
        :meth:`to_config` (:func:`.saving.deformed_model`)."""
        return saving.deformed_model(self)

    def save(self, model_path: str | Path | None = None, config_path: str | Path | None = None,
             image_path: str | Path | None = None, *, image: bool = True,
             image_size: tuple[int, int] | None = None) -> SaveResult:
        """Write the deformed model, the edit YAML that reproduces it through ``splatdeform
        deform`` and (``image``) a before/after PNG (:func:`.saving.save`; defaults:
        :meth:`default_paths`)."""
        return saving.save(self, model_path, config_path, image_path, image=image,
                           image_size=image_size)
