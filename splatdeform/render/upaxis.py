"""Which way is up in a file: the rule shared by ``render``, ``select``, ``deform --render``,
batch thumbnails, the editor and ``info``.

In order (``--up`` / ``render.up`` win over all of them):

1. 3D Gaussian splat scenes: ``-y`` (3DGS files are stored y-down).
2. LiDAR (LAS/LAZ): ``+z``.
3. Geo-referenced PLY / PCD / XYZ: ``+z``. A scan is geo-referenced when a header comment names
   a coordinate reference system (EPSG, CRS, UTM, WKT, PROJ, "spatial reference"), or when its
   horizontal coordinates are those of a projected CRS: the bounding-box centre's ``|x|`` or
   ``|y|`` is at least :data:`GEO_HORIZONTAL` (1e5; UTM eastings are 166,000-834,000 m,
   northings up to 10,000,000 m, state-plane and national grids alike) while ``|z|`` is
   below it (heights on Earth are under 9,000 m). Measured on the shared files: the UTM
   terrain (x 512,050, y 5,403,060) and the airborne LiDAR (x 635,620, y 848,900) are
   geo-referenced; the bunny, head, armadillo and the splat tiles (|coordinates| < 10) are not.
4. Otherwise ``+y`` (the PLY/OBJ modelling convention).

Several models render +z only when each of them is LiDAR or geo-referenced.

Rule 4 is a guess: nothing in such a file says which axis is up, and a scan's shape does not
settle it (Stanford's Lucy, scanned z-up, stands 3x taller along z than along y; a y-up car model
is as long along z). So the shape never changes the default, but it is reported:
``render``, ``select -o`` and ``deform --render`` print :func:`up_note` when a rule-4 model is at
least :data:`TALL_Z` times longer along z than along both x and y (the armadillo, bunny and head
of the shared data are not: 1.0, 0.8 and 1.2 along z over y).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

import numpy as np

GEO_HORIZONTAL = 1e5
#: a +y-by-convention model this many times longer along z than along x and y gets a note
TALL_Z = 1.5
_CRS_WORDS = re.compile(r"\b(epsg|crs|utm|wkt|proj4?|spatial[ _-]?ref(erence)?|"
                        r"geo-?referenced)\b", re.IGNORECASE)


def crs_comment(model: Any) -> str | None:
    """The first header comment of ``model``'s file that names a coordinate reference system."""
    source = getattr(model, "source", None)
    for comment in getattr(source, "comments", None) or ():
        if _CRS_WORDS.search(str(comment)):
            return str(comment)
    return None


def georeferenced(model: Any) -> str | None:
    """Why ``model`` counts as geo-referenced (rule 3 of the module doc), or None."""
    try:
        lo, hi = model.bbox()
        centre = (np.asarray(lo, np.float64) + np.asarray(hi, np.float64)) / 2.0
    except (AttributeError, ValueError):
        centre = np.full(3, np.nan)
    if np.all(np.isfinite(centre)) and max(abs(centre[0]), abs(centre[1])) >= GEO_HORIZONTAL \
            and abs(centre[2]) < GEO_HORIZONTAL:
        return "geo-referenced: horizontal coordinates beyond 1e5, a projected CRS"
    comment = crs_comment(model)
    if comment is not None:
        short = comment if len(comment) <= 40 else comment[:37] + "..."
        return f'geo-referenced: a CRS comment "{short}"'
    return None


def up_rule(models: Iterable[Any]) -> tuple[str, str]:
    """(up axis, why) for ``models`` by the rule of the module doc."""
    from splatdeform.render.colors import is_lidar

    models = list(models)
    if any(getattr(m, "gaussians", None) is not None for m in models):
        return "-y", "3D Gaussian splat scene: 3DGS files are y-down"
    if not models:
        return "+y", "the PLY/OBJ convention"
    reasons = []
    for m in models:
        reason = "LiDAR: LAS/LAZ are z-up" if is_lidar(m) else georeferenced(m)
        if reason is None:
            return "+y", "the PLY/OBJ convention: not LiDAR, not geo-referenced"
        reasons.append(reason)
    return "+z", reasons[0] if len(set(reasons)) == 1 else "LiDAR or geo-referenced"


def up_note(models: Iterable[Any]) -> str | None:
    """One line saying the up axis was assumed, for models drawn ``+y`` by rule 4 whose shape
    hints at z-up (:data:`TALL_Z`), with the option that changes it; else None."""
    models = list(models)
    up, why = up_rule(models)
    if up != "+y" or not models:
        return None
    tallest = 0.0
    for m in models:
        try:
            lo, hi = m.bbox()
            ext = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
        except (AttributeError, ValueError):
            continue
        if np.all(np.isfinite(ext)) and ext[2] > 0 and ext[2] >= TALL_Z * max(ext[0], ext[1]):
            tallest = max(tallest, ext[2] / max(ext[1], 1e-300))
    if not tallest:
        return None
    times = f"{tallest:.1f}x" if tallest < 1e3 else "far"
    return (f"up axis +y assumed ({why}); the model is {times} longer along z than along y: "
            "if it lies on its back, pass --up=+z (render.up in a config)")
