"""What an edit selects, before (``splatdeform select``) and after (``deform``) the fit.

Counts of the fixed, moving (handle or curve band) and free points and the sizes of the boundary
rings that become the fit's constraints, and colours by region for a preview image.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from splatdeform.edit.config import EditConfig
from splatdeform.model import PointModel

# preview colours (uint8 RGB): free grey, fixed blue / its rings light blue, moving orange /
# its rings yellow
FREE_COLOR = (170, 170, 170)
FIXED_COLOR = (40, 90, 200)
FIXED_RING_COLOR = (120, 190, 255)
MOVING_COLOR = (230, 110, 20)
MOVING_RING_COLOR = (250, 215, 40)


@dataclass
class RegionCounts:
    """Point counts per region; ring sizes ring 1 first (empty when unknown)."""

    points: int
    fixed: int
    moving: int
    free: int
    fixed_rings: list[int] = field(default_factory=list)
    moving_rings: list[int] = field(default_factory=list)
    moving_name: str = "handle"


@dataclass
class Selection:
    """Masks (N,) bool of one edit's regions and the ring point indices (int64 arrays);
    ``pairs``: a ``points:`` edit's (pairs, check pairs or None) in model units, drawn by the
    preview (never fitted by ``select``), else None."""

    fixed: np.ndarray
    moving: np.ndarray
    fixed_rings: list[np.ndarray]
    moving_rings: list[np.ndarray]
    moving_name: str
    pairs: tuple | None = None

    def counts(self) -> RegionCounts:
        n = int(self.fixed.size)
        nf, nm = int(self.fixed.sum()), int(self.moving.sum())
        return RegionCounts(n, nf, nm, n - nf - nm, [int(r.size) for r in self.fixed_rings],
                            [int(r.size) for r in self.moving_rings], self.moving_name)


def moving_label(cfg: EditConfig) -> str:
    """What the moving region is called in the counts line (from the metaphor registry)."""
    from splatdeform.edit.metaphors import moving_label as label

    return label(cfg)


def select_regions(cfg: EditConfig, model: PointModel, base_dir: str | Path) -> Selection:
    """The edit's fixed and moving masks and rings, exactly as ``deform`` computes them (the
    same metaphors, checks and rings as :func:`splatdeform.deform.prepare_metaphors`, without
    the fit; a kind with constraints of its own shows them: its ``select`` hook). Raises
    RegionError / InputError / ConfigError like ``deform``."""
    from splatdeform.deform.regions import layout
    from splatdeform.edit.metaphors import hooked
    from splatdeform.edit.plain import fixed_mask, metaphors

    base_dir = Path(base_dir)
    fixed, found = fixed_mask(cfg, model, base_dir), metaphors(cfg, model, base_dir)
    shown = None   # (pairs, check pairs or None) of a points: edit
    for kind, _key, _entry in hooked(cfg, "select"):
        shown = kind.select(cfg, model, base_dir, fixed, found)
    if found or shown is None:
        lay = layout(model, fixed, found, continuity=cfg.boundary.continuity,
                     neighbors=cfg.boundary.neighbors)
        return Selection(lay.fixed, lay.moving, list(lay.fixed_rings), list(lay.moving_rings),
                         moving_label(cfg), shown)
    from splatdeform.deform.points import _rings_of_fixed  # no moving region: pairs only

    rings = _rings_of_fixed(model, fixed, cfg.boundary.continuity, cfg.boundary.neighbors) \
        if fixed.any() else []
    return Selection(fixed, np.zeros(model.n_points, dtype=bool), rings, [], "moving", shown)


def counts_of_deformation(deformation, moving_name: str = "handle") -> RegionCounts:
    """The counts of a precomputed :class:`~splatdeform.deform.Deformation` (ring sizes per
    ring when it was computed in this run; one total per region when it was reused)."""
    n = int(deformation.n_points)
    nf, nm = int(deformation.fixed.sum()), int(deformation.moving.sum())
    f_rings, m_rings = (list(r) for r in deformation.ring_sizes)
    if not f_rings and deformation.constraint_idx.size:
        in_fixed = int(deformation.fixed[deformation.constraint_idx].sum())
        f_rings, m_rings = [in_fixed], [int(deformation.constraint_idx.size) - in_fixed]
    pairs = int(deformation.constraint_idx.size) - sum(f_rings) - sum(m_rings)
    if not nm and not any(m_rings) and pairs > 0:   # a points edit: the pairs' constraints
        m_rings = [pairs]
    return RegionCounts(n, nf, nm, n - nf - nm, [int(v) for v in f_rings],
                        [int(v) for v in m_rings], moving_name)


def format_counts(c: RegionCounts) -> str:
    """One line: ``regions: fixed 1,200 (rings 40+38+37)  handle 300 (rings ...)  free 500``.
    A points edit has no moving region: its constraints outside the fixed rings are the pairs
    (``pairs 12``), and with no fixed region either it reads ``regions: none (the 12 pairs
    are the constraints)``."""

    def rings(sizes: list[int]) -> str:
        return f" (rings {'+'.join(f'{s:,}' for s in sizes)})" if any(sizes) else ""

    tail = f"  free {c.free:,}  of {c.points:,} points"
    pairs = sum(c.moving_rings) if not c.moving else 0
    if not c.moving and not c.fixed:
        return ("regions: none" + (f" (the {pairs:,} pairs are the constraints)" if pairs
                                   else "") + tail)
    moving = (f"  {c.moving_name} {c.moving:,}{rings(c.moving_rings)}" if c.moving
              else f"  pairs {pairs:,}" if pairs else "")
    return f"regions: fixed {c.fixed:,}{rings(c.fixed_rings)}{moving}{tail}"


def region_colors(sel: Selection) -> np.ndarray:
    """(N, 3) uint8 colours by region (rings lighter than the rest of their region)."""
    colors = np.empty((sel.fixed.size, 3), dtype=np.uint8)
    colors[:] = FREE_COLOR
    colors[sel.fixed] = FIXED_COLOR
    colors[sel.moving] = MOVING_COLOR
    for ring in sel.fixed_rings:
        colors[ring] = FIXED_RING_COLOR
    for ring in sel.moving_rings:
        colors[ring] = MOVING_RING_COLOR
    return colors


def preview_model(model: PointModel, sel: Selection) -> PointModel:
    """A shallow copy of ``model`` coloured by region (stored colours win over 3DGS colours in
    the renderer)."""
    return replace(model, colors=region_colors(sel))


def kind_overlays(cfg: EditConfig, model: PointModel) -> tuple[list, str]:
    """What ``select -o`` draws over the preview for the kinds that draw something of their
    own (their ``overlays`` hook: a curve's line before and after), and the legend to append;
    ([], "") when none does."""
    from splatdeform.edit.metaphors import hooked

    drawn, legend = [], ""
    for kind, key, entry in hooked(cfg, "overlays"):
        more, text = kind.overlays(key, entry, model, cfg.regions.units)
        drawn, legend = drawn + more, legend + text
    return drawn, legend
