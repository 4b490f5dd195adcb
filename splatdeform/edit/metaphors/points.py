"""``points:`` control-point pairs (rubber-sheeting) from the config: the pairs in model units,
the edit's precomputation with them, its delta_c, its report and ``--residuals`` CSV.

Pairs are constraints at arbitrary positions, not model points: the last kind of
:data:`splatdeform.edit.metaphors.KINDS`, without a moving region (:func:`metaphor` is None).
They add 3 columns after every handle and curve (:mod:`splatdeform.deform.points`) through the
kind hooks :func:`prepare` (rings, fit and basis with the pairs), :func:`report` (residuals)
and :func:`select` (what ``select`` shows without a fit).

Pairs files: CSV or TXT (comma, semicolon, tab or blank separated), a header line naming the
columns (``x, y, z, X, Y, Z`` unless ``points.columns`` names them), ``#`` comments; at most
:data:`MAX_PAIRS_BYTES` and :data:`~splatdeform.deform.points.MAX_PAIRS` rows (reading stops
there). Numbers are read strictly, as the PLY reader reads them: decimal, finite, no digit
separators (``1_0.5``), no ``nan``/``inf``, no hex; a bad one is one line naming the file,
line and column. Coordinates follow ``regions.units`` (model units: the file's CRS, as the
loader reads LAS/LAZ with its scale and offset applied).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform.deform.points import (
    DUPLICATE_DISTANCE,
    MAX_PAIRS,
    Pairs,
    PointsFit,
    outside_hull,
    pair_errors,
    prepare_points,
)
from splatdeform.edit import units as u
from splatdeform.edit.config import EditConfig, PairsFileCfg
from splatdeform.edit.metaphors.capabilities import Capabilities
from splatdeform.errors import ConfigError
from splatdeform.model import PointModel

MAX_PAIRS_BYTES = 8 * 2**20  # a pairs file (MAX_PAIRS rows of up to ~2,800 characters)
DEFAULT_COLUMNS = ("x", "y", "z", "X", "Y", "Z")
#: A number as the PLY reader accepts it: decimal, optional sign, fraction and exponent.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def _number(token: str, path: Path, line_no: int, column: str) -> float:
    """A strict decimal (see :data:`_DECIMAL`), finite as a float64; else one line naming the
    file, line and column."""
    if _DECIMAL.fullmatch(token) is None:
        raise ConfigError(f"{path}: line {line_no}, column {column}: expected a decimal number, "
                          f"got {token[:40]!r}")
    value = float(token)
    if not np.isfinite(value):
        raise ConfigError(f"{path}: line {line_no}, column {column}: {token[:40]!r} is beyond "
                          "the float64 range")
    return value


def _data_lines(text: str):
    """(line number, stripped line) of each line that is neither blank nor a ``#`` comment,
    one at a time (no list of every line)."""
    start, line_no = 0, 0
    while start < len(text):
        end = text.find("\n", start)
        end = len(text) if end < 0 else end
        line_no += 1
        line = text[start:end].strip()
        start = end + 1
        if line and not line.startswith("#"):
            yield line_no, line

#: control-point pairs fit in memory, without --reuse (their columns come from the pairs, not a
#: region), and are edited in the editor (:func:`splatdeform.edit.capable.refusal`)
CAPABILITIES = Capabilities(streams=0, reusable=0, why={
    "streams": "points: a control-point edit runs in memory",
    "reusable": "points: a control-point edit runs without --reuse"})


def entries(cfg: EditConfig) -> list[tuple[str, object]]:
    """(key, entry) of the edit's control-point pairs: ``[("points", cfg.points)]`` or []."""
    return [("points", cfg.points)] if cfg.points is not None else []


def basis_key(entry) -> dict:
    """What of the pairs determines the basis: all of them (their sources are constraints)."""
    return entry.model_dump()


def label(n: int) -> str:
    """Pairs have no moving region: nothing in the counts line's moving name."""
    return ""


def columns(entry) -> int:
    """The basis columns of the pairs: 3 (g I)."""
    return 3


def metaphor(key: str, entry, ctx) -> None:
    """No moving region: the pairs' columns are fitted by :func:`prepare`."""
    return None


def delta(key: str, entry, group, deformation, ctx) -> tuple[np.ndarray, None]:
    """The pair columns' rows of delta_c (g I), from the fit :func:`prepare` made."""
    return group.constraints.delta(), None


def read_pairs_file(path: Path, columns: list[str] | None, key: str) -> tuple[np.ndarray, list]:
    """(n, 6) float64 rows [x, y, z, X, Y, Z] of a pairs file and their labels (file line)."""
    from splatdeform.io.regular import read_regular

    raw = read_regular(path, max_bytes=MAX_PAIRS_BYTES, what="pairs file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: {key}: not a UTF-8 text file") from None
    lines = _data_lines(text.replace("\r\n", "\n").replace("\r", "\n"))
    first = next(lines, None)
    if first is None:
        raise ConfigError(f"{path}: {key}: no header line (expected the columns "
                          f"{', '.join(columns or DEFAULT_COLUMNS)})")

    def split(line: str) -> list[str]:
        for sep in (",", ";", "\t"):
            if sep in line:
                return [v.strip().strip('"') for v in line.split(sep)]
        return re.split(r"\s+", line)

    header = split(first[1])
    wanted = list(columns or DEFAULT_COLUMNS)
    missing = [c for c in wanted if c not in header]
    if missing:
        raise ConfigError(f"{path}: {key}: the header {header} lacks the column(s) "
                          f"{', '.join(missing)}; name them with points.columns "
                          "[x, y, z, X, Y, Z]")
    where = [header.index(c) for c in wanted]
    rows, labels = [], []
    for line_no, line in lines:
        if len(rows) == MAX_PAIRS:
            raise ConfigError(f"{path}: {key}: more than {MAX_PAIRS:,} pairs (line {line_no}); "
                              "the limit keeps the dense fit to seconds and under 150 MB "
                              "(O(m^3) time, 8 m^2 bytes): thin the pairs")
        fields = split(line)
        if len(fields) <= max(where):
            raise ConfigError(f"{path}: line {line_no}: expected {len(header)} columns "
                              f"({', '.join(header)[:80]}), got {len(fields)}")
        rows.append([_number(fields[j], path, line_no, c)
                     for j, c in zip(where, wanted, strict=True)])
        labels.append(f"{path.name} line {line_no}")
    if not rows:
        raise ConfigError(f"{path}: {key}: no pairs after the header")
    return np.asarray(rows, dtype=np.float64), labels


def load_pairs(value, columns: list[str] | None, key: str, units: str, model: PointModel,
               base_dir: Path | None) -> Pairs:
    """A pairs entry (inline list or {file}) in model units (``regions.units``)."""
    if isinstance(value, PairsFileCfg):
        path = Path(base_dir or ".") / value.file
        rows, labels = read_pairs_file(path, columns, key)
    else:
        if len(value) > MAX_PAIRS:   # the schema refuses this first; a direct caller too
            raise ConfigError.at(key, f"{len(value):,} pairs exceed the limit of {MAX_PAIRS:,}")
        rows = np.asarray(value, dtype=np.float64).reshape(-1, 6)
        labels = [f"{key}[{i}]" for i in range(rows.shape[0])]
    frame = u.Frame.of(model)
    if units == "relative":
        src = frame.origin + rows[:, :3] * frame.extent
        dst = frame.origin + rows[:, 3:] * frame.extent
    else:
        src, dst = rows[:, :3].copy(), rows[:, 3:].copy()
    return Pairs(src, dst, labels, key)


def pairs_of(cfg: EditConfig, model: PointModel, base_dir: Path | None
             ) -> tuple[Pairs, Pairs | None]:
    """(the pairs, the check pairs or None) of ``cfg.points`` in model units."""
    p = cfg.points
    pairs = load_pairs(p.pairs, p.columns, "points.pairs", cfg.regions.units, model, base_dir)
    check = None if p.check_pairs is None else load_pairs(
        p.check_pairs, p.columns, "points.check_pairs", cfg.regions.units, model, base_dir)
    if check is not None and check.n and pairs.n:
        _check_not_fitted(pairs, check, model.diagonal())
    return pairs, check


def _check_not_fitted(pairs: Pairs, check: Pairs, diagonal: float) -> None:
    """A check pair at a fitted pair's source (within the duplicate distance) would report an
    error of 0: one line naming both rows."""
    from scipy.spatial import cKDTree

    if not (np.isfinite(pairs.sources).all() and np.isfinite(check.sources).all()):
        return   # check_pairs names the row
    dist, near = cKDTree(pairs.sources).query(check.sources, k=1)
    same = np.flatnonzero(dist <= DUPLICATE_DISTANCE * max(diagonal, 1e-300))
    if same.size:
        i = int(same[0])
        raise ConfigError.at(check.key, f"{check.rows[i]} is the fitted pair "
                             f"{pairs.rows[int(near[i])]} (the same source): a held-out pair "
                             "must not be fitted, its error would be 0; remove one")


@dataclass
class PointsReport:
    """Per pair: the residual (n, 3) (field(source) - target), per check pair its error,
    the points outside the pairs' convex hull, the largest pair displacement."""

    fit: PointsFit
    residuals: np.ndarray
    check: Pairs | None
    check_errors: np.ndarray | None
    outside: int
    points: int

    def lines(self) -> list[str]:
        res = np.linalg.norm(self.residuals, axis=1)
        s = float(np.linalg.norm(self.fit.pairs.displacements, axis=1).max())
        out = [f"pairs {self.fit.pairs.n:,} (smoothing {self.fit.smoothing:g}): residual max "
               f"{res.max():.3g}, RMS {np.sqrt(np.mean(res * res)):.3g} model units "
               f"({res.max() / max(s, 1e-300):.2e} of the largest pair displacement "
               f"{s:.4g}; tolerance {self.fit.tolerance:g})"]
        if self.check is not None:
            err = np.linalg.norm(self.check_errors, axis=1)
            out.append(f"check pairs {self.check.n:,}: error max {err.max():.3g}, RMS "
                       f"{np.sqrt(np.mean(err * err)):.3g} model units")
        out.append(f"{self.outside:,} of {self.points:,} points outside the pairs' convex "
                   "hull (moved by the fitted affine part's continuation)")
        return out

    def write_csv(self, path: str | Path) -> Path:
        """One row per pair and check pair: kind, label, source, target, residual vector and
        its length (model units)."""
        from splatdeform.io.atomic import atomic_write

        rows = ["kind,row,x,y,z,X,Y,Z,dx,dy,dz,error"]
        sets = [("pair", self.fit.pairs, self.residuals)]
        if self.check is not None:
            sets.append(("check", self.check, self.check_errors))
        for kind, pairs, err in sets:
            for i in range(pairs.n):
                values = [*pairs.sources[i], *pairs.targets[i], *err[i],
                          np.linalg.norm(err[i])]
                label = pairs.rows[i].replace(",", " ").replace('"', "'")
                rows.append(f"{kind},{label}," + ",".join(repr(float(v)) for v in values))
        with atomic_write(path) as fh:
            fh.write(("\n".join(rows) + "\n").encode())
        return Path(path)


def prepare(cfg: EditConfig, model: PointModel, base_dir: Path | None, fixed: np.ndarray,
            metaphors: list, *, fit_fn, basis_fn):
    """The deformation of a ``points:`` edit: the pairs plus any fixed region (``fixed`` (N,)
    bool, may be empty), handles and curve (``metaphors``), with the edit's fitter and basis;
    the pair columns come last and their group holds the :class:`PointsFit`."""
    pairs, _ = pairs_of(cfg, model, base_dir)
    return prepare_points(model, fixed, metaphors, pairs, fit_fn=fit_fn, basis_fn=basis_fn,
                          smoothing=cfg.points.smoothing, tolerance=cfg.points.tolerance,
                          continuity=cfg.boundary.continuity,
                          neighbors=cfg.boundary.neighbors)[0]


def report(cfg: EditConfig, model: PointModel, base_dir: Path | None, deformation,
           delta_c: np.ndarray) -> PointsReport:
    """Residuals at the pairs, errors at the check pairs, points outside the hull."""
    fit = next(g.constraints for g in deformation.groups if isinstance(g.constraints, PointsFit))
    _, check = pairs_of(cfg, model, base_dir)
    check_err = None if check is None else pair_errors(deformation, check, delta_c)
    return PointsReport(fit, pair_errors(deformation, fit.pairs, delta_c), check, check_err,
                        outside_hull(fit.pairs.sources, model.positions), model.n_points)


def select(cfg: EditConfig, model: PointModel, base_dir: Path | None, fixed: np.ndarray,
           metaphors: list) -> tuple[Pairs, Pairs | None]:
    """What ``select`` shows of the pairs, without the fit: (pairs, check pairs or None) in
    model units, checked against the fixed mask (N,) bool and the moving regions as ``deform``
    checks them (the same one-line refusals)."""
    from splatdeform.deform.points import check_pair_regions, check_pairs

    pairs, check = pairs_of(cfg, model, base_dir)
    lo, hi = model.bbox()
    check_pairs(pairs, lo, hi, anchored=bool(metaphors) or bool(fixed.any()))
    check_pair_regions(pairs, model.positions, fixed, metaphors)
    return pairs, check
