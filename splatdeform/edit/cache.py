"""Save/load a precomputed deformation so a new handle transform skips fit and basis.

The file (``.npz``) holds the centers, weights, normalisation, basis, region masks, the kept
(thinned) subset of the constraints and the edit
key: a hash of everything that determines the basis (input file bytes, regions, boundary, fit,
normals, curve control points, backend). The handle transform and curve ``moved_to`` are not in
the key: changing them is exactly what reuse is for.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np

from splatdeform.basis.result import Basis
from splatdeform.deform import Deformation, Group
from splatdeform.deform.handle import AffineFrame
from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import basis_keys
from splatdeform.errors import InputError
from splatdeform.io.atomic import atomic_path
from splatdeform.model import PointModel
from splatdeform.rbf.result import Normalization, RbfFit

FORMAT_VERSION = 7  # 3: metaphor groups; 4: registry key; 5: frames only in groups;
#                      6: the thinned (kept) constraints; 7: coarse rings kept whole


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def edit_key(cfg: EditConfig, input_path: str | Path) -> str:
    """Hash of the parts of an edit that determine the precomputed basis."""
    parts = cfg.model_dump(include={"regions", "boundary", "fit", "normals", "backend",
                                    "device"})
    parts["fit"].pop("on_not_converged", None)  # what to do about a miss, not what is fitted
    parts["metaphors"] = basis_keys(cfg)  # e.g. a handle's region, not its transform
    parts["input"] = _file_digest(Path(input_path))
    parts["version"] = FORMAT_VERSION
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def _groups_arrays(d: Deformation) -> dict[str, np.ndarray]:
    """The metaphor groups as plain arrays: names, column bounds, each moving point's group,
    and the handles' frame inverses (zeros for curves)."""
    owner = np.full(d.moving_idx.size, -1, dtype=np.int64)
    for j, g in enumerate(d.groups):
        owner[g.rows] = j
    inverses = [g.frame.inverse if g.frame is not None else np.zeros((4, 4)) for g in d.groups]
    return {
        "group_names": np.array([g.name for g in d.groups], dtype=str),
        "group_columns": np.array([g.columns for g in d.groups], dtype=np.int64).reshape(-1, 2),
        "group_owner": owner,
        "group_has_frame": np.array([g.frame is not None for g in d.groups], dtype=bool),
        "group_inverses": np.array(inverses).reshape(-1, 4, 4),
    }


def _groups_from(z) -> list[Group]:
    groups = []
    for j, name in enumerate(z["group_names"]):
        start, stop = (int(v) for v in z["group_columns"][j])
        frame = None
        if z["group_has_frame"][j]:
            frame = AffineFrame(control_points=z["control_points"][start:stop],
                                inverse=z["group_inverses"][j])
        groups.append(Group(str(name), (start, stop), np.flatnonzero(z["group_owner"] == j),
                            frame))
    return groups


def save_deformation(path: str | Path, key: str, d: Deformation) -> Path:
    """Write ``d`` atomically to ``path`` (.npz)."""
    arrays = {
        "key": np.array(key), "n_points": np.array(d.n_points), "fixed": d.fixed,
        "moving": d.moving, "free_idx": d.free_idx, "moving_idx": d.moving_idx,
        "moving_coords": d.moving_coords,
        "moving_gradients": np.ascontiguousarray(d.moving_gradients),
        "constraint_idx": d.constraint_idx, "constraint_points": d.constraint_points,
        "constraint_rhs": d.constraint_rhs, "control_points": d.control_points,
        "centers": d.fit.centers, "weights": d.fit.weights, "residuals": d.fit.residuals,
        "converged": np.array(d.fit.converged), "tolerance": np.array(d.fit.tolerance),
        "max_error": np.array(d.fit.max_error), "rms_error": np.array(d.fit.rms_error),
        "method": np.array(d.fit.method),
        "norm_center": d.fit.normalization.center,
        "norm_scale": np.array(d.fit.normalization.scale),
        "values": d.basis.values,
        "gradients": d.basis.gradients if d.basis.gradients is not None else np.zeros(0),
        "ring_fixed": np.asarray(d.ring_sizes[0], dtype=np.int64),
        "ring_moving": np.asarray(d.ring_sizes[1], dtype=np.int64),
        "kept": d.kept if d.kept is not None else np.zeros(0, dtype=bool),
        **_groups_arrays(d),
    }
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


MAX_EXPANSION = 10  # np.savez stores members uncompressed: their sum is about the file size
MAX_EXTRA_BYTES = 300 * 2**20
MAX_CACHE_BYTES = 1 << 40  # no cap of its own: the members' declared sizes are bounded instead
MAX_MEMBERS = 64  # save_deformation writes about 35


def _read(path: Path, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The members of a cache file (``names`` only, when given) through the one bounded .npz
    reader (:func:`splatdeform.io.npz.read_npz`): refused, before numpy reads anything, when it
    is not a zip, when its members would expand beyond 10x the file + 300 MB, or when a
    member holds objects (a hostile or foreign cache)."""
    from splatdeform.errors import FormatError
    from splatdeform.io.npz import read_npz

    try:
        return read_npz(path, label=str(path), max_bytes=MAX_CACHE_BYTES,
                        max_members=MAX_MEMBERS, allowed=lambda _name: True,
                        header=lambda *_: None, max_expansion=MAX_EXPANSION,
                        extra_bytes=MAX_EXTRA_BYTES, what="precomputed deformation",
                        names=names)
    except FormatError as exc:
        reason = " ".join(str(exc).removeprefix(f"{path}: ").split())[:160]
        raise InputError(f"{path}: not a splatdeform precomputed deformation ({reason}); "
                         "delete it or choose another --reuse-file") from None


def load_deformation(path: str | Path, key: str, model: PointModel) -> Deformation | None:
    """The stored deformation if ``path`` exists and matches ``key`` and the model, else None."""
    path = Path(path)
    if path.exists() and not path.is_file():
        raise InputError(f"{path}: is not a regular file; expected a precomputed deformation "
                         "(.npz) or a path to create one")
    if not path.is_file():
        return None
    try:
        head = _read(path, ("key", "n_points"))
        if str(head["key"]) != key or int(head["n_points"]) != model.n_points:
            return None
        z = _read(path)
        fit = RbfFit(centers=z["centers"], weights=z["weights"],
                     normalization=Normalization(z["norm_center"], float(z["norm_scale"])),
                     residuals=z["residuals"], converged=bool(z["converged"]),
                     tolerance=float(z["tolerance"]), max_error=float(z["max_error"]),
                     rms_error=float(z["rms_error"]), method=str(z["method"]))
        grads = z["gradients"]
        return Deformation(
            n_points=int(z["n_points"]), fixed=z["fixed"], moving=z["moving"],
            free_idx=z["free_idx"], moving_idx=z["moving_idx"], moving_coords=z["moving_coords"],
            moving_gradients=z["moving_gradients"], constraint_idx=z["constraint_idx"],
            constraint_points=z["constraint_points"], constraint_rhs=z["constraint_rhs"],
            control_points=z["control_points"], fit=fit,
            basis=Basis(z["values"], grads if grads.size else None),
            ring_sizes=(list(z["ring_fixed"]), list(z["ring_moving"])),
            groups=_groups_from(z), kept=z["kept"] if z["kept"].size else None)
    except InputError:
        raise
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        reason = "missing " + str(exc) if isinstance(exc, KeyError) else \
            "not an .npz written by splatdeform" if "pickle" in str(exc) or not str(exc) else \
            " ".join(str(exc).split())[:120]
        raise InputError(f"{path}: not a splatdeform precomputed deformation ({reason}); delete "
                         "it or choose another --reuse-file") from exc
