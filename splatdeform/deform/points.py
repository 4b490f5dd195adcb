"""The control-point metaphor ("rubber-sheeting"): pairs p_i -> q_i in model units.

The deformation is the triharmonic interpolant of the pair displacements D = Q - P with the
linear polynomial (a pure affine drift is reproduced exactly from 4 pairs), optionally with
fixed regions (their rings as for a handle) and any handles and curves of the same edit.

Columns: a pair is a constraint at an arbitrary position (not a model point), so the pairs add
k = 3 columns to M: row i of M is D_i / g and delta_c is g * I (3, 3). ``g`` scales the columns
so that the shared ``fit.tolerance`` (largest |r_ic| in M's units) means the pair tolerance:
a pair misses its target by at most ``sqrt(3) * fit.tolerance * g`` = ``tolerance * s`` model
units, s the largest pair displacement (:func:`pair_scale`). Default
:data:`DEFAULT_PAIR_TOLERANCE` = 1e-6 of s ("exact").

``smoothing`` > 0: least squares with scipy RBFInterpolator's meaning (data units: s is added
to the diagonal of the r^3 kernel matrix of the pair rows; fixed rings stay exact), solved
densely (:func:`fit_smoothed`, at most :data:`EXACT_MAX_CONSTRAINTS` constraints).

Checks (one line naming the row): more than :data:`MAX_PAIRS` pairs; duplicate or conflicting
pairs (sources closer than :data:`DUPLICATE_DISTANCE` of the model's diagonal), two sources
closer than :data:`NEAR_DISTANCE` of the diagonal whose displacements differ by more than
their distance (the field would fold between them), a source or target farther than
:data:`PAIR_MARGIN` diagonals outside the model's bounding box, a source in a fixed region or a
moving region (its nearest model point belongs to it: those points do not follow the field);
without fixed regions or other metaphors, fewer than 4 pairs or an ill-conditioned affine part
(:data:`AFFINE_MIN_RATIO`).
After the fit (smoothing 0), a pair missed by more than ``tolerance`` times the largest pair
displacement is refused (:func:`check_pair_residuals`): nothing is written.
Duplicates and near pairs are found with a kd-tree (at most :data:`NEAR_NEIGHBOURS` neighbours
a source): O(n log n).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from splatdeform.deform.deformation import BasisFn, Deformation, FitSettings
from splatdeform.deform.metaphor import Metaphor
from splatdeform.deform.regions import Group
from splatdeform.errors import ConfigError, InputError, RegionError
from splatdeform.model import PointModel
from splatdeform.rbf.exact import EXACT_MAX_CONSTRAINTS
from splatdeform.rbf.result import Normalization, RbfFit

DEFAULT_PAIR_TOLERANCE = 1e-6  # largest pair residual / largest pair displacement
PAIR_MARGIN = 0.5  # pairs farther outside the model's box than this many diagonals: refused
DUPLICATE_DISTANCE = 1e-9  # sources closer than this (times the diagonal) are the same point
#: Without fixed regions or other metaphors the affine part comes from the pairs alone: the
#: smallest singular value of their centred sources must be at least this of the largest
#: (nearly collinear or coplanar pairs leave an axis of the affine part undetermined).
AFFINE_MIN_RATIO = 1e-3
#: Pairs (and check pairs) in one edit. Every pair is a center of its own (the pairs are
#: scattered data), so the fit is a dense solve: O(m^3) time and 8 m^2 bytes (twice with
#: smoothing). 3,000 pairs take about a second and under 150 MB; 20,000 would take minutes and
#: gigabytes. More pairs than this are refused at once (reading stops at the limit).
MAX_PAIRS = 3_000
#: Two sources closer than this (times the diagonal) whose displacements differ by more than
#: their distance are refused: the interpolant would fold between them (a strain above 1; 1e-7
#: apart with targets 0.5 apart moved points of a 10-unit model by 7e5). Close pairs that agree
#: (ground control points measured twice) are kept; the residual check still guards them.
NEAR_DISTANCE = 1e-4
NEAR_NEIGHBOURS = 8  # neighbours of each source searched for duplicates and near pairs
PLANAR_HULL_RATIO = 0.1  # pairs flatter than this: the hull is taken in their principal plane
SMALL_DENSE = 64  # constraints up to this: the plain saddle solve (the exact fit needs more)


@dataclass
class Pairs:
    """sources, targets: (n, 3) float64 model units; rows: (n,) labels naming where each pair
    came from (``gcp.csv line 7``, ``points.pairs[3]``); key: the config key."""

    sources: np.ndarray
    targets: np.ndarray
    rows: list[str]
    key: str = "points.pairs"

    @property
    def n(self) -> int:
        return int(self.sources.shape[0])

    @property
    def displacements(self) -> np.ndarray:
        return self.targets - self.sources


def check_pairs(pairs: Pairs, lo: np.ndarray, hi: np.ndarray, *, anchored: bool) -> None:
    """Refuse with one line naming the row: too many pairs, duplicate or conflicting pairs,
    pairs outside the box [lo, hi] by more than :data:`PAIR_MARGIN` of its diagonal, and (when
    not ``anchored`` by fixed regions or other metaphors) an affine part the pairs cannot
    determine (fewer than 4, or :data:`AFFINE_MIN_RATIO`)."""
    n = pairs.n
    if n == 0:
        raise ConfigError.at(pairs.key, "expected at least one pair")
    if n > MAX_PAIRS:
        raise ConfigError.at(pairs.key, f"{n:,} pairs exceed the limit of {MAX_PAIRS:,}")
    for name, arr in (("source", pairs.sources), ("target", pairs.targets)):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise ConfigError.at(pairs.key, f"{pairs.rows[int(np.flatnonzero(bad)[0])]}: "
                                 f"non-finite {name}")
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    margin = PAIR_MARGIN * diag
    for name, arr in (("source", pairs.sources), ("target", pairs.targets)):
        out = np.maximum(lo - arr, arr - hi).max(axis=1) > margin
        if out.any():
            i = int(np.flatnonzero(out)[0])
            raise ConfigError.at(pairs.key, f"{pairs.rows[i]}: {name} {arr[i].tolist()} lies "
                                 f"more than {PAIR_MARGIN:g} diagonals ({margin:.6g} model "
                                 f"units) outside the model's box {lo.tolist()} .. "
                                 f"{hi.tolist()} (wrong units or CRS?)")
    check_close_sources(pairs, diag)
    if anchored:
        return
    if n < 4:
        raise ConfigError.at(pairs.key, f"{n} pair(s) without fixed regions: expected at least "
                             "4 pairs not in one plane (the affine part needs them)")
    ratio = affine_ratio(pairs.sources)
    if ratio < AFFINE_MIN_RATIO:
        raise ConfigError.at(pairs.key, f"the pairs' sources are nearly collinear or coplanar "
                             f"(smallest / largest singular value {ratio:.2g} < "
                             f"{AFFINE_MIN_RATIO:g}): the affine part is ill-conditioned; add "
                             "pairs off that plane or fixed regions")


def _first_close(nbr: np.ndarray, hit: np.ndarray) -> tuple[int, int] | None:
    """The pair (i, j), i < j, with the smallest j (then i) among the neighbour hits (n, k)."""
    rows = np.nonzero(hit)
    if rows[0].size == 0:
        return None
    a, b = rows[0], nbr[rows]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    best = int(np.lexsort((lo, hi))[0])
    return int(lo[best]), int(hi[best])


def check_close_sources(pairs: Pairs, diag: float) -> None:
    """Duplicates (sources within :data:`DUPLICATE_DISTANCE` diagonals) and near pairs (within
    :data:`NEAR_DISTANCE` diagonals, with displacements that differ by more than the sources'
    distance): one line naming both rows. Exact duplicates by sorting, the rest from each source's
    :data:`NEAR_NEIGHBOURS` nearest sources in a kd-tree: O(n log n)."""
    from scipy.spatial import cKDTree

    n = pairs.n
    if n < 2:
        return
    src = pairs.sources
    order = np.lexsort(src.T[::-1])
    same = np.flatnonzero((src[order[1:]] == src[order[:-1]]).all(axis=1))
    if same.size:   # identical sources: sorting finds them however many there are
        a, b = order[same], order[same + 1]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        best = int(np.lexsort((lo, hi))[0])
        _refuse_close(pairs, int(lo[best]), int(hi[best]), diag)
    atol = DUPLICATE_DISTANCE * diag
    k = min(NEAR_NEIGHBOURS, n - 1) + 1
    dist, nbr = cKDTree(src).query(src, k=k, distance_upper_bound=NEAR_DISTANCE * diag)
    valid = (nbr < n) & (nbr != np.arange(n)[:, None])
    nbr = np.where(valid, nbr, 0)
    found = _first_close(nbr, valid & (dist <= atol))
    if found is not None:
        _refuse_close(pairs, *found, diag)
    disp = pairs.displacements
    differ = np.linalg.norm(disp[nbr] - disp[:, None, :], axis=2) > np.maximum(dist, atol)
    found = _first_close(nbr, valid & differ)
    if found is not None:
        i, j = found
        d = float(np.linalg.norm(src[j] - src[i]))
        raise ConfigError.at(pairs.key, f"{pairs.rows[j]} lies {d:.3g} model units from "
                             f"{pairs.rows[i]} (closer than {NEAR_DISTANCE:g} of the model's "
                             f"diagonal, {NEAR_DISTANCE * diag:.3g}) and their displacements "
                             "differ by more than that: the field would fold between them; "
                             "remove or merge one")


def _refuse_close(pairs: Pairs, i: int, j: int, diag: float) -> None:
    same = np.allclose(pairs.targets[i], pairs.targets[j], rtol=0,
                       atol=DUPLICATE_DISTANCE * diag)
    what = "duplicates" if same else "conflicts with"
    tail = "" if same else " (the same source with another target)"
    raise ConfigError.at(pairs.key, f"{pairs.rows[j]} {what} {pairs.rows[i]}{tail}; "
                         "remove one")


def check_pair_regions(pairs: Pairs, positions: np.ndarray, fixed: np.ndarray,
                       metaphors: list[Metaphor]) -> None:
    """Refuse a pair whose source lies in the fixed region or a moving region (handle, curve
    band): its nearest model point (positions (N, 3)) belongs to it. Those points do not follow
    the field (fixed: copied; moving: their own map), and a source among the ring constraints
    makes the system singular (a residual of 1e19). One line naming the row and the region."""
    from scipy.spatial import cKDTree

    regions = [("regions.fixed", fixed)] if fixed.any() else []
    for mph in metaphors:
        mask = np.zeros(positions.shape[0], dtype=bool)
        mask[mph.idx] = True
        regions.append((mph.name, mask))
    if not regions or pairs.n == 0:
        return
    _, nearest = cKDTree(positions).query(pairs.sources, k=1)
    for name, mask in regions:
        inside = np.flatnonzero(mask[nearest])
        if inside.size:
            i = int(inside[0])
            raise ConfigError.at(pairs.key, f"{pairs.rows[i]}: source {pairs.sources[i].tolist()} "
                                 f"lies in {name} (its nearest model point, {int(nearest[i])}, "
                                 "is one of its points, which do not follow the field); "
                                 "move the pair into the free region or drop it")


def check_pair_residuals(pairs: Pairs, fit: RbfFit, columns: tuple[int, int], scale: float,
                         tolerance: float, diagonal: float) -> None:
    """After an interpolating fit: refuse (one line naming the worst row, nothing written) when
    a pair misses its target by more than ``tolerance`` times the largest pair displacement
    (the documented bound, :func:`pair_scale`). Only the pair columns are evaluated (g I)."""
    from splatdeform.basis.reference import compute_basis

    values = compute_basis(pairs.sources, fit, gradients=False,
                           max_chunk_bytes=32 * 2**20).values   # float64, small temporaries
    moved = values[:, columns[0]:columns[1]].astype(np.float64) * scale
    err = np.linalg.norm(moved - pairs.displacements, axis=1)
    s = max(float(np.linalg.norm(pairs.displacements, axis=1).max()),
            1e-9 * max(diagonal, 1e-300))
    bound = tolerance * s
    bad = ~np.isfinite(err) | (err > bound)
    if bad.any():
        i = int(np.argmax(np.where(np.isfinite(err), err, np.inf)))
        raise ConfigError.at(pairs.key, f"{pairs.rows[i]}: the fit misses this pair by "
                             f"{err[i]:.3g} model units, more than the bound {bound:.3g} "
                             f"(points.tolerance {tolerance:g} of the largest pair displacement "
                             f"{s:.4g}); nothing written (pairs too close together or next to a "
                             "region? raise fit.max_centers or use fit.method: exact)")


def affine_ratio(sources: np.ndarray) -> float:
    """Smallest / largest singular value of the centred sources (n, 3) (0: degenerate)."""
    sv = np.linalg.svd(sources - sources.mean(axis=0), compute_uv=False)
    return float(sv[-1] / sv[0]) if sv.size == 3 and sv[0] > 0 else 0.0


def outside_hull(sources: np.ndarray, points: np.ndarray) -> int:
    """How many points (N, 3) lie outside the convex hull of the sources (n, 3): there the
    warp continues the fitted affine part. Flat pair sets (a terrain: smallest singular value
    below :data:`PLANAR_HULL_RATIO` of the largest) use the hull of their footprint in their
    principal plane; fewer pairs than a hull needs: every point is outside."""
    from scipy.spatial import Delaunay, QhullError

    centre = sources.mean(axis=0)
    _, sv, vt = np.linalg.svd(sources - centre, full_matrices=False)
    dims = 2 if sv.size < 3 or sv[2] < PLANAR_HULL_RATIO * sv[0] else 3
    if sources.shape[0] <= dims or sv[dims - 1] <= 0:
        return int(points.shape[0])
    try:
        tri = Delaunay((sources - centre) @ vt[:dims].T)
    except QhullError:
        return int(points.shape[0])
    outside = 0
    for start in range(0, points.shape[0], 1_000_000):
        chunk = (points[start:start + 1_000_000] - centre) @ vt[:dims].T
        outside += int(np.count_nonzero(tri.find_simplex(chunk) < 0))
    return outside


def pair_scale(pairs: Pairs, tolerance: float, fit_tolerance: float, diagonal: float
               ) -> float:
    """g: the pair columns are D / g and delta_c = g I, so that |r| <= fit_tolerance in M's
    units is a pair error of at most ``tolerance`` times the largest pair displacement s
    (s: at least 1e-9 of the diagonal, for pairs that do not move)."""
    s = float(np.linalg.norm(pairs.displacements, axis=1).max()) if pairs.n else 0.0
    s = max(s, 1e-9 * max(diagonal, 1e-300))
    return tolerance * s / (np.sqrt(3.0) * fit_tolerance)


@dataclass
class PointsFit:
    """What the pairs added to a deformation: the pairs, their column scale g, their columns
    (start, stop) and the smoothing (data units)."""

    pairs: Pairs
    scale: float
    columns: tuple[int, int]
    smoothing: float
    tolerance: float

    def delta(self) -> np.ndarray:
        """The pair columns' rows of delta_c: g I (3, 3)."""
        return self.scale * np.eye(3)


def fit_smoothed(points: np.ndarray, rhs: np.ndarray, diagonal: np.ndarray,
                 normalization: Normalization) -> RbfFit:
    """The dense least-squares fit with scipy RBFInterpolator's smoothing: the saddle system
    [[Phi + diag, P], [P^T, 0]] with Phi = |x_i - x_j|^3 in model units and ``diagonal``
    (m,) (0 for exact rows), solved in normalised coordinates (Phi / L^3, diag / L^3)."""
    from scipy.linalg import LinAlgError

    from splatdeform.rbf.kernel import cubed_distances

    m, k = rhs.shape
    if m > EXACT_MAX_CONSTRAINTS:
        raise ConfigError.at("points.smoothing", f"{m:,} constraints exceed the dense solve's "
                             f"limit of {EXACT_MAX_CONSTRAINTS:,} (smoothing needs it)")
    x = normalization.apply(points)
    lhs = np.zeros((m + 4, m + 4))
    cubed_distances(x, x, out=lhs[:m, :m])
    lhs[np.arange(m), np.arange(m)] += diagonal / normalization.scale ** 3
    lhs[:m, m] = lhs[m, :m] = 1.0
    lhs[:m, m + 1:] = x
    lhs[m + 1:, :m] = x.T
    full = np.zeros((m + 4, k))
    full[:m] = rhs
    try:
        from scipy.linalg import lu_factor, lu_solve

        lu = lu_factor(lhs, check_finite=False)
        sol = lu_solve(lu, full, check_finite=False)
        for _ in range(2):  # iterative refinement: the affine part to rounding
            sol += lu_solve(lu, full - lhs @ sol, check_finite=False)
    except (LinAlgError, ValueError) as exc:
        raise InputError(f"points: the smoothed system is singular ({exc})") from None
    if not np.isfinite(sol).all():
        raise InputError("points: the pairs' system is singular (coplanar pairs without fixed "
                         "regions?)")
    weights = np.ascontiguousarray(np.vstack([sol[m:], sol[:m]]))
    # the interpolation residual (the kernel without the smoothing diagonal), with no
    # (m, m) temporary: 3,000 pairs peaked at 380 MB with np.diag and the difference
    r = rhs - lhs[:m, :m] @ sol[:m] + (diagonal / normalization.scale ** 3)[:, None] * sol[:m] \
        - lhs[:m, m:] @ sol[m:]
    return RbfFit(centers=x, weights=weights, normalization=normalization,
                  residuals=np.zeros((1, k)), converged=True, tolerance=0.0,
                  max_error=float(np.abs(r).max()), rms_error=float(np.sqrt(np.mean(r * r))),
                  method="smoothed" if diagonal.any() else "exact")


def _rings_of_fixed(model: PointModel, fixed: np.ndarray, continuity: int, neighbors: int
                    ) -> list[np.ndarray]:
    from splatdeform.deform.regions import not_adjacent
    from splatdeform.deform.rings import region_adjacency, rings

    moving = np.zeros_like(fixed)
    free = ~fixed
    if not free.any():
        raise RegionError.at("regions.fixed", "covers every point; leave a free region")
    adj = region_adjacency(model, fixed, moving, neighbors, continuity + 2)
    found = rings(adj, fixed, free, continuity + 1)
    if found[0].size == 0:
        raise not_adjacent("regions.fixed", "fixed")
    return list(found)


def prepare_points(model: PointModel, fixed: np.ndarray, metaphors: list[Metaphor],
                   pairs: Pairs, *, fit_fn: FitSettings, basis_fn: BasisFn,
                   smoothing: float = 0.0, tolerance: float = DEFAULT_PAIR_TOLERANCE,
                   continuity: int = 2, neighbors: int = 10
                   ) -> tuple[Deformation, PointsFit]:
    """Rings, constraints (ring points, then the pairs), one fit and one basis for the pairs
    plus a fixed mask (N,) bool (may be empty) and any handles and curves; the pair columns
    come last. ``constraint_idx`` holds -1 for the pairs (not model points)."""
    from splatdeform.deform.regions import layout
    from splatdeform.deform.thin import thin_rings

    n = model.n_points
    lo, hi = model.bbox()
    check_pairs(pairs, lo, hi, anchored=bool(metaphors) or bool(fixed.any()))
    check_pair_regions(pairs, model.positions, fixed, metaphors)
    t0 = time.perf_counter()
    if metaphors:
        lay = layout(model, fixed, metaphors, continuity=continuity, neighbors=neighbors)
        moving, moving_idx, coords, grads = lay.moving, lay.moving_idx, lay.coords, lay.gradients
        groups, fixed_rings, moving_rings = list(lay.groups), lay.fixed_rings, lay.moving_rings
    else:
        moving, moving_idx = np.zeros(n, dtype=bool), np.empty(0, dtype=np.int64)
        coords, grads, groups = np.zeros((0, 0)), np.zeros((0, 0, 3)), []
        fixed_rings = _rings_of_fixed(model, fixed, continuity, neighbors) if fixed.any() \
            else []
        moving_rings = []
    k0 = coords.shape[1]
    k = k0 + 3
    scale = pair_scale(pairs, tolerance, fit_fn.tolerance, model.diagonal())
    coords = np.concatenate([coords, np.zeros((coords.shape[0], 3))], axis=1)
    grads = np.concatenate([grads, np.zeros((grads.shape[0], 3, 3))], axis=1)
    ring_lists = list(fixed_rings) + list(moving_rings)
    ring_idx = np.concatenate(ring_lists) if ring_lists else np.empty(0, dtype=np.int64)
    n_fixed_c = sum(r.size for r in fixed_rings)
    lookup = np.full(n, -1, dtype=np.int64)
    lookup[moving_idx] = np.arange(moving_idx.size)
    rhs = np.zeros((ring_idx.size + pairs.n, k))
    rhs[n_fixed_c:ring_idx.size] = coords[lookup[ring_idx[n_fixed_c:]]]
    rhs[ring_idx.size:, k0:] = pairs.displacements / scale
    points = np.vstack([model.positions[ring_idx], pairs.sources])
    kept = None
    if ring_lists and fit_fn.thinning > 0 and fit_fn.method != "exact" and smoothing == 0:
        kept = np.concatenate([thin_rings(model.positions, ring_lists, neighbors,
                                          fit_fn.thinning), np.ones(pairs.n, dtype=bool)])
    timings = {"rings": time.perf_counter() - t0}
    t0 = time.perf_counter()
    if smoothing > 0 or points.shape[0] <= SMALL_DENSE:
        diag = np.zeros(points.shape[0])
        diag[ring_idx.size:] = smoothing
        fit = fit_smoothed(points, rhs, diag, fit_fn.normalization)
        kept = None
    else:
        fit = fit_fn(points, rhs, kept)
        if fit.method == "exact":
            kept = None
        elif fit.kept is not None:
            kept = fit.kept
    if smoothing == 0:
        check_pair_residuals(pairs, fit, (k0, k), scale, tolerance, model.diagonal())
    timings["fit"] = time.perf_counter() - t0
    free_idx = np.flatnonzero(~(fixed | moving))
    t0 = time.perf_counter()
    basis = basis_fn(model.positions[free_idx], fit)
    timings["basis"] = time.perf_counter() - t0
    control = [m.control_points for m in metaphors] + [np.repeat(
        pairs.sources.mean(axis=0, keepdims=True), 3, axis=0)]
    points_fit = PointsFit(pairs, scale, (k0, k), smoothing, tolerance)
    groups.append(Group("points", (k0, k), np.empty(0, dtype=np.int64), None, points_fit))
    deformation = Deformation(
        n_points=n, fixed=fixed, moving=moving, free_idx=free_idx, moving_idx=moving_idx,
        moving_coords=coords, moving_gradients=grads,
        constraint_idx=np.concatenate([ring_idx, np.full(pairs.n, -1, dtype=np.int64)]),
        constraint_points=points, constraint_rhs=rhs, control_points=np.vstack(control),
        fit=fit, basis=basis, timings=timings,
        ring_sizes=([r.size for r in fixed_rings], [r.size for r in moving_rings]),
        groups=groups, kept=kept)
    return deformation, points_fit


def displacement_at(deformation: Deformation, points: np.ndarray, delta_c: np.ndarray
                    ) -> np.ndarray:
    """The field's displacement (M, 3) at any points (M, 3) for delta_c (k, 3) (numpy)."""
    from splatdeform.basis import compute_basis

    values = compute_basis(points, deformation.fit, gradients=False, backend="numpy").values
    return values.astype(np.float64) @ np.asarray(delta_c, dtype=np.float64)


def pair_errors(deformation: Deformation, pairs: Pairs, delta_c: np.ndarray) -> np.ndarray:
    """(n, 3) where the field sends each source minus its target (model units)."""
    if pairs.n == 0:
        return np.zeros((0, 3))
    return pairs.sources + displacement_at(deformation, pairs.sources, delta_c) - pairs.targets
