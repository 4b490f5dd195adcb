"""The editor page's actions over one controller (no web imports): JSON-able requests in,
JSON-able state out. :mod:`.page_server` only moves these over HTTP.

Coordinates in requests and answers are *local* (model minus ``controller.origin``), as the page
draws them. Every change is recorded for undo / redo (:mod:`.history`); a pose drag sends
``pose`` messages (16 floats) and records once when the drag ends (``commit``).

Requests name their action in ``op``; :data:`Session.OPS` is the table of actions (the pair
actions and handle removal come from :mod:`.pairs`; with a current fit, a pair change and its
undo / redo refit at once). The session
changes the controller only through its public methods (selectors, :meth:`~.controller.
EditorController.store_pose`, ``set_curve``, ``set_covariance``, ``set_points``,
``remove_handle``, ``save``; undo through
:mod:`.history`'s ``snapshot`` / ``restore``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..errors import InputError, SplatdeformError
from . import payload
from . import selectors as sl
from .controller import EditorController, check_pose
from .history import History
from .pairs import OPS as _PAIR_OPS
from .security import SaveFolder, default_save_folder
from .state import Snapshot

DEFAULT_SIZE = 0.08  # a new selector: this fraction of the model's diagonal
MAX_NUMBER = 1e15    # the largest magnitude a number in a request may have


def _refuse_constant(name: str) -> float:
    raise InputError(f"request: {name} is not a number; expected finite numbers")


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value) or abs(value) > MAX_NUMBER:
        raise InputError(f"request: number {text[:24]}: expected a finite number of magnitude "
                         f"at most {MAX_NUMBER:g}")
    return value


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > 16 or abs(int(text)) > MAX_NUMBER:
        raise InputError(f"request: number {text[:24]}: expected a whole number of magnitude "
                         f"at most {MAX_NUMBER:g}")
    return int(text)


def parse_request(body: bytes) -> dict[str, Any]:
    """One action request: a JSON object whose numbers are all finite and at most
    :data:`MAX_NUMBER` in magnitude (NaN, Infinity and 1e400 refused with one line)."""
    try:
        req = json.loads(body.decode("utf-8"), parse_constant=_refuse_constant,
                         parse_float=_parse_float, parse_int=_parse_int)
    except UnicodeDecodeError:
        raise InputError("request: expected a UTF-8 JSON body") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"request: invalid JSON ({exc.msg} at character {exc.pos})") from None
    if not isinstance(req, dict):
        raise InputError("request: expected a JSON object")
    return req


def dumps(data: Any) -> bytes:
    """JSON for the page: never NaN or Infinity (ValueError instead: not valid JSON)."""
    return json.dumps(data, allow_nan=False).encode()


def _json_value(v: Any) -> Any:
    """A fit figure for the page: numbers as they are when finite, anything else as text."""
    if isinstance(v, (int, bool, str)) or (isinstance(v, float) and math.isfinite(v)):
        return v
    return str(v)


def _check_numbers(value: Any, key: str) -> None:
    """Every number in ``value`` (nested lists / mappings) finite and at most
    :data:`MAX_NUMBER` in magnitude."""
    if isinstance(value, dict):
        for v in value.values():
            _check_numbers(v, key)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _check_numbers(v, key)
    elif isinstance(value, float) and not (math.isfinite(value) and abs(value) <= MAX_NUMBER):
        raise InputError(f"{key}: expected finite numbers of magnitude at most "
                         f"{MAX_NUMBER:g}, got {value!r}")


class Session:
    """Controller + undo history + what the page needs to know (see the module docstring)."""

    def __init__(self, ed: EditorController, save_folder: SaveFolder | None = None) -> None:
        self.ed = ed
        self.save_folder = save_folder or default_save_folder(ed)
        self._confirm_pending: tuple[str, str, str] | None = None
        self.history = History(ed)
        self.fit_id = 0
        self.last_fit: dict[str, Any] = {}
        self.message = ""
        self._saver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="editor-save")

    # ---- state --------------------------------------------------------------------------
    def _selector_info(self, role: str, h: int, i: int, sel: Any) -> dict[str, Any]:
        shape = sl.shape_of(sel, self.ed.model, self.ed.units)
        return {"role": role, "handle": h, "index": i, "kind": shape.kind,
                "type": type(sel).__name__.lower(),
                "center": [float(v) for v in shape.center - self.ed.origin],
                "size": [float(v) for v in shape.size],
                "normal": [float(v) for v in shape.normal],
                "yaml": sl.to_yaml(sel, self.ed.base_dir)}

    def state(self) -> dict[str, Any]:
        ed = self.ed
        sels = [self._selector_info("fixed", 0, i, s)
                for i, s in enumerate(ed.selectors("fixed"))]
        for h in range(len(ed.handles)):
            sels += [self._selector_info("handle", h, i, s)
                     for i, s in enumerate(ed.selectors("handle", h))]
        fit = None
        if ed.deformation is not None:
            _, control = payload.basis_arrays_meta(ed)
            fit = {"id": self.fit_id, "k": int(ed.deformation.k), "control": control,
                   "stats": {k: _json_value(v) for k, v in self.last_fit.items()}}
        return {
            "selectors": sels, "handles": len(ed.handles), "fit": fit, "stale": ed.stale,
            "curve": self._curve_info(), "points": self._points_info(),
            "covariance": ed.covariance,
            "poses": [payload.model_to_local(ed, ed.pose(h)).tolist()
                      for h in range(len(ed.handles))],
            "counts": ed.counts(), "problem": ed.problem(),
            "can_undo": bool(self.history.undo_stack), "can_redo": bool(self.history.redo_stack),
            "message": self.message,
            "defaults": [p.name for p in ed.default_paths()],
            "save_folder": str(self.save_folder.root),
        }

    def _curve_info(self) -> dict[str, Any] | None:
        """The curve for the page (local coordinates): control points, moved points, settings,
        band size, and the snapped curve's samples with their spline weights (the page draws
        the moved curve as samples + weights . delta)."""
        ed = self.ed
        if ed.curve is None:
            return None
        given, moved, radius = ed.curve.model_points(ed.model, ed.units)
        view = ed.curve_view()
        return {"control": (given - ed.origin).tolist(), "moved": (moved - ed.origin).tolist(),
                "degree": ed.curve.degree, "parametrization": ed.curve.parametrization,
                "capture_radius": radius, "band": int(view.band.sum()),
                "samples": (view.samples - ed.origin).tolist(), "weights": view.weights.tolist(),
                "problem": view.problem, "yaml": ed.curve.to_yaml()}

    def _points_info(self) -> dict[str, Any] | None:
        """The control-point pairs for the page (local coordinates): sources, targets (the
        arrows before), the pair columns' rows of delta C (g I; they come after the handles'
        and the curve's) and, with a current fit, where the field sends each source (after)."""
        ed = self.ed
        if ed.points is None:
            return None
        from splatdeform.deform.points import pair_errors

        from .pairs import model_pairs

        fit = ed.points_fit if not ed.stale else None
        pairs = fit.pairs if fit is not None else model_pairs(ed.points, ed.units, ed.model,
                                                              ed.base_dir)
        info: dict[str, Any] = {"n": pairs.n, "sources": (pairs.sources - ed.origin).tolist(),
                                "targets": (pairs.targets - ed.origin).tolist(),
                                "delta": None, "after": None}
        if fit is not None:
            info["delta"] = fit.delta().tolist()
            moved = pairs.targets + pair_errors(ed.deformation, pairs, ed.delta_c())
            info["after"] = (moved - ed.origin).tolist()
        return info

    # ---- actions ------------------------------------------------------------------------
    def act(self, req: dict[str, Any]) -> dict[str, Any]:
        """Apply one request; returns the new state (``pose`` without ``commit``: {"ok": 1})."""
        op = req.get("op")
        handler = self.OPS.get(op) if isinstance(op, str) else None
        if handler is None:
            raise InputError(f"op: unknown editor action {op!r}")
        self.message = ""
        quick = handler(self, req)
        if quick is not None:
            return quick
        self.history.record()
        return self.state()

    def _center(self, req: dict[str, Any], key: str = "center") -> np.ndarray | None:
        v = req.get(key)
        if v is None:
            return None
        a = np.asarray(v, np.float64)
        if a.shape != (3,) or not np.isfinite(a).all():
            raise InputError(f"{key}: expected 3 finite numbers")
        return a + self.ed.origin

    @staticmethod
    def _size(req: dict[str, Any]) -> np.ndarray | None:
        """``size``: a positive finite number or 3 of them, or None."""
        size = req.get("size")
        if size is None:
            return None
        try:
            a = np.asarray(size, np.float64)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape not in ((), (3,)) or not np.isfinite(a).all() or (a <= 0).any() or \
                (np.abs(a) > MAX_NUMBER).any():
            raise InputError(f"size: expected a positive finite number or 3 of them (at most "
                             f"{MAX_NUMBER:g}), got {str(size)[:80]}")
        return a

    def _checked(self, sel: Any, key: str = "selector") -> Any:
        """``sel`` when every number of it is finite and bounded (the state stays JSON)."""
        _check_numbers(sl.to_yaml(sel, self.ed.base_dir), key)
        shape = sl.shape_of(sel, self.ed.model, self.ed.units)
        _check_numbers([*map(float, shape.center), *map(float, shape.size)], key)
        return sel

    def _op_add_selector(self, req: dict[str, Any]) -> None:
        role, kind, h = req["role"], req["kind"], int(req.get("handle", 0))
        size = self._size(req)
        center = self._center(req)
        index = self.ed.add_selector(role, kind, handle=h, center=center)
        try:
            if kind != "plane":
                if size is None:
                    d = DEFAULT_SIZE * self.ed.model.diagonal()
                    size = np.array([d, d, d] if kind == "box" else d / 2)
                self.ed.move_selector(role, index, size=size, handle=h)
            self._checked(self.ed.selector(role, index, handle=h))
        except Exception:
            self.ed.remove_selector(role, index, handle=h)
            raise

    def _op_add_indices(self, req: dict[str, Any]) -> None:
        """A screen-space selection (rectangle) as an ``indices`` selector."""
        from splatdeform.edit.selectors import Indices

        idx = np.unique(np.asarray(req.get("indices", []), dtype=np.int64))
        if idx.size == 0:
            raise InputError("selection: the rectangle holds no point; drag over the model")
        if idx[0] < 0 or idx[-1] >= self.ed.model.n_points:
            raise InputError(f"indices: expected 0..{self.ed.model.n_points - 1}")
        self.ed.add_selector(req["role"], Indices(tuple(int(i) for i in idx)),
                             handle=int(req.get("handle", 0)))

    def _op_add_selector_text(self, req: dict[str, Any]) -> None:
        """A selector of any kind typed as YAML (all / not nest freely)."""
        sel = sl.from_text(req.get("text", ""), self.ed.model, self.ed.units, self.ed.base_dir)
        self.ed.add_selector(req["role"], self._checked(sel), handle=int(req.get("handle", 0)))

    def _op_set_selector_text(self, req: dict[str, Any]) -> None:
        """Replace selector ``index`` of a region by one typed as YAML."""
        sel = sl.from_text(req.get("text", ""), self.ed.model, self.ed.units, self.ed.base_dir)
        self.ed.set_selector(req["role"], int(req["index"]), self._checked(sel),
                             handle=int(req.get("handle", 0)))

    def _op_move_selector(self, req: dict[str, Any]) -> None:
        size = self._size(req)
        normal = req.get("normal")
        if normal is not None:
            normal = np.asarray(normal, np.float64)
            if normal.shape != (3,) or not np.isfinite(normal).all() or not normal.any():
                raise InputError("normal: expected 3 finite numbers, not all zero")
        role, index, h = req["role"], int(req["index"]), int(req.get("handle", 0))
        before = self.ed.selector(role, index, handle=h)
        moved = self.ed.move_selector(role, index, center=self._center(req), size=size,
                                      normal=normal, handle=h)
        try:
            self._checked(moved, "size")
        except InputError:
            self.ed.set_selector(role, index, before, handle=h)
            raise

    def _op_remove_selector(self, req: dict[str, Any]) -> None:
        self.ed.remove_selector(req["role"], int(req["index"]), handle=int(req.get("handle", 0)))

    def _op_add_handle(self, req: dict[str, Any]) -> None:
        self.ed.add_handle()

    def _op_fit(self, req: dict[str, Any]) -> None:
        self.refit()

    def refit(self) -> None:
        """Fit the current state (the page uploads the new basis: a new ``fit.id``)."""
        self.last_fit = self.ed.fit()
        self.fit_id += 1

    def _op_pose(self, req: dict[str, Any]) -> dict[str, Any] | None:
        h = int(req.get("handle", 0))
        self.ed.pose(h)  # the handle exists
        key = f"handle {h}: pose ({self.ed.pose_key(h)})"
        try:
            m = np.asarray(req["matrix"], np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise InputError(f"{key}: expected a 4x4 matrix (16 numbers)") from None
        if self.ed.stale:
            raise InputError("fit: the regions changed since the last fit (or there is none); "
                             "fit again before moving the handle")
        self.ed.store_pose(check_pose(payload.local_to_model(self.ed, check_pose(m, key)), key),
                           h)
        return None if req.get("commit") else {"ok": 1}

    # ---- the curve ----------------------------------------------------------------------
    def _curve(self):
        if self.ed.curve is None:
            raise InputError("curve: there is none; click control points on the model first")
        return self.ed.curve

    def _op_add_curve_point(self, req: dict[str, Any]) -> None:
        """A control point at the picked point (the first one starts the curve)."""
        from .curve import CurveState

        at = self._center(req)
        if at is None:
            raise InputError("center: expected 3 finite numbers")
        ed = self.ed
        ed.set_curve(CurveState.new(ed.model, ed.units, at) if ed.curve is None
                     else ed.curve.appended(ed.model, ed.units, at))

    def _op_move_curve_point(self, req: dict[str, Any]) -> dict[str, Any] | None:
        """Control point ``index`` to ``center``; ``moved``: its moved_to (the pose, needs a
        current fit; without ``commit`` a drag step, not recorded), else the point itself."""
        curve, index = self._curve(), int(req["index"])
        at = self._center(req)
        if at is None:
            raise InputError("center: expected 3 finite numbers")
        moved = bool(req.get("moved"))
        if moved and self.ed.stale:
            raise InputError("fit: the regions changed since the last fit (or there is none); "
                             "fit again before moving the curve")
        self.ed.set_curve(curve.with_point(self.ed.model, self.ed.units, index, at,
                                           moved=moved))
        return None if (not moved or req.get("commit")) else {"ok": 1}

    def _op_remove_curve_point(self, req: dict[str, Any]) -> None:
        self.ed.set_curve(self._curve().without(int(req["index"])))

    def _op_remove_curve(self, req: dict[str, Any]) -> None:
        self.ed.set_curve(None)

    def _op_curve_settings(self, req: dict[str, Any]) -> None:
        """capture_radius (model units), degree, parametrization: any of them."""
        self.ed.set_curve(self._curve().with_settings(
            self.ed.model, self.ed.units, capture_radius=req.get("capture_radius"),
            degree=req.get("degree"), parametrization=req.get("parametrization")))

    def _op_reset_curve(self, req: dict[str, Any]) -> None:
        self.ed.set_curve(self._curve().reset())

    def _op_covariance(self, req: dict[str, Any]) -> None:
        """``gaussians.covariance`` of the edit (jacobian | rotation | limited): what the page's
        vertex stage draws and what Save writes (the fit does not depend on it)."""
        mode = req.get("mode")
        self.ed.set_covariance(mode)
        self.message = f"gaussians.covariance: {mode}"

    def _op_reset_pose(self, req: dict[str, Any]) -> None:
        self.ed.reset_pose(int(req.get("handle", 0)))

    def _op_undo(self, req: dict[str, Any]) -> dict[str, Any]:
        self._step(self.history.undo)
        return self.state()

    def _op_redo(self, req: dict[str, Any]) -> dict[str, Any]:
        self._step(self.history.redo)
        return self.state()

    def _step(self, move: Callable[[], bool]) -> None:
        """Undo or redo; a step that changed only the pairs of a current fit refits, as the
        pair actions do (a refused refit leaves the fit stale, with its line as the message)."""
        live, before = not self.ed.stale, self.ed.snapshot()
        if not move() or not live or not self.ed.stale:
            return
        after = self.ed.snapshot()
        if after.points is not None and after.points != before.points and \
                Snapshot(before.fixed, before.handles, before.curve, before.covariance,
                         after.points).same(after):
            try:
                self.refit()
            except SplatdeformError as exc:
                self.message = f"{exc} (Fit again after fixing it)"

    def _op_save(self, req: dict[str, Any]) -> dict[str, Any]:
        """Save under the file *names* typed in the page, into the save folder (never a path,
        never an input). An existing file is replaced only when the page repeats the same
        names with ``replace`` after the user confirmed (the state's ``confirm`` lists them)."""
        names = tuple(str(req.get(k) or "") for k in ("model", "yaml", "png"))
        replace = bool(req.get("replace")) and self._confirm_pending == names
        self._confirm_pending = None
        paths = self.save_folder.save_targets(*names)  # the PNG's camera file too
        if self.ed.stale:
            raise InputError("fit: the regions changed since the last fit (or there is none);"
                             " fit again before saving")
        self.ed.check_poses()
        existing = self.save_folder.existing(paths)
        if existing and not replace:
            self._confirm_pending = names
            self.message = ("exists already: " + ", ".join(p.name for p in existing)
                            + "; press Replace to overwrite, or change the names")
            return {**self.state(), "confirm": [p.name for p in existing]}
        result = self.save(*paths[:3])
        self.message = "wrote " + ", ".join(p.name for p in
                                            (result.model, result.config, result.image) if p)
        return self.state()

    def save(self, model: Path, config: Path, image: Path):
        """The controller's save (the PNG at ``render.size`` when the YAML has one), always on
        the session's one save thread: the page's server answers each request on a new
        thread, and an OpenGL context serves only the thread that made it (a second Save
        failed with "cannot create renderbuffer"); one thread keeps one context."""
        return self._saver.submit(self.ed.save, model, config, image).result()

    # ---- arrays -------------------------------------------------------------------------
    def labels(self) -> np.ndarray:
        return self.ed.labels()

    def basis(self) -> np.ndarray:
        if self.ed.deformation is None:
            raise InputError("fit: no fit yet")
        return payload.basis_arrays(self.ed)[0]

    # ---- the actions' table: op -> handler(session, request) ------------------------------
    OPS: ClassVar[dict[str, Callable[[Session, dict[str, Any]], dict[str, Any] | None]]] = {
        "add_selector": _op_add_selector, "add_indices": _op_add_indices,
        "add_selector_text": _op_add_selector_text, "set_selector_text": _op_set_selector_text,
        "move_selector": _op_move_selector, "remove_selector": _op_remove_selector,
        "add_handle": _op_add_handle, "fit": _op_fit, "pose": _op_pose,
        "reset_pose": _op_reset_pose, "add_curve_point": _op_add_curve_point,
        "move_curve_point": _op_move_curve_point, "remove_curve_point": _op_remove_curve_point,
        "remove_curve": _op_remove_curve, "curve_settings": _op_curve_settings,
        "reset_curve": _op_reset_curve, "covariance": _op_covariance, "undo": _op_undo,
        "redo": _op_redo, "save": _op_save, **_PAIR_OPS,
    }


def error_line(exc: Exception) -> str:
    """The one line the page shows for a failed action."""
    if isinstance(exc, SplatdeformError):
        return str(exc)
    if isinstance(exc, (KeyError, TypeError, ValueError)):
        return f"bad request: {type(exc).__name__}: {exc}"
    return f"internal error: {type(exc).__name__}: {exc}"
