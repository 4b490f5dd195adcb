"""Normal estimation for clouds without normals: the one estimator in the package.

:func:`pca_normals` (local PCA over the k nearest neighbours, numpy + scipy) gives the normal
directions; the renderer uses it as is (two-sided shading, sign arbitrary) and
:func:`estimate_normals` orients them (Open3D only for the "consistent" orientation, imported
when used).
"""

from __future__ import annotations

import numpy as np

from splatdeform.errors import InputError
from splatdeform.interrupts import knn_query
from splatdeform.model import PointModel, classify

PCA_CHUNK = 200_000  # points per kNN query / covariance batch: bounded memory for large scans


def pca_normals(positions: np.ndarray, k: int = 12) -> np.ndarray:
    """(N, 3) float64 unit normals by local PCA: the smallest-eigenvalue direction of the
    covariance of each point's k nearest neighbours (the point included; scipy cKDTree).

    Deterministic (nothing random); the sign of each normal is arbitrary. Points are shifted to
    the bounding-box centre first, so large offsets (UTM) do not cost precision, and processed
    in chunks of :data:`PCA_CHUNK`, so memory stays bounded for millions of points. Fewer than
    3 points (or k < 3): every normal is +z.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    kk = min(int(k), n)
    if kk < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    pts = pts - (pts.min(axis=0) + pts.max(axis=0)) / 2
    tree = cKDTree(pts)
    normals = np.empty_like(pts)
    for start in range(0, n, PCA_CHUNK):
        stop = min(start + PCA_CHUNK, n)
        _, nbr = knn_query(tree, pts[start:stop], k=kk)
        nb = pts[nbr]  # (chunk, k, 3)
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred)
        _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
        normals[start:stop] = vecs[:, :, 0]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return normals


def estimate_normals(model: PointModel, k: int = 16, *, orient: str = "consistent") -> PointModel:
    """A copy of ``model`` with unit normals (N, 3) float64 estimated by local PCA over k
    nearest neighbours (:func:`pca_normals`), then oriented.

    orient: "consistent" (Open3D's tangent-plane propagation; globally consistent on closed
    surfaces), "+z" (towards +z, e.g. airborne LiDAR terrain), or "outward" (away from the
    centroid). Coordinates are shifted to the bounding-box centre first, so large offsets
    (UTM) do not cost precision.

    Parameters
    ----------
    model : PointModel
        Any model; its positions are read, its other arrays copied.
    k : int
        Neighbours per point for the PCA (and the propagation); at least 3.
    orient : {"consistent", "+z", "outward"}
        How the sign of each normal is chosen.

    Returns
    -------
    PointModel
        A copy with ``normals`` set (a plain cloud becomes an ``oriented_cloud``).

    Raises
    ------
    InputError
        ``k`` below 3 or an unknown ``orient``.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # with its exact normals
    >>> bare = sd.PointModel(positions=bar.positions)
    >>> est = sd.estimate_normals(bare, k=12, orient="outward")
    >>> est.normals.shape, est.kind, bare.normals is None
    ((2000, 3), 'oriented_cloud', True)
    >>> agree = np.einsum("ij,ij->i", est.normals, bar.normals)
    >>> bool(np.median(agree) > 0.9)
    True
    """
    if k < 3:
        raise InputError(f"k: expected at least 3 neighbours, got {k}")
    if orient not in ("consistent", "+z", "outward"):
        raise InputError(f"orient: expected 'consistent', '+z' or 'outward', got {orient!r}")
    lo, hi = model.bbox()
    centred = np.asarray(model.positions, dtype=np.float64) - (lo + hi) / 2
    normals = pca_normals(centred, k)
    if orient == "consistent" and model.n_points > k:
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centred))
        cloud.normals = o3d.utility.Vector3dVector(normals)
        cloud.orient_normals_consistent_tangent_plane(k)
        normals = np.asarray(cloud.normals, dtype=np.float64).copy()
    elif orient == "+z":
        normals[normals[:, 2] < 0] *= -1
    elif orient == "outward":
        flip = np.einsum("ij,ij->i", normals, centred - centred.mean(axis=0)) < 0
        normals[flip] *= -1
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    out = model.copy()
    out.normals = normals
    if out.kind == "cloud":
        out.kind = classify(has_faces=False, has_normals=True, has_radius=False,
                            has_axes=False, has_gaussians=False)
    return out
