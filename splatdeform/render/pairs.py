"""Control-point pairs drawn over a rendered panel (``select -o`` of a ``points:`` edit): each
source a dark dot, each target a magenta dot, an arrow source -> target (magenta) with its head
facing the camera; check pairs in teal. Nothing is fitted.

Arrows are :class:`~splatdeform.render.overlay.Overlay` polylines in model coordinates (shaft,
then the two wings of the head, which lie in the plane of the arrow and the camera's right-up
plane, so the head reads as a flat ``>`` on screen). When the largest displacement is below
:data:`MIN_ARROW` of the scene's diagonal (a few centimetres of drift on a kilometre scan) the
arrows are drawn longer by a round factor so that they show; the legend says so and the target
dots sit at the arrow tips. At most :data:`MAX_ARROWS` pairs are drawn (evenly strided).
"""

from __future__ import annotations

import math

import numpy as np

from splatdeform.render.camera import View
from splatdeform.render.overlay import Overlay

SOURCE_COLOR = (20, 20, 20)
ARROW_COLOR = (230, 0, 200)      # magenta: in no region colour of the preview
CHECK_COLOR = (0, 170, 170)      # check pairs (held out of the fit)
MIN_ARROW = 0.04                 # the longest arrow: at least this of the scene's diagonal
HEAD = 0.3                       # arrow head: this of the arrow's length ...
MAX_HEAD = 0.03                  # ... at most this of the scene's diagonal
MAX_ARROWS = 20_000


def exaggeration(displacements: np.ndarray, diagonal: float) -> float:
    """1, or the round factor (1, 2 or 5 times a power of ten) that makes the longest of the
    (n, 3) ``displacements`` at least :data:`MIN_ARROW` of ``diagonal``."""
    longest = float(np.linalg.norm(displacements, axis=1).max()) if len(displacements) else 0.0
    if longest <= 0 or longest >= MIN_ARROW * diagonal:
        return 1.0
    need = MIN_ARROW * diagonal / longest
    power = 10.0 ** math.floor(math.log10(need))
    return next(f * power for f in (1, 2, 5, 10) if f * power >= need)


def arrow_polylines(sources: np.ndarray, tips: np.ndarray, forward: np.ndarray,
                    diagonal: float) -> np.ndarray:
    """(n, 6, 3) polylines: source, tip, wing 1, tip, wing 2, tip. The wings go back from the
    tip along the arrow and out across it in the plane normal to ``forward`` (3,) (the
    camera's viewing direction), so heads face the camera."""
    d = tips - sources
    length = np.linalg.norm(d, axis=1, keepdims=True)
    unit = d / np.where(length > 0, length, 1.0)
    side = np.cross(unit, forward)
    norm = np.linalg.norm(side, axis=1, keepdims=True)
    fallback = np.cross(unit, np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9
                        else np.array([1.0, 0.0, 0.0]))  # an arrow along the view
    side = np.where(norm > 1e-9, side / np.where(norm > 0, norm, 1.0), fallback)
    head = np.minimum(HEAD * length, MAX_HEAD * diagonal)
    back = tips - unit * head
    w1, w2 = back + 0.5 * side * head, back - 0.5 * side * head
    return np.stack([sources, tips, w1, tips, w2, tips], axis=1)


def pair_overlays(sources: np.ndarray, targets: np.ndarray, view: View, point_sets: list,
                  models: list, *, check: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[list[Overlay], str]:
    """The overlays of the pairs (sources, targets (n, 3) model units) and of the optional
    check pairs for a panel of ``view`` framing ``point_sets`` (the models' positions) of
    ``models``, and the legend to append (names the exaggeration and any striding)."""
    sets = [np.asarray(p, np.float64) for p in point_sets] + [sources, targets]
    pts = np.vstack([s.reshape(-1, 3) for s in sets])
    diagonal = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0
    camera = view.framed(sets, models, view.size[0] / view.size[1])
    forward = camera.basis()[2]
    scale = exaggeration(targets - sources, diagonal)
    overlays: list[Overlay] = []
    legend = "; pairs: source dot, arrow to target (magenta)"
    groups = [(sources, targets, ARROW_COLOR)]
    if check is not None and len(check[0]):
        groups.append((check[0], check[1], CHECK_COLOR))
        legend += ", check pairs teal"
    arrows: list[Overlay] = []
    for src, dst, color in groups:
        step = max(1, math.ceil(len(src) / MAX_ARROWS))
        if step > 1:
            legend += f" (every {step}th of {len(src):,} drawn)"
        src, dst = src[::step], dst[::step]
        tips = src + scale * (dst - src)
        overlays.append(Overlay(src, "markers", SOURCE_COLOR, 3))
        overlays.append(Overlay(tips, "markers", color, 3))
        arrows += [Overlay(line, "line", color, 2)
                   for line in arrow_polylines(src, tips, forward, diagonal)]
    if scale != 1:
        legend += f"; arrows drawn x{scale:g} (displacements small at this scale)"
    return overlays + arrows, legend
