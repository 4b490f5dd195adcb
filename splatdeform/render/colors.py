"""Colour modes of a render (``--color`` / ``render.color``): the file's own colours (``rgb``),
or colours computed from the points: ``elevation`` along the up axis, ``intensity``,
``classification`` (the ASPRS LAS classes), ``region`` (the edit's regions; ``select``).

Default: the file's colours when it has them, else elevation for LiDAR (LAS/LAZ), else the
renderer's grey."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from splatdeform.errors import InputError
from splatdeform.io import LIDAR_EXTENSIONS
from splatdeform.io import is_lidar as _is_lidar
from splatdeform.model import PointModel, vertex_column

COLOR_MODES = ("rgb", "elevation", "intensity", "classification", "region")
LIDAR_SUFFIXES = LIDAR_EXTENSIONS   # declared by the formats (splatdeform.io)

# a perceptual ramp (low -> high): deep blue, teal, green, yellow, light
_RAMP = np.array([[48, 18, 120], [33, 110, 160], [40, 170, 110], [200, 210, 60],
                  [250, 240, 200]], dtype=np.float64)
# ASPRS LAS 1.4 standard classes; others get a colour from their number
_CLASSES = {0: (160, 160, 160), 1: (170, 170, 170), 2: (150, 110, 70), 3: (140, 200, 110),
            4: (80, 170, 60), 5: (30, 120, 40), 6: (220, 90, 60), 7: (255, 0, 255),
            8: (255, 255, 0), 9: (60, 120, 230), 10: (120, 120, 120), 11: (90, 90, 90),
            17: (200, 200, 230), 18: (255, 0, 128)}


def is_lidar(model: PointModel) -> bool:
    """A model read from LAS/LAZ (z-up, often without colours)."""
    return _is_lidar(model)


def default_color(model: PointModel) -> str:
    """``rgb`` for models with colours (or not LiDAR), else ``elevation``."""
    if model.colors is not None or model.gaussians is not None or not is_lidar(model):
        return "rgb"
    return "elevation"


def ramp(values: np.ndarray) -> np.ndarray:
    """(N,) values -> (N, 3) uint8 along the ramp, stretched over the 1st..99th percentile."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    x = _unit(v) * (len(_RAMP) - 1)
    out = np.stack([np.interp(x, np.arange(len(_RAMP)), _RAMP[:, c]) for c in range(3)], axis=1)
    return out.astype(np.uint8)


def point_colors(model: PointModel, mode: str, up: str = "+z") -> np.ndarray | None:
    """(N, 3) uint8 colours of ``mode`` (None for ``rgb``: the file's own)."""
    if mode not in COLOR_MODES:
        raise InputError(f"--color/render.color: expected one of {', '.join(COLOR_MODES)}, "
                         f"got {mode!r}")
    if mode == "rgb":
        return None
    if mode == "region":
        raise InputError("--color region: colours an edit's regions; use `splatdeform select "
                         "EDIT.yaml -o OUT.png`")
    if model.gaussians is not None:
        raise InputError(f"--color/render.color {mode}: Gaussian splat scenes render their own "
                         "colours (rgb)")
    if mode == "elevation":
        axis = "xyz".index(up[1])
        sign = -1.0 if up[0] == "-" else 1.0
        return ramp(sign * model.positions[:, axis])
    if mode == "intensity":
        key = f"--color/render.color {mode}"
        grey = 40 + 215 * _unit(vertex_column(model, "intensity", key))
        return np.repeat(grey[:, None], 3, axis=1).astype(np.uint8)
    key = f"--color/render.color {mode}"
    classes = np.asarray(vertex_column(model, "classification", key)).astype(np.int64)
    table = np.array([_CLASSES.get(c, ((c * 97) % 256, (c * 57) % 256, (c * 29) % 256))
                      for c in range(256)], dtype=np.uint8)
    return table[np.clip(classes, 0, 255)]


def _unit(values: np.ndarray) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    lo, hi = np.percentile(v, [1, 99]) if v.size else (0.0, 1.0)
    return np.clip((v - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(v)


def colored(model: PointModel, mode: str | None, up: str = "+z") -> PointModel:
    """``model`` (arrays shared) with the colours of ``mode`` (None: its default)."""
    colors = point_colors(model, mode or default_color(model), up)
    return model if colors is None else replace(model, colors=colors)
