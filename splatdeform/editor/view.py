"""Viewer buffers for the editor, pure numpy: colours by region, normal shading, point sizes and
viser's packed Gaussian splat buffer. No web imports (the benchmark and tests use them too)."""

from __future__ import annotations

import numpy as np

from ..model import PointModel

SH_C0 = 0.28209479177387814
FIXED_RGB = np.array([50, 110, 255], dtype=np.float32)
HANDLE_RGB = np.array([255, 120, 30], dtype=np.float32)
NEUTRAL_RGB = (185, 185, 185)
TINT = 0.55  # how much of the region colour a fixed / handle point shows


def up_direction(model: PointModel) -> str:
    """The viewer's up axis: 3DGS scenes are stored y-down, everything else is +y up."""
    return "-y" if model.gaussians is not None else "+y"


def base_colors(model: PointModel) -> np.ndarray:
    """(N, 3) uint8 colours as stored: RGB, the SH DC colour of 3DGS, else neutral grey."""
    if model.colors is not None:
        return np.asarray(model.colors, dtype=np.uint8)
    g = model.gaussians
    if g is not None and g.sh_dc is not None:
        rgb = np.clip(0.5 + SH_C0 * g.sh_dc.astype(np.float32), 0.0, 1.0)
        return (rgb * 255.0 + 0.5).astype(np.uint8)
    return np.tile(np.array(NEUTRAL_RGB, dtype=np.uint8), (model.n_points, 1))


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
    light = np.array([0.35, 0.8 * sign, 0.5], dtype=np.float32)
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


_TRIU = np.array([0, 1, 2, 4, 5, 8])


def splat_buffer(centers: np.ndarray, covariances: np.ndarray, rgba: np.ndarray,
                 out: np.ndarray | None = None) -> np.ndarray:
    """viser's packed Gaussian buffer (N, 8) uint32: centers (N, 3) float32, a reserved word,
    the upper triangle of covariances (N, 3, 3) as 6 float16, RGBA (N, 4) uint8."""
    n = centers.shape[0]
    buf = np.empty((n, 8), dtype=np.uint32) if out is None else out
    buf[:, 0:3] = np.ascontiguousarray(centers, dtype=np.float32).view(np.uint32)
    buf[:, 3] = 0
    triu = np.ascontiguousarray(covariances.reshape(n, 9)[:, _TRIU], dtype=np.float16)
    buf[:, 4:7] = triu.view(np.uint32)
    buf[:, 7] = np.ascontiguousarray(rgba, dtype=np.uint8).view(np.uint32)[:, 0]
    return buf
