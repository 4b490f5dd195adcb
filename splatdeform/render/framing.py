"""The default camera: fit the model's robust projected extent, flat scenes seen obliquely,
zoom, and clip distances computed from the model.

Framing (:func:`fit_frame`): the orbit direction (azimuth, elevation, roll about the up axis)
fixes the view; the target and distance are then chosen so that the points' projection fills
the field of view (``margin`` 5 %), measured on the points themselves, not on a bounding
sphere. Isolated outliers and floaters do not shrink the subject: the points within the
:data:`ROBUST_PERCENTILES` of each view coordinate are framed when framing every point would
need :data:`OUTLIER_GAIN` times the distance; a :class:`FramingNote` then says how many points
fall outside the frame. A scene whose extent along the up axis is below :data:`FLAT_RATIO` of
both horizontal extents (airborne LiDAR, terrain) gets :data:`FLAT_ELEVATION` degrees of
elevation by default instead of :data:`DEFAULT_ELEVATION`. ``zoom`` F narrows the field of view
about the target by F (the camera stays where the lens angle ``fov`` put it): the written camera
holds the narrowed angle, so a camera file re-renders the zoomed image.

The changed part of an edit (:func:`moved_mask`): the points whose displacement is at least
:data:`CHANGED_SHARE` of the largest one (the handle and the free region as they visibly move;
the fixed region and the fit's residual wobble stay out). Batch reports frame a close-up on it.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable

import numpy as np

from splatdeform.errors import InputError

ROBUST_PERCENTILES = (0.5, 99.5)
OUTLIER_GAIN = 1.15      # robust framing when framing every point needs 15 % more distance
FLAT_RATIO = 0.2         # up extent / smaller horizontal extent below this: a flat scene
FLAT_ELEVATION = 40.0    # degrees: the default elevation of flat scenes
DEFAULT_ELEVATION = 20.0
MAX_SAMPLE = 400_000     # points framed (a regular stride over larger sets)
CHANGED_SHARE = 0.05     # a point moved when its displacement is 5 % of the largest or more
STILL = 1e-9             # largest displacement / model diagonal below this: nothing moved


class FramingNote(UserWarning):
    """Framing left some outlying points outside the picture (one line on stderr)."""


def stacked(point_sets: Iterable[np.ndarray], limit: int = MAX_SAMPLE) -> np.ndarray:
    """(M, 3) float64: the union of the (M_i, 3) ``point_sets``, each thinned by a regular
    stride to at most ``limit`` points together. Raises InputError for an empty or ill-shaped
    set."""
    sets = []
    for pts in point_sets:
        a = np.asarray(pts)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise InputError(f"point set: expected a non-empty (M, 3) array, got shape {a.shape}")
        sets.append(a)
    if not sets:
        raise InputError("point_sets: expected at least one point array, got none")
    total = sum(len(a) for a in sets)
    step = max(1, math.ceil(total / limit))
    out = np.concatenate([np.asarray(a[::step], dtype=np.float64) for a in sets])
    finite = np.all(np.isfinite(out), axis=1)
    return out if finite.all() else out[finite]


def is_flat(points: np.ndarray, up: str) -> bool:
    """True when the robust extent of (M, 3) ``points`` along the ``up`` axis is below
    :data:`FLAT_RATIO` of each horizontal one (LiDAR tiles, terrain; not a lying pole)."""
    lo, hi = np.percentile(points, ROBUST_PERCENTILES, axis=0)
    extent = hi - lo
    axis = "xyz".index(up[1])
    horizontal = min(float(extent[i]) for i in range(3) if i != axis)
    return horizontal > 0 and float(extent[axis]) < FLAT_RATIO * horizontal


def default_elevation(points: np.ndarray, up: str) -> float:
    """:data:`FLAT_ELEVATION` for flat scenes (:func:`is_flat`), else :data:`DEFAULT_ELEVATION`."""
    return FLAT_ELEVATION if is_flat(points, up) else DEFAULT_ELEVATION


def zoomed_fov(fov: float, zoom: float) -> float:
    """The vertical angle (degrees) of a ``fov`` lens narrowed ``zoom`` times about its axis."""
    if not (zoom > 0 and math.isfinite(zoom)):
        raise InputError(f"--zoom/render.zoom: expected a number > 0, got {zoom}")
    if zoom == 1.0:
        return float(fov)   # as given: the camera file holds the very number
    return math.degrees(2.0 * math.atan(math.tan(math.radians(fov) / 2.0) / zoom))


def _fit(x: np.ndarray, y: np.ndarray, z: np.ndarray, tx: float, ty: float
         ) -> tuple[float, float, float, float]:
    """(cx, cy, cz, distance) framing view coordinates x (right), y (up), z (toward the
    camera): the eye at (cx, cy, cz + distance) looking down -z sees every point within the
    half-angle tangents tx, ty, the projection centred."""
    cx, cy = (x.min() + x.max()) / 2.0, (y.min() + y.max()) / 2.0
    cz = (z.min() + z.max()) / 2.0
    span = max(float(np.ptp(x)), float(np.ptp(y)), float(np.ptp(z)), 1e-9)
    dist = 1.0
    for _ in range(4):   # perspective: re-centre the projection, then fit the distance again
        zr = z - cz
        dist = float(np.max(np.maximum(np.abs(x - cx) / tx, np.abs(y - cy) / ty) + zr))
        dist = max(dist, float(zr.max()) + 1e-3 * span, 1e-3 * span)
        depth = dist - zr
        u, v = (x - cx) / depth, (y - cy) / depth
        cx += (u.min() + u.max()) / 2.0 * dist
        cy += (v.min() + v.max()) / 2.0 * dist
    zr = z - cz
    dist = float(np.max(np.maximum(np.abs(x - cx) / tx, np.abs(y - cy) / ty) + zr))
    return cx, cy, cz, max(dist, float(zr.max()) + 1e-3 * span, 1e-3 * span)


def fit_frame(pts: np.ndarray, basis: tuple[np.ndarray, np.ndarray, np.ndarray], fov: float,
              *, aspect: float = 1.0, margin: float = 1.05
              ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(position, target, near, far) of a camera looking along ``basis`` (right, true_up,
    forward: three (3,) orthonormal vectors) with a ``fov`` degrees lens that frames the (M, 3)
    points ``pts`` (:func:`stacked`) at width / height ``aspect`` (see the module doc). Warns
    (:class:`FramingNote`) when outliers are left out."""
    if not (0 < fov < 180):
        raise InputError(f"fov: expected degrees in (0, 180), got {fov}")
    if pts.shape[0] == 0:
        raise InputError("point set: expected finite coordinates, got none")
    ref = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    local = pts - ref
    right, true_up, forward = basis
    back = -forward
    x, y, z = local @ right, local @ true_up, local @ back
    ty = math.tan(math.radians(fov) / 2.0) / margin
    tx = ty * aspect
    full = _fit(x, y, z, tx, ty)
    lows = [np.percentile(c, ROBUST_PERCENTILES[0]) for c in (x, y, z)]
    highs = [np.percentile(c, ROBUST_PERCENTILES[1]) for c in (x, y, z)]
    inside = np.ones(len(x), dtype=bool)
    for c, lo, hi in zip((x, y, z), lows, highs, strict=True):
        inside &= (c >= lo) & (c <= hi)
    cx, cy, cz, dist = full
    if inside.any() and not inside.all():
        robust = _fit(x[inside], y[inside], z[inside], tx, ty)
        if full[3] > OUTLIER_GAIN * robust[3]:
            cx, cy, cz, dist = robust
            out = _outside(x, y, z, robust, tx * margin, ty * margin)
            if out:
                warnings.warn(FramingNote(
                    f"framing: {out:,} of {len(x):,} points "
                    f"({100.0 * out / len(x):.2g} %) are isolated outliers outside the picture "
                    "(framed on the 0.5-99.5 percentile extent; --camera or --zoom below 1 "
                    "shows them)"), stacklevel=2)
    target = ref + cx * right + cy * true_up + cz * back
    position = target + dist * back
    depth = (dist + cz) - z            # every sampled point's depth from the eye
    span = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0
    far = float(depth.max()) * 1.01 + 1e-6 * span
    front = depth[depth > 0]
    near = max(float(front.min()) * 0.95 if front.size else far * 1e-4, far * 1e-4)
    return position, target, min(near, far * 0.5), far


def _outside(x: np.ndarray, y: np.ndarray, z: np.ndarray, fit: tuple[float, float, float, float],
             tx: float, ty: float) -> int:
    """How many points the camera ``fit`` (:func:`_fit`) leaves outside its field of view."""
    cx, cy, cz, dist = fit
    depth = dist - (z - cz)
    with np.errstate(divide="ignore", invalid="ignore"):
        seen = (depth > 0) & (np.abs(x - cx) <= tx * depth * 1.0001) & (
            np.abs(y - cy) <= ty * depth * 1.0001)
    return int((~seen).sum())


def moved_mask(before: np.ndarray, after: np.ndarray) -> np.ndarray | None:
    """(N,) bool: the points of (N, 3) ``before`` whose displacement to (N, 3) ``after`` is at
    least :data:`CHANGED_SHARE` of the largest displacement; None when the shapes differ or
    nothing moved (the largest displacement below :data:`STILL` of the model's diagonal, or
    no finite one)."""
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    if before.shape != after.shape or before.ndim != 2 or before.shape[0] == 0:
        return None
    with np.errstate(invalid="ignore", over="ignore"):
        moved = np.linalg.norm(after - before, axis=1)
    finite = np.isfinite(moved) & np.all(np.isfinite(before), axis=1)
    if not finite.any():
        return None
    largest = float(moved[finite].max())
    pts = before[finite]
    diagonal = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    if largest == 0.0 or largest <= STILL * diagonal:
        return None
    return finite & (moved >= CHANGED_SHARE * largest)


def clip_range(eye: np.ndarray, forward: np.ndarray, target: np.ndarray,
               point_sets: Iterable[np.ndarray]) -> tuple[float, float]:
    """(near, far) that keep every point of the (M_i, 3) ``point_sets`` in front of a camera at
    ``eye`` looking along unit ``forward`` (at ``target``) between the clip planes (near no
    closer than far / 10,000)."""
    pts = stacked(point_sets)
    depth = (pts - eye) @ forward
    if depth.size == 0 or depth.max() <= 0:   # nothing in front: any sane range (it warns)
        scale = float(np.linalg.norm(eye - np.asarray(target))) or 1.0
        return scale * 1e-3, scale * 10.0
    far = float(depth.max()) * 1.01
    front = depth[depth > 0]
    near = max(float(front.min()) * 0.95, far * 1e-4)
    return min(near, far * 0.5), far


def complete_clip(near: float | None, far: float | None, computed: tuple[float, float]
                  ) -> tuple[float, float]:
    """A camera file's ``near`` / ``far`` as written, a missing one (None) from ``computed``
    (:func:`clip_range`), kept in order."""
    cn, cf = computed
    if near is not None and far is not None:
        return near, far
    if near is not None:
        return near, max(cf, near * 2.0)
    if far is not None:
        return min(cn, far * 0.5), far
    return cn, cf
