"""3D Gaussian splat fields as the renderer uploads them (3DGS file conventions in, floats out).

- covariance Sigma = R S^2 R^T from the log-scales and the quaternion (w, x, y, z; normalised
  here), as 6 floats (xx, xy, xz, yy, yz, zz);
- colour: the stored colour when it is not just the loader's 8-bit rounding of f_dc (e.g. a
  preview coloured by region), else
  the SH degree-0 term 0.5 + C0 f_dc (unclamped; view-dependent bands are added in the shader),
  else a light grey; opacity: sigmoid(logit), 1 when absent;
- higher SH bands: ``f_rest`` as stored (channel-major: per channel, coefficients 1..r) and the
  full degree it holds (r = 3, 8, 15 -> degree 1, 2, 3).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from splatdeform.deform.gaussians import dc_to_colors, dc_to_rgb
from splatdeform.errors import InputError
from splatdeform.geometry import quaternion_to_matrix, triu6
from splatdeform.model import PointModel
from splatdeform.render.splats import DEFAULT_COLOR

SH_REST_PER_DEGREE = {1: 3, 2: 8, 3: 15}


@dataclass
class GaussianData:
    """cov: (N, 6) float32 (xx, xy, xz, yy, yz, zz). color: (N, 4) float32 (rgb, opacity).
    sh_rest: (N, 3 r) float32 channel-major f_rest, or None. degree: SH degree used (0..3).
    rest: r, f_rest coefficients per channel (the storage stride; >= the degree's count).
    shape: (N, 2) float32 per splat: log(largest / smallest axis) and the mean log-scale, from
    the float64 log-scales (the ``limited`` covariance mode needs both; a float32 eigen-solve of
    a thin splat's Sigma loses its smallest axis)."""

    cov: np.ndarray
    color: np.ndarray
    sh_rest: np.ndarray | None
    degree: int
    rest: int
    shape: np.ndarray


def covariances(scale_log: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(N, 3, 3) float64 Sigma = R diag(exp(scale_log))^2 R^T from (N, 3) log-scales and (N, 4)
    quaternions (w, x, y, z)."""
    rot = quaternion_to_matrix(rotation)
    s2 = np.exp(2.0 * np.asarray(scale_log, dtype=np.float64))
    return np.einsum("nij,nj,nkj->nik", rot, s2, rot)


def log_scale_shape(scale_log: np.ndarray) -> np.ndarray:
    """(N, 2) float32: the spread (max - min) and the mean of (N, 3) log-scales."""
    s = np.asarray(scale_log, dtype=np.float64)
    return np.ascontiguousarray(np.stack([np.ptp(s, axis=1), s.mean(axis=1)], axis=1),
                                dtype=np.float32)


def sh_layout(n_rest: int) -> tuple[int, int]:
    """(degree, coefficients per channel) of an f_rest block of ``n_rest`` floats (3 channels);
    the degree is the highest one fully present (0 when fewer than 3 per channel)."""
    per_channel = int(n_rest) // 3
    degree = max((d for d, r in SH_REST_PER_DEGREE.items() if per_channel >= r), default=0)
    return degree, per_channel


_BAND4_SAID: list[bool] = []


def warn_band4_not_drawn() -> None:
    """SH band 4 (a degree-4 file: SPZ v4, 72 f_rest) is kept in saves but not drawn: say so
    once per process."""
    if not _BAND4_SAID:
        _BAND4_SAID.append(True)
        warnings.warn("SH band 4 is kept in the files written but not drawn: renders and the "
                      "editor use SH bands 0-3", UserWarning, stacklevel=3)


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function, overflow-free, float64."""
    x = np.asarray(x, dtype=np.float64)
    return np.exp(-np.logaddexp(0.0, -x))


def _own_colors(model: PointModel) -> bool:
    """True when ``model.colors`` says more than the 8-bit rounding of the SH DC colour (the
    loader fills ``colors`` from f_dc when a 3DGS file has no red/green/blue)."""
    g = model.gaussians
    if model.colors is None:
        return False
    if g is None or g.sh_dc is None:
        return True
    derived = dc_to_colors(g.sh_dc)  # as the loader
    return not np.array_equal(np.asarray(model.colors), derived)


def gaussian_data(model: PointModel) -> GaussianData:
    """The upload arrays of a model with ``model.gaussians`` (see the module doc)."""
    g = model.gaussians
    if g is None:
        raise InputError("model: expected 3D Gaussian splat fields (model.gaussians), got none")
    n = model.n_points
    sigma = covariances(g.scale_log, g.rotation)
    color = np.empty((n, 4), dtype=np.float64)
    own_colors = _own_colors(model)
    if own_colors:  # stored colours win (also: previews coloured by region)
        color[:, :3] = np.asarray(model.colors, dtype=np.float64) / 255.0
    elif g.sh_dc is not None:
        color[:, :3] = dc_to_rgb(g.sh_dc)
    else:
        color[:, :3] = np.array(DEFAULT_COLOR) / 255.0
    color[:, 3] = 1.0 if g.opacity is None else sigmoid(g.opacity)
    degree, rest = (0, 0)
    sh_rest = None
    if g.sh_rest is not None and g.sh_dc is not None and not own_colors:
        degree, rest = sh_layout(np.asarray(g.sh_rest).shape[1])
        if rest > SH_REST_PER_DEGREE[3]:
            warn_band4_not_drawn()
        if degree:
            sh_rest = np.ascontiguousarray(np.asarray(g.sh_rest)[:, : 3 * rest], dtype=np.float32)
    return GaussianData(
        cov=triu6(sigma),
        color=np.ascontiguousarray(color, dtype=np.float32),
        sh_rest=sh_rest,
        degree=degree,
        rest=rest if degree else 0,
        shape=log_scale_shape(g.scale_log),
    )
