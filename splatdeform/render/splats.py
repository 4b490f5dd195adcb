"""Per-point splat geometry for rendering: unit normals, tangent axes (u, v) and colors.

Sources, in order of preference:
- surfel axes (``model.axes``) as stored;
- surfel radius with normals: :func:`splatdeform.deform.arrays.radius_to_axes`;
  stored surfels smaller than the local sample spacing are enlarged (``fill_holes``);
- 3D Gaussians: the two largest principal axes of each Gaussian, ``GAUSSIAN_EXTENT`` standard
  deviations long, normal along the smallest one (an ellipse per Gaussian for callers that want
  surfels; the renderer draws Gaussians with EWA splatting, see ``gaussian_data.py``);
- anything else: round splats sized from the k-nearest-neighbour spacing (scipy cKDTree) so a
  dense scan renders without holes; missing normals are estimated by local PCA
  (:func:`splatdeform.deform.normals.pca_normals`).
Meshes need no splat axes (they render as triangles); missing mesh normals are area-weighted
face normals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.deform.arrays import axes_to_radius, normalize_rows, radius_to_axes
from splatdeform.deform.gaussians import dc_to_colors
from splatdeform.deform.normals import pca_normals  # the one estimator; also importable here
from splatdeform.geometry import quaternion_to_matrix
from splatdeform.interrupts import knn_query
from splatdeform.model import PointModel
from splatdeform.render.colors import is_lidar

DEFAULT_COLOR = (190, 190, 190)
GAUSSIAN_EXTENT = 1.5  # ellipse semi-axes in standard deviations
SPACING_NEIGHBORS = 8  # kNN used to estimate the sampling spacing
SPACING_FACTOR = 1.0  # splat radius = factor * mean distance to the SPACING_NEIGHBORS nearest
SPACING_CAP = 4.0  # outliers: spacing capped at this multiple of the median spacing
PCA_NEIGHBORS = 12  # kNN for missing normals (pca_normals)
# Beyond this many points (big scans, budget samples) per-point kNN costs ~35 us a point, so
# the spacing comes from a seeded subsample (scaled to the full density) and clouds without
# normals get flat discs in their best-fit plane (shaded flat; eye-dome lighting gives depth);
# LiDAR (LAS/LAZ) without normals always does, as LiDAR viewers draw it.
LARGE_CLOUD = 1_000_000
SPACING_SAMPLE = 100_000


@dataclass
class SplatGeometry:
    """What the renderer uploads besides positions.

    normals: (N, 3) float32 unit (zero where unknown). axes: (N, 2, 3) float32 tangent axes, or
    None for meshes. colors: (N, 3) uint8.
    """

    normals: np.ndarray
    axes: np.ndarray | None
    colors: np.ndarray


def model_colors(model: PointModel, default: tuple[int, int, int] = DEFAULT_COLOR
                 ) -> np.ndarray:
    """(N, 3) uint8 colors: stored colors, 3DGS DC colors, or ``default`` (a light grey)."""
    if model.colors is not None:
        return np.asarray(model.colors, dtype=np.uint8)
    g = model.gaussians
    if g is not None and g.sh_dc is not None:
        return dc_to_colors(g.sh_dc)
    return np.tile(np.array(default, dtype=np.uint8), (model.n_points, 1))


def gaussian_axes(scale_log: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ellipse of each Gaussian: (N, 2, 3) axes along its two largest principal directions,
    ``GAUSSIAN_EXTENT`` sigma long, and (N, 3) unit normals along the smallest one."""
    rot = quaternion_to_matrix(rotation)  # columns are the principal directions
    sigma = np.exp(np.asarray(scale_log, dtype=np.float64))
    order = np.argsort(-sigma, axis=1)  # largest first
    idx = np.arange(sigma.shape[0])[:, None]
    dirs = np.take_along_axis(rot, order[:, None, :], axis=2)  # (N, 3, 3) columns sorted
    s = sigma[idx, order]
    axes = np.stack([dirs[:, :, 0] * s[:, 0:1], dirs[:, :, 1] * s[:, 1:2]], axis=1)
    return axes * GAUSSIAN_EXTENT, dirs[:, :, 2]


def knn_spacing(positions: np.ndarray, k: int = SPACING_NEIGHBORS) -> np.ndarray:
    """(N,) mean distance of each point to its k nearest neighbours (cKDTree), capped at
    ``SPACING_CAP`` times the median."""
    from scipy.spatial import cKDTree

    pts = np.asarray(positions, dtype=np.float64)
    kk = min(k, pts.shape[0] - 1)
    if kk < 1:
        return np.ones(pts.shape[0])
    dist, _ = knn_query(cKDTree(pts), pts, k=kk + 1)
    spacing = dist[:, 1:].mean(axis=1)
    # isolated outliers would become huge discs: cap at a multiple of the median spacing
    return np.minimum(spacing, SPACING_CAP * np.median(spacing))


def mesh_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit vertex normals: area-weighted sums of the (F, 3) faces' normals."""
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    normals = np.zeros_like(p)
    for corner in range(3):
        np.add.at(normals, f[:, corner], face_n)
    return normalize_rows(normals)


def splat_geometry(model: PointModel, *, fill_holes: bool = True) -> SplatGeometry:
    """Normals, splat axes (None for meshes) and colors of ``model`` for rendering.

    fill_holes: enlarge stored surfels (radius or axes) whose area-equivalent radius is below
    ``SPACING_FACTOR`` times the kNN spacing, so the splats overlap. Scanner surfel radii are
    often smaller than that (head_surfels: median 0.43 x the spacing) and leave holes.
    """
    colors = model_colors(model)
    if model.faces is not None and model.n_faces > 0 and model.gaussians is None:
        normals = model.normals
        if normals is None:
            normals = mesh_normals(model.positions, model.faces)
        return SplatGeometry(_f32(normalize_rows(np.asarray(normals, float))), None, colors)
    if model.gaussians is not None:
        axes, normals = gaussian_axes(model.gaussians.scale_log, model.gaussians.rotation)
        return SplatGeometry(_f32(normals), _f32(axes), colors)
    normals = model.normals
    large = model.n_points > LARGE_CLOUD
    if (normals is None or not np.any(normals)) and (large or is_lidar(model)):
        return _flat_discs(model, colors)
    if normals is None or not np.any(normals):
        normals = pca_normals(model.positions, PCA_NEIGHBORS)
    normals = normalize_rows(np.asarray(normals, dtype=np.float64))
    spacing = sampled_spacing if large else knn_spacing
    cover = SPACING_FACTOR * spacing(model.positions) if fill_holes else None
    if model.axes is not None:
        axes = np.asarray(model.axes, dtype=np.float64)
        if cover is not None:  # scale each ellipse up (shape kept) to the covering radius
            grow = np.maximum(1.0, cover / np.maximum(axes_to_radius(axes), 1e-300))
            axes = axes * grow[:, None, None]
        return SplatGeometry(_f32(normals), _f32(axes), colors)
    if model.radius is not None:
        radius = np.asarray(model.radius, dtype=np.float64)
        if cover is not None:
            radius = np.maximum(radius, cover)
    else:
        radius = SPACING_FACTOR * spacing(model.positions) if cover is None else cover
    return SplatGeometry(_f32(normals), _f32(radius_to_axes(normals, radius)), colors)


def sampled_spacing(positions: np.ndarray, sample: int = SPACING_SAMPLE) -> np.ndarray:
    """(N,) one spacing for all points: the median kNN spacing of a seeded subsample of
    ``sample`` points, scaled to the full density as a surface (sqrt(sample / N)). O(N) time
    beyond the subsample's kNN: the point size adapts to the density of what is drawn."""
    pts = np.asarray(positions)
    n = pts.shape[0]
    if n <= sample:
        return knn_spacing(pts)
    pick = np.random.default_rng(0).choice(n, size=sample, replace=False)
    value = float(np.median(knn_spacing(pts[pick]))) * np.sqrt(sample / n)
    return np.full(n, value)


def _flat_discs(model: PointModel, colors: np.ndarray) -> SplatGeometry:
    """A large or LiDAR cloud without normals: discs in the cloud's best-fit plane (the two
    largest principal directions; terrain: horizontal), of the (subsample) spacing, shaded
    flat (zero normals) so eye-dome lighting or the colour carries the shape."""
    pts = np.asarray(model.positions, dtype=np.float64)
    centred = pts[:: max(1, pts.shape[0] // SPACING_SAMPLE)]
    centred = centred - centred.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    radius = SPACING_FACTOR * sampled_spacing(pts)[:, None]   # (N, 1)
    axes = np.empty((pts.shape[0], 2, 3), dtype=np.float32)
    axes[:, 0] = vt[0] * radius
    axes[:, 1] = vt[1] * radius
    return SplatGeometry(np.zeros((pts.shape[0], 3), dtype=np.float32), axes, colors)


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
