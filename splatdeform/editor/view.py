"""What the editor page draws with, pure numpy: base colours, the splats' RGBA and a point size
(:mod:`.payload` uploads them). No web imports."""

from __future__ import annotations

import numpy as np

from ..model import PointModel
from ..render.splats import model_colors

NEUTRAL_RGB = (185, 185, 185)


def base_colors(model: PointModel) -> np.ndarray:
    """(N, 3) uint8 colours as stored: RGB, the SH DC colour of 3DGS, else neutral grey (the
    renderer's rule, :func:`splatdeform.render.splats.model_colors`)."""
    return model_colors(model, NEUTRAL_RGB)


def point_size(model: PointModel) -> float:
    """A splat diameter for the viewer: twice the median surfel radius, else the mean spacing of
    N points on the bounding box's surface."""
    if model.radius is not None and model.radius.size:
        return float(2.0 * np.median(model.radius))
    lo, hi = model.bbox()
    e = np.sort(hi - lo)[::-1]
    area = 2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]) or float(e[0] ** 2) or 1.0
    return float(1.5 * np.sqrt(area / max(model.n_points, 1)))


def splat_rgba(model: PointModel, colors: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 colour (N, 3) plus the 3DGS opacity sigmoid(logit) (opaque when absent)."""
    g = model.gaussians
    alpha = np.full(model.n_points, 255, dtype=np.uint8)
    if g is not None and g.opacity is not None:
        a = 1.0 / (1.0 + np.exp(-np.clip(g.opacity.astype(np.float32), -30, 30)))
        alpha = (a * 255.0 + 0.5).astype(np.uint8)
    return np.concatenate([np.clip(colors, 0, 255).astype(np.uint8), alpha[:, None]], axis=1)
