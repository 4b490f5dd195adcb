"""Viewer buffers for the editor, pure numpy: colours by region, normal shading, point sizes and
viser's packed Gaussian splat buffer. No web imports (the benchmark and tests use them too)."""

from __future__ import annotations

import numpy as np

from ..model import PointModel
from ..render.splats import model_colors

FIXED_RGB = np.array([50, 110, 255], dtype=np.float32)
HANDLE_RGB = np.array([255, 120, 30], dtype=np.float32)
NEUTRAL_RGB = (185, 185, 185)
TINT = 0.55  # how much of the region colour a fixed / handle point shows


def up_direction(model: PointModel) -> str:
    """The viewer's up axis: 3DGS scenes are stored y-down, everything else is +y up."""
    return "-y" if model.gaussians is not None else "+y"


def base_colors(model: PointModel) -> np.ndarray:
    """(N, 3) uint8 colours as stored: RGB, the SH DC colour of 3DGS, else neutral grey (the
    renderer's rule, :func:`splatdeform.render.splats.model_colors`)."""
    return model_colors(model, NEUTRAL_RGB)


def tinted(colors: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(N, 3) float32 colours mixed toward blue (fixed, label 1) / orange (handles, >= 2)."""
    out = colors.astype(np.float32)
    fixed, handle = labels == 1, labels >= 2
    out[fixed] = (1 - TINT) * out[fixed] + TINT * FIXED_RGB
    out[handle] = (1 - TINT) * out[handle] + TINT * HANDLE_RGB
    return out


def shaded(colors: np.ndarray, normals: np.ndarray | None, up: str) -> np.ndarray:
    """(N, 3) uint8: float colours (N, 3) times a two-sided Lambert factor for a light from
    above and in front, so orientation shows; unshaded when there are no normals."""
    if normals is None:
        return np.clip(colors, 0, 255).astype(np.uint8)
    sign = -1.0 if up.startswith("-") else 1.0
    light = np.array([0.35, 0.8 * sign, 0.5 * sign], dtype=np.float32)
    light /= np.linalg.norm(light)
    factor = np.abs(normals @ light)
    factor *= 0.65
    factor += 0.35
    out = colors * factor[:, None]
    np.clip(out, 0, 255, out=out)
    return out.astype(np.uint8)


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


def splat_buffer(centers: np.ndarray, cov6: np.ndarray, rgba: np.ndarray) -> np.ndarray:
    """viser's packed Gaussian buffer (N, 8) uint32: centers (N, 3) float32, a reserved word,
    the covariances' upper triangles cov6 (N, 6) as float16, RGBA (N, 4) uint8."""
    packed = np.ascontiguousarray(rgba, dtype=np.uint8).view(np.uint32)[:, 0]
    return splat_rows(centers, cov6, packed)


def splat_rows(centers: np.ndarray, cov6: np.ndarray, rgba_packed: np.ndarray) -> np.ndarray:
    """(M, 8) uint32 packed rows from centers (M, 3), cov6 (M, 6) and RGBA packed as (M,)
    uint32; contiguous, so ``buffer[rows] = splat_rows(...)`` is one row-wise copy."""
    block = np.empty((centers.shape[0], 8), dtype=np.uint32)
    block[:, 0:3] = np.ascontiguousarray(centers, dtype=np.float32).view(np.uint32)
    block[:, 3] = 0
    block[:, 4:7] = to_float16(cov6).view(np.uint32)
    block[:, 7] = rgba_packed
    return block


_MIN_NORMAL16 = np.float32(2.0**-14)


def to_float16(a: np.ndarray) -> np.ndarray:
    """float32 -> float16 like ``astype``, fast also for values in float16's subnormal range
    (|x| < 2^-14, common for splat covariances: numpy's cast is ~40x slower there).
    Subnormals are round(|x| * 2^24) units of 2^-24 with the sign bit; 1024 units is exactly
    the smallest normal, so the two ranges join."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    mag = np.abs(a)
    small = mag < _MIN_NORMAL16
    with np.errstate(over="ignore"):  # beyond float16's range -> inf, as astype
        out = np.where(small, np.float32(0), a).astype(np.float16)
    sub = np.rint(np.fmin(mag, _MIN_NORMAL16) * np.float32(2.0**24)).astype(np.uint16)
    sub |= (np.signbit(a).astype(np.uint16) << 15)
    bits = out.view(np.uint16)
    np.copyto(bits, sub, where=small)
    return out
