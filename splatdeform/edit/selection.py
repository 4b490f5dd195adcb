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
    """Masks (N,) bool of one edit's regions and the ring point indices (int64 arrays)."""

    fixed: np.ndarray
    moving: np.ndarray
    fixed_rings: list[np.ndarray]
    moving_rings: list[np.ndarray]
    moving_name: str

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
    the fit). Raises RegionError / InputError / ConfigError like ``deform``."""
    from splatdeform.deform.regions import layout
    from splatdeform.edit.plain import fixed_mask, metaphors

    base_dir = Path(base_dir)
    lay = layout(model, fixed_mask(cfg, model, base_dir), metaphors(cfg, model, base_dir),
                 continuity=cfg.boundary.continuity, neighbors=cfg.boundary.neighbors)
    return Selection(lay.fixed, lay.moving, lay.fixed_rings, lay.moving_rings, moving_label(cfg))


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


CURVE_BEFORE_COLOR = (200, 20, 20)
CURVE_AFTER_COLOR = (20, 160, 40)
CONTROL_POINT_COLOR = (20, 20, 20)


def curve_overlays(cfg: EditConfig, model: PointModel, base_dir: str | Path
                   ) -> tuple[list, str]:
    """What ``select -o`` draws over a curve edit's preview (the capture band is the coloured
    moving region): the curve snapped to the model (red), the curve after the edit (green: the
    same knots with each control point moved by moved_to - control_points) and the snapped
    control points (black dots); and the legend to append. ([], "") without a curve."""
    if cfg.curve is None:
        return [], ""
    from splatdeform.deform.curve import SAMPLES_PER_SPAN, snapped_curve
    from splatdeform.edit.metaphors.curve import points
    from splatdeform.render.overlay import Overlay

    given, moved, _ = points(cfg.curve, cfg.regions.units, model)
    curve = snapped_curve(model, given, degree=cfg.curve.degree,
                          parametrization=cfg.curve.parametrization)
    t = np.linspace(0, 1, SAMPLES_PER_SPAN * (given.shape[0] - 1) + 1)
    before = curve.points(t)
    after = before + curve.weights(t) @ (moved - given)
    overlays = [Overlay(before, "line", CURVE_BEFORE_COLOR, 3),
                Overlay(after, "line", CURVE_AFTER_COLOR, 3),
                Overlay(curve.control_points, "markers", CONTROL_POINT_COLOR, 4)]
    return overlays, "; curve red, moved green"
