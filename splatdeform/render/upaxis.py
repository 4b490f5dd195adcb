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
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

import numpy as np

GEO_HORIZONTAL = 1e5
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
