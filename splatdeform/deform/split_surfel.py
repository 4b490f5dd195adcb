"""Splitting oriented surfel discs that one disc cannot follow (issue 46, item 3).

A surfel with tangent axes u, v (the disc {x + a u + b v : a^2 + b^2 <= 1}) is deformed by its
centre's Jacobian J: under a strong bend a large disc keeps one tangent plane and its rim lifts
off the curved surface (gaps on one side, overlaps on the other). ``gaussians.split: auto``
(the same key and default as for splats) replaces such a disc by children, each moved by the
field at its own centre and deformed by its own J.

**The rule** is the splat rule (:mod:`splatdeform.deform.split`) with the disc's two axes as
its principal axes and no third axis: extents |u|, |v| (the sigma points x +- u, x +- v, the
disc's rim), axes u/|u|, v/|v|, a zero third extent. The bend test e_k / l_k is the fit's
RBF part's second-order term (exactly 0 for an affine field: an affine map never splits), the
stretch test the non-similarity part of J on the two axes; only free-region discs are
candidates, the same growth cap applies, fixed rows stay bit-identical and in order, children
are appended after the originals (a split parent's row holds its child 0).

**Coverage** (the children's layout). Children are discs with the parent's axes scaled,
centred along the parent's axes. At rest their union covers the parent disc and stays inside
1.1 x the parent disc (both checked by ``tests/test_surfel_split.py``). That bound admits few
useful layouts: a child must reach the parent's rim near the other axis, so children centred
off the middle overshoot unless they stay large (the smallest children within 1.1 x stall at
0.68 of the parent's extent however many there are). Hence :data:`LAYOUTS`: 2 children at
+-0.2 (each 0.8 along, 1.04 across), 3 at 0, +-0.28 (0.72 along, 1.01 across) along one axis,
or 2 x 2 at (+-0.18, +-0.18) (0.84 on both axes), in disc units. The splat rule's counts per
axis (grown to at most 4 children, the layouts' largest) map to these: both axes split ->
2 x 2, else min(count, 3) along the split axis.

Round surfels (a radius and a normal, no axes) are not split: their children must be round,
and round discs covering a disc from off-centre overshoot it by far more than 1.1 x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.deform import split as sp
from splatdeform.deform.split_field import SIGMA_EXTENT, Field
from splatdeform.model import PointModel

#: (children along u, along v) -> (offsets (n, 2) in disc units, axis factors (2,)), child 0
#: the lowest offsets, u slowest
LAYOUTS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {
    (1, 1): (np.array([[0.0, 0.0]]), np.array([1.0, 1.0])),
    (2, 1): (np.array([[-0.2, 0.0], [0.2, 0.0]]), np.array([0.8, 1.04])),
    (3, 1): (np.array([[-0.28, 0.0], [0.0, 0.0], [0.28, 0.0]]), np.array([0.72, 1.01])),
    (2, 2): (np.array([[-0.18, -0.18], [-0.18, 0.18], [0.18, -0.18], [0.18, 0.18]]),
             np.array([0.84, 0.84])),
}
LAYOUTS[(1, 2)] = (LAYOUTS[(2, 1)][0][:, ::-1].copy(), LAYOUTS[(2, 1)][1][::-1].copy())
LAYOUTS[(1, 3)] = (LAYOUTS[(3, 1)][0][:, ::-1].copy(), LAYOUTS[(3, 1)][1][::-1].copy())


def has_surfel_axes(model: PointModel) -> bool:
    """True for a model of oriented surfel discs (tangent axes, no splats, no faces)."""
    return model.gaussians is None and model.axes is not None and model.faces is None


def splittable(model: PointModel) -> bool:
    """True when ``gaussians.split`` can split points of ``model``: splats or surfel axes."""
    return (model.gaussians is not None and model.faces is None) or has_surfel_axes(model)


def surfel_frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) extents and (M, 3, 3) axes (columns u/|u|, v/|v|, their normal) of M discs with
    tangent axes (M, 2, 3), such that the split's sigma steps are exactly u, v and 0."""
    axes = np.asarray(axes, np.float64)
    length = np.linalg.norm(axes, axis=2)  # (M, 2)
    sigma = np.zeros((axes.shape[0], 3))
    sigma[:, :2] = length / SIGMA_EXTENT
    unit = np.divide(axes, length[:, :, None], out=np.zeros_like(axes),
                     where=length[:, :, None] > 0)
    normal = np.cross(unit[:, 0], unit[:, 1])
    nlen = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, nlen, out=np.zeros_like(normal), where=nlen > 0)
    return sigma, np.stack([unit[:, 0], unit[:, 1], normal], axis=2)


def surfel_counts(counts: np.ndarray) -> np.ndarray:
    """(M, 3) the splat rule's children per axis mapped to a :data:`LAYOUTS` key (and 1 on
    the third axis): both disc axes split -> 2 x 2, else at most 3 along the split axis."""
    out = np.ones_like(counts)
    both = (counts[:, 0] > 1) & (counts[:, 1] > 1)
    out[:, :2] = np.minimum(counts[:, :2], 3)
    out[both, :2] = 2
    return out


def wanted_surfels(model: PointModel, rows: np.ndarray, jac: np.ndarray, field: Field
                   ) -> tuple[np.ndarray, sp.SplitPlan]:
    """The candidate discs ``rows`` (R,) (Jacobians ``jac`` (R, 3, 3)) with finite centres and
    axes (R',) and the rule's :class:`~splatdeform.deform.split.SplitPlan` for them (counts
    mapped by :func:`surfel_counts`), before the cap; each disc's decision is its own."""
    finite = np.isfinite(model.positions[rows]).all(axis=1) & \
        np.isfinite(model.axes[rows]).reshape(rows.size, -1).all(axis=1)
    rows, jac = rows[finite], jac[finite]
    if getattr(field, "own_jacobians", False) and rows.size:  # as a one-shot run (--reuse)
        jac = field(model.positions[rows], True)[1]
    sigma, rot = surfel_frames(model.axes[rows])
    curv = sp.curvature(model.positions[rows], sigma, rot, field) if rows.size \
        else np.zeros((0, 3))
    want = sp.plan_frames(sigma, rot, jac, curv, max_children=4)   # the layouts' largest
    return rows, sp.SplitPlan(surfel_counts(want.counts), want.excess)


@dataclass
class SurfelChildren:
    """The rest-state children of split discs: parent (C,) model rows, child (C,) number
    within the parent, centers (C, 3), axes (C, 2, 3); sorted by (parent, child)."""

    parent: np.ndarray
    child: np.ndarray
    centers: np.ndarray
    axes: np.ndarray


def surfel_children(model: PointModel, rows: np.ndarray, counts: np.ndarray
                    ) -> SurfelChildren:
    """Children in rest space of discs ``rows`` (P,) with ``counts`` (P, 3) (a
    :data:`LAYOUTS` key in the first two): centres x + o_u u + o_v v, axes (f_u u, f_v v)."""
    axes = np.asarray(model.axes[rows], np.float64)
    parts = []
    for combo in np.unique(counts[:, :2], axis=0):
        sel = np.flatnonzero((counts[:, :2] == combo).all(axis=1))
        offsets, factors = LAYOUTS[(int(combo[0]), int(combo[1]))]
        n = offsets.shape[0]
        centers = model.positions[rows[sel], None, :] + np.einsum(
            "nk,pkx->pnx", offsets, axes[sel])
        kid_axes = np.broadcast_to((axes[sel] * factors[None, :, None])[:, None],
                                   (sel.size, n, 2, 3))
        parts.append((np.repeat(rows[sel], n), np.tile(np.arange(n), sel.size),
                      centers.reshape(-1, 3), kid_axes.reshape(-1, 2, 3)))
    parent = np.concatenate([p[0] for p in parts])
    child = np.concatenate([p[1] for p in parts])
    order = np.lexsort((child, parent))
    return SurfelChildren(parent[order], child[order],
                          np.concatenate([p[2] for p in parts])[order],
                          np.concatenate([p[3] for p in parts])[order].astype(model.axes.dtype))


def deformed_surfel_children(model: PointModel, rows: np.ndarray, counts: np.ndarray,
                             field: Field, *, covariance: str, transform: sp.Transform,
                             stats: dict | None = None, dtype=None
                             ) -> tuple[SurfelChildren, PointModel, np.ndarray]:
    """The children of discs ``rows`` (P,) with ``counts`` (P, 3), each moved by ``field`` at
    its own centre and its axes and normal mapped by its own J: the rest-state children, the
    deformed children (C points, :func:`~splatdeform.deform.split.take` rows of ``model``)
    and their Jacobians (C, 3, 3)."""
    kids = surfel_children(model, rows, counts)
    rest = sp.take(model, kids.parent)
    rest.positions = kids.centers
    rest.axes = kids.axes
    moved_pos, kid_jac = field(kids.centers, True)
    deformed = rest.copy()
    deformed.positions = moved_pos.astype(model.positions.dtype if dtype is None else dtype)
    transform(rest, deformed, np.arange(rest.n_points), kid_jac, covariance, stats)
    return kids, deformed, kid_jac


def wanted_any(model: PointModel, rows: np.ndarray, jac: np.ndarray, field: Field
               ) -> tuple[np.ndarray, sp.SplitPlan]:
    """:func:`splatdeform.deform.split.wanted` for splats, :func:`wanted_surfels` for discs."""
    if has_surfel_axes(model):
        return wanted_surfels(model, rows, jac, field)
    return sp.wanted(model, rows, jac, field)


def deformed_any(model: PointModel, rows: np.ndarray, counts: np.ndarray, field: Field,
                 **kw):
    """:func:`splatdeform.deform.split.deformed_children` for splats,
    :func:`deformed_surfel_children` for discs."""
    if has_surfel_axes(model):
        return deformed_surfel_children(model, rows, counts, field, **kw)
    return sp.deformed_children(model, rows, counts, field, **kw)


def split_points(model: PointModel, out: PointModel, rows: np.ndarray, jac: np.ndarray,
                 field: Field, *, moved: int, covariance: str, transform: sp.Transform,
                 stats: dict | None = None) -> PointModel:
    """``out`` (the deformed ``model``) with the candidate splats or discs ``rows`` (R,)
    (Jacobians ``jac`` (R, 3, 3)) that the rule splits replaced by their deformed children,
    as :func:`splatdeform.deform.split.split_splats` (the same cap, order and ``stats``
    keys: split_splats counts split discs too)."""
    if not has_surfel_axes(model):
        return sp.split_splats(model, out, rows, jac, field, moved=moved,
                               covariance=covariance, transform=transform, stats=stats)
    if rows.size == 0:
        return out
    rows, want = wanted_surfels(model, rows, jac, field)
    chosen = sp.cap(want, moved)
    sp.count_stats(stats, chosen)
    split = chosen.split
    if not split.any():
        return out
    kids, deformed, _ = deformed_surfel_children(
        model, rows[split], chosen.counts[split], field, covariance=covariance,
        transform=transform, stats=stats, dtype=out.positions.dtype)
    return sp.assemble(model, out, kids, deformed, stats)
