"""Adaptive splitting of 3D Gaussian splats that one Gaussian cannot follow (issue 37).

A splat is deformed by its centre's Jacobian J, a linear map. Where the deformation stretches
space anisotropically (the outer side of a bend) or curves across the splat's own extent, one
Gaussian is a poor image of the parent: ``gaussians.split: auto`` replaces such a splat by up
to :data:`MAX_CHILDREN` children, each deformed at its own centre (own J, own SH rotation).

**The rule** (fixed estimator and thresholds, deterministic). For a moved free-region splat with
rest centre x, rotation R (columns a_k), standard deviations s_k and Jacobian J:

- *stretch*: N = J / |det J|^(1/3) (the non-similarity part of J). The splat stretches when the
  longest axis of N R S exceeds :data:`STRETCH_LIMIT` times its longest rest axis; a uniform
  scale or a rotation never stretches.
- *nonlinearity*: sigma points x +- 2 s_k a_k along each principal axis through the field f:
  e_k = |f(x + h) + f(x - h) - 2 f(x)| / 2 (the second-order term over the 2-sigma extent)
  against l_k = |f(x + h) - f(x - h)| / 2 (the first-order term); the splat is too curved when
  some e_k / l_k exceeds :data:`CURVE_LIMIT`.
- *affine across the splat*: when every e_k / l_k is below :data:`AFFINE_FLOOR` the field is
  affine over the splat and the deformed Gaussian is the exact image of the parent: never
  split (so an affine map, whatever its stretch, never splits).

**Cost.** For an RBF fit (:class:`FitField`) the sigma points and the children go through the
backend the centres use (OpenCL float32 with double accumulation where it runs, else the
float64 numpy reference), one-shot from W delta_c a chunk at a time; e_k comes from the RBF
part alone (the polynomial part's second difference is zero), so it is exactly 0 when the RBF
weights W delta_c are 0, whatever the backend's rounding; l_k adds the polynomial part's linear
map. :func:`plan` uses closed forms (determinants by cofactors, the largest singular value
from the Gram matrix's largest eigenvalue), no per-splat LAPACK call.

Children per axis: m_k children along rest axis k (product <= 8) at offsets
(2j - (m_k - 1)) c_k s_k, j = 0..m_k-1, each with that axis shrunk to c_k s_k, c_k = 1/sqrt(m_k),
and binomial weights C(m_k - 1, j) / 2^(m_k - 1): spacing of two child sigmas, and in rest space
the children's mixture has the parent's mean and covariance (m c^2 = 1). The axes grow greedily
(one child more along the worst axis per step: the longest axis of N R S C while the stretch
test fails, else the axis with the largest e_k / l_k c_k) until both tests pass or 8 children.
Opacity: a child of weight w (product over the axes) gets alpha' = 1 - (1 - alpha)^(w / prod c_k)
(the density matches for faint splats, MCMC's rule 1 - (1 - alpha)^(1/n) for co-located
copies); colour, SH and every other property are the parent's (SH rotated by the child's own J).

**Bounds.** Only free-region splats are candidates: fixed splats stay bit-identical, handle
splats move by the handle's affine map (nothing to split; curve bands are not split either).
The total growth (children written minus parents replaced) is capped at :data:`GROWTH_CAP` of
the moved (non-fixed) splats; beyond it the splats with the largest excess (worst test ratio)
are split first and the rest stay whole (counted as ``split_capped``).

**Order.** Every original splat keeps its row: a split parent's row holds its first child
(child 0: the lowest offsets, axis 0 slowest); the other children are appended after all
originals, by parent row, then child number.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from math import comb

import numpy as np

from splatdeform.deform.split_field import (  # noqa: F401 - the split's public names
    SIGMA_EXTENT,
    Field,
    FitField,
    basis_field,
    fit_field,
    ratio,
    sigma_points,
    sigma_steps,
    split_like_oneshot,
)
from splatdeform.errors import InputError
from splatdeform.geometry import quaternion_to_matrix
from splatdeform.model import Gaussians, PointModel

SPLIT_MODES = ("auto", "off")
DEFAULT_SPLIT = "auto"  # on by default (issue 46): benchmarks/bench_needles.py --psnr
STRETCH_LIMIT = 2.0  # longest axis of N R S / longest rest axis above this: split
CURVE_LIMIT = 0.1  # second-order / first-order term over +-2 sigma above this: split
AFFINE_FLOOR = 1e-6  # below this on every axis the field is affine across the splat: never split
MAX_CHILDREN = 8  # per split splat
GROWTH_CAP = 0.3  # new splats (children - parents) <= this x moved (non-fixed) splats


@dataclass
class SplitPlan:
    """Which of M candidate splats split and how: counts (M, 3) children per rest axis (all 1:
    whole); excess (M,) the worst test ratio over its limit (> 1: the rule wants a split);
    capped: splats the rule wanted but the growth cap kept whole."""

    counts: np.ndarray
    excess: np.ndarray
    capped: int = 0

    @property
    def split(self) -> np.ndarray:
        """(M,) bool: splats replaced by children."""
        return self.counts.prod(axis=1) > 1


def _frames(scale_log: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) standard deviations and (M, 3, 3) rotations (columns: the principal axes)."""
    return np.exp(np.asarray(scale_log, np.float64)), quaternion_to_matrix(rotation)


def curvature(centers: np.ndarray, sigma: np.ndarray, rot: np.ndarray,
              field: Field) -> np.ndarray:
    """(M, 3) second-order / first-order term of ``field`` along each principal axis over
    +-:data:`SIGMA_EXTENT` sigma (0 where the first-order term is 0), from 7 sigma points.
    A :class:`FitField` answers from its RBF part alone (:meth:`FitField.curvature`: exactly 0
    for an affine field); any other field from its values at the sigma points."""
    if hasattr(field, "curvature"):  # a FitField
        return field.curvature(centers, sigma, rot)
    m = centers.shape[0]
    f, _ = field(sigma_points(centers, sigma_steps(sigma, rot)), False)
    f = f.reshape(m, 7, 3)
    plus, minus = f[:, 1:4], f[:, 4:7]
    second = np.linalg.norm(plus + minus - 2 * f[:, :1], axis=2) / 2
    first = np.linalg.norm(plus - minus, axis=2) / 2
    return ratio(second, first)


def _det3(m: np.ndarray) -> np.ndarray:
    """(M,) determinants of (M, 3, 3) matrices by the cofactor expansion (no LAPACK call)."""
    return (m[:, 0, 0] * (m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1])
            - m[:, 0, 1] * (m[:, 1, 0] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 0])
            + m[:, 0, 2] * (m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0]))


def _largest_singular(mats: np.ndarray) -> np.ndarray:
    """(M,) largest singular values of (M, 3, 3) matrices in closed form: the square root of the
    largest eigenvalue of the Gram matrix G = F^T F by the trigonometric formula for symmetric
    3 x 3 matrices (no per-matrix SVD); relative accuracy ~1e-15 on the largest value."""
    if not mats.shape[0]:
        return np.zeros(0)
    g = np.einsum("mki,mkj->mij", mats, mats)
    q = (g[:, 0, 0] + g[:, 1, 1] + g[:, 2, 2]) / 3
    off = g[:, 0, 1] ** 2 + g[:, 0, 2] ** 2 + g[:, 1, 2] ** 2
    d0, d1, d2 = g[:, 0, 0] - q, g[:, 1, 1] - q, g[:, 2, 2] - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2 * off) / 6)
    safe = np.where(p > 0, p, 1.0)
    b = (g - q[:, None, None] * np.eye(3)) / safe[:, None, None]
    half_det = np.clip(_det3(b) / 2, -1.0, 1.0)
    top = q + 2 * p * np.cos(np.arccos(half_det) / 3)
    top = np.maximum(top, g[:, [0, 1, 2], [0, 1, 2]].max(axis=1))  # >= every diagonal entry
    return np.sqrt(np.maximum(top, 0.0))


def shrink(counts: np.ndarray) -> np.ndarray:
    """Child / parent standard deviation per axis for ``counts`` children along it: 1/sqrt(m)."""
    return 1.0 / np.sqrt(counts)


def plan(scale_log: np.ndarray, rotation: np.ndarray, jac: np.ndarray,
         curv: np.ndarray) -> SplitPlan:
    """The children per axis of M splats (rest log-scales (M, 3), quaternions (M, 4),
    Jacobians (M, 3, 3), :func:`curvature` (M, 3)) by the module's rule, before the cap."""
    sigma, rot = _frames(scale_log, rotation)
    return plan_frames(sigma, rot, jac, curv)


def plan_frames(sigma: np.ndarray, rot: np.ndarray, jac: np.ndarray, curv: np.ndarray,
                max_children: int = MAX_CHILDREN) -> SplitPlan:
    """:func:`plan` from the extents (M, 3) and axes (M, 3, 3) (columns) themselves, at most
    ``max_children`` per splat: a surfel disc passes its two axes and a zero third extent
    (never split along it)."""
    jac = np.asarray(jac, np.float64)
    m = jac.shape[0]
    det = _det3(jac)
    uniform = np.cbrt(np.abs(det))
    ok = (uniform > 0) & np.isfinite(uniform) & np.isfinite(curv).all(axis=1) & \
        np.isfinite(sigma).all(axis=1) & (sigma.max(axis=1, initial=0) > 0)
    curved = ok & (curv.max(axis=1, initial=0) > AFFINE_FLOOR)
    norm = np.where(ok, uniform, 1.0)
    nonsim = jac / norm[:, None, None]
    longest = np.where(ok, sigma.max(axis=1, initial=0), 1.0)
    counts = np.ones((m, 3), dtype=np.int64)

    def excesses(cnt: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        factor = nonsim[rows] @ (rot[rows] * (sigma[rows] * shrink(cnt[rows]))[:, None, :])
        stretch = _largest_singular(factor) / (STRETCH_LIMIT * longest[rows])
        stretch = np.where(curved[rows], stretch, 0.0)
        bend = np.where(curved[rows, None], curv[rows] * shrink(cnt[rows]) / CURVE_LIMIT, 0.0)
        axis = np.where(stretch >= bend.max(axis=1, initial=0),
                        np.argmax(np.linalg.norm(factor, axis=1), axis=1),
                        np.argmax(bend, axis=1))
        return np.maximum(stretch, bend.max(axis=1, initial=0)), axis, factor

    active = np.flatnonzero(curved)
    excess = np.zeros(m)
    if active.size:
        excess[active] = excesses(counts, active)[0]
    active = active[excess[active] > 1]
    while active.size:
        ex, axis, _ = excesses(counts, active)
        active, axis = active[ex > 1], axis[ex > 1]
        nxt = counts[active].copy()
        nxt[np.arange(active.size), axis] += 1
        fits = nxt.prod(axis=1) <= max_children
        active = active[fits]
        counts[active] = nxt[fits]
    return SplitPlan(counts, excess)


def cap(split_plan: SplitPlan, moved: int, growth: float = GROWTH_CAP) -> SplitPlan:
    """``split_plan`` with at most ``growth`` x ``moved`` new splats: the splats with the
    largest excess first (ties by row), the rest kept whole."""
    extra = split_plan.counts.prod(axis=1) - 1
    budget = int(np.floor(growth * moved))
    if extra.sum() <= budget:
        return split_plan
    order = np.argsort(-split_plan.excess, kind="stable")
    order = order[extra[order] > 0]
    keep = order[np.cumsum(extra[order]) <= budget]
    counts = np.ones_like(split_plan.counts)
    counts[keep] = split_plan.counts[keep]
    return SplitPlan(counts, split_plan.excess, int(order.size - keep.size))


def _axis_layout(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (m,) in parent sigmas and binomial weights (m,) of m children along one axis."""
    c = 1.0 / np.sqrt(m)
    j = np.arange(m)
    return (2 * j - (m - 1)) * c, np.array([comb(m - 1, i) for i in j], float) / 2 ** (m - 1)


def layout(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For one count triple (3,): offsets (n, 3) in parent sigmas and weights (n,) of its n
    children, axis 0 slowest (child 0: the lowest offsets)."""
    parts = [_axis_layout(int(m)) for m in counts]
    grids = np.meshgrid(*[p[0] for p in parts], indexing="ij")
    weights = np.meshgrid(*[p[1] for p in parts], indexing="ij")
    return (np.stack([g.ravel() for g in grids], axis=1),
            weights[0].ravel() * weights[1].ravel() * weights[2].ravel())


def child_opacity(logit: np.ndarray, power: np.ndarray) -> np.ndarray:
    """Logit of 1 - (1 - alpha)^power for opacity logits (M,) and powers (M,): float32."""
    lg = np.asarray(logit, np.float64)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        softplus = np.logaddexp(0.0, lg)  # -log(1 - alpha)
        tau = power * softplus
        out = np.log(-np.expm1(-tau)) + tau  # log(a') - log(1 - a')
    out = np.where(np.isposinf(lg), np.inf, np.where(np.isneginf(lg), -np.inf, out))
    return out.astype(np.float32)


@dataclass
class Children:
    """The rest-state children of the split splats: parent (C,) model rows, child (C,) number
    within the parent, centers (C, 3), scale_log (C, 3), opacity (C,) logits or None; sorted by
    (parent, child)."""

    parent: np.ndarray
    child: np.ndarray
    centers: np.ndarray
    scale_log: np.ndarray
    opacity: np.ndarray | None


def children(model: PointModel, rows: np.ndarray, counts: np.ndarray) -> Children:
    """Children in rest space of splats ``rows`` (P,) with ``counts`` (P, 3) (see the module
    docstring: offsets along the axes, shrunk axes, the opacity rule)."""
    g = model.gaussians
    sigma, rot = _frames(g.scale_log[rows], g.rotation[rows])
    parts: list[tuple] = []
    for combo in np.unique(counts, axis=0):
        sel = np.flatnonzero((counts == combo).all(axis=1))
        offsets, weights = layout(combo)
        n = offsets.shape[0]
        c = shrink(combo.astype(np.float64))
        local = offsets[None, :, :] * sigma[sel, None, :]  # (P, n, 3) along the axes
        centers = model.positions[rows[sel], None, :] + np.einsum("pij,pnj->pni", rot[sel], local)
        scale = np.broadcast_to(g.scale_log[rows[sel]].astype(np.float64)[:, None, :]
                                + np.log(c), (sel.size, n, 3))
        opacity = None
        if g.opacity is not None:
            power = np.broadcast_to(weights / c.prod(), (sel.size, n)).ravel()
            opacity = child_opacity(np.repeat(g.opacity[rows[sel]], n), power)
        parts.append((np.repeat(rows[sel], n), np.tile(np.arange(n), sel.size),
                      centers.reshape(-1, 3), scale.reshape(-1, 3), opacity))
    parent = np.concatenate([p[0] for p in parts])
    order = np.lexsort((np.concatenate([p[1] for p in parts]), parent))
    opacity = None if g.opacity is None else np.concatenate([p[4] for p in parts])[order]
    return Children(parent[order], np.concatenate([p[1] for p in parts])[order],
                    np.concatenate([p[2] for p in parts])[order],
                    np.concatenate([p[3] for p in parts])[order].astype(g.scale_log.dtype),
                    opacity)


def take(model: PointModel, rows: np.ndarray) -> PointModel:
    """The points ``rows`` (R,) of a model without faces, every per-point array and the PLY
    source's vertex rows included (its ascii text and quantised codes dropped)."""
    def t(a):
        return None if a is None else a[rows]

    g = model.gaussians
    gaussians = None if g is None else Gaussians(t(g.scale_log), t(g.rotation), t(g.opacity),
                                                 t(g.sh_dc), t(g.sh_rest))
    return replace(model, positions=model.positions[rows], normals=t(model.normals),
                   colors=t(model.colors), radius=t(model.radius), axes=t(model.axes),
                   gaussians=gaussians, source=_source_rows(model.source, rows))


def _source_rows(source, rows: np.ndarray):
    if source is None or source.element("vertex") is None:
        return source
    elements = [replace(el, data=el.data[rows], ascii_text=None) if el.name == "vertex" else el
                for el in source.elements]
    return replace(source, elements=elements, quantised=None)


def concat(a: PointModel, b: PointModel) -> PointModel:
    """``a``'s points followed by ``b``'s (same fields, as from :func:`take` of one model)."""
    def c(x, y):
        return None if x is None else np.concatenate([x, y])

    ga, gb = a.gaussians, b.gaussians
    gaussians = None if ga is None else Gaussians(
        c(ga.scale_log, gb.scale_log), c(ga.rotation, gb.rotation), c(ga.opacity, gb.opacity),
        c(ga.sh_dc, gb.sh_dc), c(ga.sh_rest, gb.sh_rest))
    source = a.source
    if source is not None and source.element("vertex") is not None:
        va, vb = source.element("vertex"), b.source.element("vertex")
        grown = replace(va, data=np.concatenate([va.data, vb.data]), ascii_text=None)
        source = replace(source, elements=[grown if el.name == "vertex" else el
                                           for el in source.elements], quantised=None)
    return replace(a, positions=c(a.positions, b.positions), normals=c(a.normals, b.normals),
                   colors=c(a.colors, b.colors), radius=c(a.radius, b.radius),
                   axes=c(a.axes, b.axes), gaussians=gaussians, source=source)


Transform = Callable[[PointModel, PointModel, np.ndarray, np.ndarray, str, dict | None], None]


def wanted(model: PointModel, rows: np.ndarray, jac: np.ndarray, field: Field
           ) -> tuple[np.ndarray, SplitPlan]:
    """The candidate splats ``rows`` (R,) (Jacobians ``jac`` (R, 3, 3)) with finite centres,
    scales and rotations (R',) and the rule's :class:`SplitPlan` for them, before the cap.
    Each splat's decision depends on that splat alone (the streamed path tests the splats a
    chunk at a time and caps them all at once)."""
    g = model.gaussians
    finite = np.isfinite(model.positions[rows]).all(axis=1) & \
        np.isfinite(g.scale_log[rows]).all(axis=1) & np.isfinite(g.rotation[rows]).all(axis=1)
    rows, jac = rows[finite], jac[finite]
    if getattr(field, "own_jacobians", False) and rows.size:  # as a one-shot run (--reuse)
        jac = field(model.positions[rows], True)[1]
    sigma, rot = _frames(g.scale_log[rows], g.rotation[rows])
    curv = curvature(model.positions[rows], sigma, rot, field) if rows.size else np.zeros((0, 3))
    return rows, plan(g.scale_log[rows], g.rotation[rows], jac, curv)


def deformed_children(model: PointModel, rows: np.ndarray, counts: np.ndarray, field: Field,
                      *, covariance: str, transform: Transform, stats: dict | None = None,
                      dtype=None) -> tuple[Children, PointModel, np.ndarray]:
    """The children of splats ``rows`` (P,) with ``counts`` (P, 3) (:func:`children`), each
    moved by ``field`` at its own centre and deformed by its own J (``transform``): the
    rest-state :class:`Children`, the deformed children (C points, :func:`take` rows of
    ``model``; positions of ``dtype``, default the model's) and their Jacobians (C, 3, 3)."""
    kids = children(model, rows, counts)
    rest = take(model, kids.parent)
    rest.positions = kids.centers
    rest.gaussians.scale_log = kids.scale_log
    if kids.opacity is not None:
        rest.gaussians.opacity = kids.opacity
    moved_pos, kid_jac = field(kids.centers, True)
    deformed = rest.copy()
    deformed.positions = moved_pos.astype(model.positions.dtype if dtype is None else dtype)
    transform(rest, deformed, np.arange(rest.n_points), kid_jac, covariance, stats)
    return kids, deformed, kid_jac


def put_first(out: PointModel, kids: Children, deformed: PointModel, *,
              copy: bool = False) -> PointModel:
    """``out`` (a copy with ``copy``) with each split parent's row holding its child 0 (the
    rows of ``deformed`` where ``kids.child`` is 0); the PLY source's quantised codes
    dropped."""
    first = kids.child == 0
    result = out.copy() if copy else out
    for name in ("positions", "normals", "colors", "radius", "axes"):
        arr = getattr(result, name)
        if arr is not None:
            arr[kids.parent[first]] = getattr(deformed, name)[first]
    for name in ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
        arr = None if result.gaussians is None else getattr(result.gaussians, name)
        if arr is not None:
            arr[kids.parent[first]] = getattr(deformed.gaussians, name)[first]
    if result.source is not None and result.source.element("vertex") is not None:
        result = replace(result, source=replace(result.source, quantised=None))
    return result


def count_stats(stats: dict | None, chosen: SplitPlan) -> None:
    """Add ``chosen``'s split_capped, split_splats and split_children to ``stats``."""
    if stats is None:
        return
    split = chosen.split
    stats["split_capped"] = stats.get("split_capped", 0) + chosen.capped
    stats["split_splats"] = stats.get("split_splats", 0) + int(split.sum())
    stats["split_children"] = stats.get("split_children", 0) + \
        int(chosen.counts[split].prod(axis=1).sum())


def split_splats(model: PointModel, out: PointModel, rows: np.ndarray, jac: np.ndarray,
                 field: Field, *, moved: int, covariance: str, transform: Transform,
                 stats: dict | None = None) -> PointModel:
    """``out`` (the deformed ``model``) with the candidate splats ``rows`` (R,) (free-region
    rows, Jacobians ``jac`` (R, 3, 3)) that the rule splits replaced by their deformed children
    (see the module docstring for the rule, the cap over ``moved`` splats and the order).
    ``field`` evaluates the deformation at rest points; ``transform(rest, deformed, idx, jac,
    covariance, stats)`` deforms the attributes of rows ``idx``. ``stats`` receives
    split_splats, split_children, split_capped and parent_rows (the parent row of each
    appended child)."""
    g = model.gaussians
    if g is None or model.faces is not None or rows.size == 0:
        return out
    rows, want = wanted(model, rows, jac, field)
    chosen = cap(want, moved)
    count_stats(stats, chosen)
    split = chosen.split
    if not split.any():
        return out
    kids, deformed, kid_jac = deformed_children(
        model, rows[split], chosen.counts[split], field, covariance=covariance,
        transform=transform, stats=stats, dtype=out.positions.dtype)
    if stats is not None and "child_jacobians" in stats:  # asked for (benchmarks): (C, 3, 3)
        stats["child_jacobians"] = (kids.parent, kids.child, kid_jac)
    return assemble(model, out, kids, deformed, stats)


def assemble(model: PointModel, out: PointModel, kids, deformed: PointModel,
             stats: dict | None) -> PointModel:
    """``out`` with child 0 of each split parent in its parent's row and the other children
    appended in order (``stats["parent_rows"]``: the parent row of every appended child); the
    one assembly of split splats and split surfel discs."""
    first = kids.child == 0
    if stats is not None:
        stats["parent_rows"] = np.concatenate([stats.get("parent_rows", np.zeros(0, np.int64)),
                                               kids.parent[~first]])
    result = put_first(out, kids, deformed, copy=out is model)
    return concat(result, take(deformed, np.flatnonzero(~first)))


def check_mode(split: str) -> str:
    if split not in SPLIT_MODES:
        raise InputError(f"gaussians.split: expected one of {', '.join(SPLIT_MODES)}, "
                         f"got {split!r}")
    return split
