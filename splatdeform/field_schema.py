"""A saved field file is untrusted input: its schema, and the one reader that checks it.

Members (``.npy`` in the ``.npz``; nothing else is read, pickles never):

=================  =====================  ==================================================
member             dtype                  shape
=================  =====================  ==================================================
``centers``        float64 / float32      (n, 3), n <= :data:`MAX_CENTERS`
``weights``        float64 / float32      (4 + n, k), k <= :data:`MAX_COLUMNS`
``norm_center``    float64 / float32      (3,)
``norm_scale``     float64 / float32      () positive
``delta_c``        float64 / float32      (k, 3)
``frames``         float64 / float32      (h, 4, 4): rows 0..3, columns 0..2 a handle's frame
``inverses``       float64 / float32      (h, 4, 4): the inverse of [frame^T; 1]
``matrices``       float64 / float32      (h, 4, 4) affine (last row 0 0 0 1), non-singular
``support``        float64 / float32      (2, 3): the box of the constraints and fitted model
``fixed_idx``      int64 / int32          (m,) in 0..n_points-1 (indices regions only)
``handle_idx_<j>`` int64 / int32          (m,) likewise, j < h
``meta``           unicode                () JSON, at most :data:`MAX_META_CHARS`
=================  =====================  ==================================================

with h handles (at most :data:`MAX_HANDLES`), every float finite and within :data:`BOUNDS`.
The size bounds are what a ``deform`` can make: ``fit.max_centers`` is at most 20,000 (the
exact fit 12,000), and an edit has at most 32 handles of 4 columns, one curve of at most 128
control points and 3 columns for ``points:`` (259); :data:`MAX_COLUMNS` leaves room for the
editor's 64 handles. Beyond them the evaluation alone would cost minutes and gigabytes on a
modest model (200,000 centers on a 90,000-point model ran past a minute).

``meta`` (JSON) holds exactly: ``format``, ``version``, ``fixed`` (stored selectors,
:mod:`splatdeform.edit.selectors.stored`), ``handles`` (each ``name``, ``columns`` [a, a + 4]
in order within 0..k, ``selectors``), ``backend``, ``gaussians``, ``method``,
``transferable``, ``input`` (a note, never opened) and, for indices regions, ``n_points`` and
``digest``. Version 1 fields (selectors stored by class name, no ``support``) are read by a
translation of the names that version wrote; their support is the box of their centers.

Every refusal is one :class:`~splatdeform.errors.FormatError` line naming the file and the
member: ``field F.npz: member 'centers': expected float64 (n, 3), got complex128 (5, 3)``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.errors import FormatError

FORMAT = "splatdeform-field"
VERSION = 2  # 2: selectors by kind name, indices only as arrays, the support box
READS = (1, 2)
MAX_FIELD_BYTES = 512 * 2**20  # the file (an indices field of a 60M-point model fits)
MAX_CENTERS = 20_000  # fit.max_centers' largest value
MAX_COLUMNS = 512  # 64 handles x 4 + 128 curve control points + 3 (points:), rounded up
MAX_HANDLES = 64  # the editor's largest edit (a config has at most 32)
MAX_META_CHARS = 2 * 2**20  # the JSON meta
MAX_MEMBERS = 12 + MAX_HANDLES
FLOATS = (np.dtype(np.float64), np.dtype(np.float32))
INTS = (np.dtype(np.int64), np.dtype(np.int32))
MAX_POINTS = 2**40  # a model's point count, as the meta may state it
#: largest magnitudes: centers are normalised by the fitted model's box (pairs may lie half a
#: diagonal outside it), model coordinates stay within what the LAS reader takes (1e15)
BOUNDS = {"centers": 1e3, "norm_center": 1e15, "norm_scale": 1e16, "support": 1e15,
          "frames": 1e15, "matrices": 1e15}
_BACKENDS = ("auto", "numpy", "opencl")
_METHOD = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")
_DIGEST = re.compile(r"^[0-9a-f]{64}$")
META_KEYS = {"format", "version", "fixed", "handles", "backend", "gaussians", "method",
             "transferable", "input", "n_points", "digest"}


_HANDLES = f"(h, 4, 4) with h <= {MAX_HANDLES}"


def _square(s: tuple) -> bool:
    return len(s) == 3 and s[1:] == (4, 4) and s[0] <= MAX_HANDLES


#: member -> (what it must be, in words; the shape test on the header alone)
_SHAPES = {
    "centers": (f"(n, 3) with n <= {MAX_CENTERS}",
                lambda s: len(s) == 2 and s[1] == 3 and s[0] <= MAX_CENTERS),
    "weights": (f"(4 + n, k) with k <= {MAX_COLUMNS}",
                lambda s: len(s) == 2 and 4 <= s[0] <= MAX_CENTERS + 4
                and 1 <= s[1] <= MAX_COLUMNS),
    "norm_center": ("(3,)", lambda s: s == (3,)),
    "norm_scale": ("()", lambda s: s == ()),
    "delta_c": (f"(k, 3) with 1 <= k <= {MAX_COLUMNS}",
                lambda s: len(s) == 2 and s[1] == 3 and 1 <= s[0] <= MAX_COLUMNS),
    "frames": (_HANDLES, _square),
    "inverses": (_HANDLES, _square),
    "matrices": (_HANDLES, _square),
    "support": ("(2, 3)", lambda s: s == (2, 3)),
}
REQUIRED = ("centers", "weights", "norm_center", "norm_scale", "delta_c", "frames", "inverses",
            "matrices", "meta")
_INDEX = re.compile(r"^(fixed_idx|handle_idx_(0|[1-9][0-9]?))$")


def _allowed(name: str) -> bool:
    return name in _SHAPES or name == "meta" or _INDEX.match(name) is not None


def _header(label: str):
    def check(name: str, shape: tuple, dtype: np.dtype) -> None:
        where = f"{label}: member {name!r}"
        got = f"{dtype} {shape}"
        if name == "meta":
            if dtype.kind != "U" or shape != () or dtype.itemsize // 4 > MAX_META_CHARS:
                raise FormatError(f"{where}: expected one JSON string of at most "
                                  f"{MAX_META_CHARS:,} characters, got {got}")
            return
        if name in _SHAPES:
            words, ok = _SHAPES[name]
            if dtype.newbyteorder("=") not in FLOATS or not ok(shape):
                raise FormatError(f"{where}: expected float64 or float32 {words}, got {got}")
            return
        if dtype.newbyteorder("=") not in INTS or len(shape) != 1:
            raise FormatError(f"{where}: expected int64 point indices (m,), got {got}")
    return check


def read_field(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, meta) of a field file, every member and key checked (see the module); arrays
    float64 (indices int64), meta in this version's form. FormatError naming the member."""
    from splatdeform.io.npz import read_npz

    path = Path(path)
    label = f"field {path}"
    data = read_npz(path, label=label, max_bytes=MAX_FIELD_BYTES, max_members=MAX_MEMBERS,
                    allowed=_allowed, header=_header(label), what="field file")
    missing = [m for m in REQUIRED if m not in data]
    if "meta" in missing:
        raise FormatError(f"{label}: member 'meta': missing; not a field file written by "
                          "deform --save-field")
    meta = _parse_meta(data.pop("meta"), label)
    if meta["version"] >= 2 and "support" not in data:
        missing.append("support")  # version 1 fields had none: their normalisation stands in
    if missing:
        raise FormatError(f"{label}: member {missing[0]!r}: missing")
    arrays = {}
    for name, a in data.items():
        if a.dtype.kind == "f":
            a = a.astype(np.float64)
            if not np.isfinite(a).all():
                raise FormatError(f"{label}: member {name!r}: expected finite numbers, got "
                                  f"{int((~np.isfinite(a)).sum()):,} NaN or infinite")
            bound = BOUNDS.get(name)
            if bound is not None and a.size and np.abs(a).max() > bound:
                raise FormatError(f"{label}: member {name!r}: expected values within "
                                  f"+-{bound:g}, got {float(np.abs(a).max()):.6g}")
        else:
            a = a.astype(np.int64)
        arrays[name] = a
    _check_shapes(arrays, label)
    meta = check_meta(meta, arrays, label)
    _check_frames(arrays, label)
    _check_indices(arrays, meta, label)
    if "support" in arrays and np.any(arrays["support"][0] > arrays["support"][1]):
        raise FormatError(f"{label}: member 'support': expected a low corner <= the high "
                          f"corner, got {arrays['support'].tolist()}")
    return arrays, meta


def _parse_meta(raw: np.ndarray, label: str) -> dict:
    where = f"{label}: member 'meta'"
    try:
        meta = json.loads(str(raw))
    except RecursionError:
        raise FormatError(f"{where}: JSON nested too deeply") from None
    except ValueError as exc:
        raise FormatError(f"{where}: not JSON ({' '.join(str(exc).split())[:80]})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        fmt = str(meta.get("format") if isinstance(meta, dict) else None)[:40]
        raise FormatError(f"{where}: not the meta of a field written by deform --save-field "
                          f"(format {fmt!r})")
    version = meta.get("version")
    if isinstance(version, bool) or version not in READS:
        raise FormatError(f"{where}: field version {str(version)[:20]}; this splatdeform reads "
                          f"versions {', '.join(map(str, READS))}")
    return meta


def _check_shapes(a: dict, label: str) -> None:
    n, k = a["centers"].shape[0], a["delta_c"].shape[0]
    if a["weights"].shape != (4 + n, k):
        raise FormatError(f"{label}: member 'weights': expected (4 + n, k) = ({4 + n}, {k}) "
                          f"after centers ({n}, 3) and delta_c ({k}, 3), got "
                          f"{a['weights'].shape}")
    h = a["frames"].shape[0]
    for name in ("inverses", "matrices"):
        if a[name].shape[0] != h:
            raise FormatError(f"{label}: member {name!r}: expected ({h}, 4, 4) like frames, got "
                              f"{a[name].shape}")
    if not a["norm_scale"] > 0:
        raise FormatError(f"{label}: member 'norm_scale': expected a positive number, got "
                          f"{float(a['norm_scale'])}")


def _check_frames(a: dict, label: str) -> None:
    from splatdeform.edit.config import handle_matrix_problem

    eye = np.eye(4)
    for j in range(a["frames"].shape[0]):
        frame, inverse, matrix = a["frames"][j], a["inverses"][j], a["matrices"][j]
        if np.any(frame[:, 3] != 0):
            raise FormatError(f"{label}: member 'frames': [{j}]: expected column 3 zero (rows "
                              "0..3, columns 0..2 hold the frame)")
        system = np.vstack([frame[:4, :3].T, np.ones(4)])
        if not np.abs(inverse @ system - eye).max() <= 1e-6:
            raise FormatError(f"{label}: member 'inverses': [{j}]: not the inverse of handle "
                              f"{j}'s frame (a singular or altered frame)")
        if np.any(matrix[3] != [0, 0, 0, 1]):
            raise FormatError(f"{label}: member 'matrices': [{j}]: expected an affine matrix "
                              f"(last row 0 0 0 1), got last row {matrix[3].tolist()}")
        problem = handle_matrix_problem(matrix, bound=None)
        if problem is not None:
            raise FormatError(f"{label}: member 'matrices': [{j}]: {problem}")


def _check_indices(a: dict, meta: dict, label: str) -> None:
    regions = {"fixed_idx": meta["fixed"]} | {
        f"handle_idx_{j}": h["selectors"] for j, h in enumerate(meta["handles"])}
    for name in a:
        if name.startswith(("fixed_idx", "handle_idx_")) and name not in regions:
            raise FormatError(f"{label}: member {name!r}: no such region (the field has "
                              f"{len(meta['handles'])} handles)")
    from splatdeform.edit.selectors import stored

    for name, form in regions.items():
        needs = stored.has_indices(stored.decode(form, name))
        if needs and name not in a:
            raise FormatError(f"{label}: member {name!r}: missing (its region has an indices "
                              "selector, whose indices a field stores)")
        if name in a:
            if not needs:
                raise FormatError(f"{label}: member {name!r}: its region has no indices "
                                  "selector")
            idx, count = a[name], meta["n_points"]
            if idx.size > count or (idx.size and (idx.min() < 0 or idx.max() >= count)):
                raise FormatError(f"{label}: member {name!r}: expected at most {count:,} "
                                  f"indices in 0..{count - 1:,} (meta n_points)")


# ----------------------------------------------------------------------------- the meta

def _fail(label: str, key: str, message: str) -> FormatError:
    return FormatError(f"{label}: member 'meta': {key}: {message}")


def check_meta(meta: dict, arrays: dict, label: str) -> dict:
    """The meta's every key and type checked against the arrays (k columns, h handles); a
    version 1 meta translated. Returns the meta in this version's (JSON) form."""
    from splatdeform.edit.selectors import stored

    k, h = arrays["delta_c"].shape[0], arrays["frames"].shape[0]
    unknown = sorted(str(key)[:40] for key in meta if key not in META_KEYS)
    if unknown:
        raise _fail(label, unknown[0], f"unknown key (expected {', '.join(sorted(META_KEYS))})")
    for key in ("fixed", "handles", "backend", "gaussians", "method", "transferable"):
        if key not in meta:
            raise _fail(label, key, "required key is missing")
    v1 = meta["version"] == 1
    out: dict[str, Any] = {"format": FORMAT, "version": VERSION}

    plain: list = []  # every region's plain selectors, to check indices below

    def selectors(value: Any, key: str) -> list:
        try:
            form = stored.from_v1(value, key) if v1 else value
            plain.append(stored.decode(form, key))
        except stored.StoredError as exc:
            raise FormatError(f"{label}: member 'meta': {exc}") from None
        return form

    out["fixed"] = selectors(meta["fixed"], "fixed")
    handles = meta["handles"]
    if not isinstance(handles, list) or len(handles) != h:
        raise _fail(label, "handles", f"expected a list of {h} handles (one per frame), got "
                    f"{stored._kind(handles)}")
    out["handles"], end = [], 0
    for j, entry in enumerate(handles):
        key = f"handles[{j}]"
        if not isinstance(entry, dict) or set(entry) != {"name", "columns", "selectors"}:
            raise _fail(label, key, "expected a mapping of name, columns and selectors, got "
                        + (f"keys {sorted(map(str, entry))[:5]}" if isinstance(entry, dict)
                           else stored._kind(entry)))
        name, cols = entry["name"], entry["columns"]
        if not isinstance(name, str) or not 0 < len(name) <= 256:
            raise _fail(label, f"{key}.name", f"expected a name, got {stored._kind(name)}")
        if not (isinstance(cols, list) and len(cols) == 2 and all(
                isinstance(c, int) and not isinstance(c, bool) for c in cols)
                and end <= cols[0] and cols[1] == cols[0] + 4 and cols[1] <= k):
            raise _fail(label, f"{key}.columns", f"expected [a, a + 4] after the previous "
                        f"handle's columns and within 0..{k}, got {str(cols)[:40]}")
        end = cols[1]
        out["handles"].append({"name": name, "columns": [cols[0], cols[1]],
                               "selectors": selectors(entry["selectors"], f"{key}.selectors")})
    if not isinstance(meta["backend"], str) or meta["backend"] not in _BACKENDS:
        raise _fail(label, "backend", f"expected one of {', '.join(_BACKENDS)}, got "
                    f"{stored._kind(meta['backend'])}")
    out["backend"] = meta["backend"]
    method = meta["method"]
    if not isinstance(method, str) or not _METHOD.match(method):
        raise _fail(label, "method", f"expected a fit method name, got {stored._kind(method)}")
    out["method"] = method
    out["gaussians"] = _gaussians(meta["gaussians"], label)
    if not isinstance(meta["transferable"], bool):
        raise _fail(label, "transferable", f"expected true or false, got "
                    f"{stored._kind(meta['transferable'])}")
    out["transferable"] = meta["transferable"]
    note = meta.get("input", "")
    if not isinstance(note, str) or len(note) > 4096:
        raise _fail(label, "input", f"expected a file name (a note), got {stored._kind(note)}")
    out["input"] = note
    indexed = any(stored.has_indices(s) for s in plain)
    if indexed == out["transferable"]:
        raise _fail(label, "transferable", f"expected {str(not indexed).lower()} (the regions "
                    f"{'use' if indexed else 'use no'} indices selectors)")
    if indexed:
        n, digest = meta.get("n_points"), meta.get("digest")
        if isinstance(n, bool) or not isinstance(n, int) or not 0 < n <= MAX_POINTS:
            raise _fail(label, "n_points", f"expected the saved model's point count, got "
                        f"{stored._kind(n)}")
        if not isinstance(digest, str) or not _DIGEST.match(digest):
            raise _fail(label, "digest", "expected 64 hexadecimal digits, got "
                        + stored._kind(digest))
        out["n_points"], out["digest"] = n, digest
    elif "n_points" in meta or "digest" in meta:
        raise _fail(label, "n_points", "only a field with indices regions has it")
    return out


def _gaussians(value: Any, label: str) -> dict:
    from pydantic import ValidationError

    from splatdeform.edit.config import GaussiansCfg

    if not isinstance(value, dict):
        raise _fail(label, "gaussians", f"expected a mapping, got {value!r:.40}")
    try:
        return GaussiansCfg.model_validate(value).model_dump()
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ()))
        raise _fail(label, f"gaussians.{where}" if where else "gaussians",
                    " ".join(str(err.get("msg", "invalid")).split())[:120]) from None
