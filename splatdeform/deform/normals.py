"""Normal estimation for clouds without normals (Open3D)."""

from __future__ import annotations

import numpy as np

from splatdeform.errors import InputError
from splatdeform.model import PointModel, classify


def estimate_normals(model: PointModel, k: int = 16, *, orient: str = "consistent") -> PointModel:
    """A copy of ``model`` with unit normals (N, 3) float64 estimated by local PCA over k
    nearest neighbours (Open3D).

    orient: "consistent" (Open3D's tangent-plane propagation; globally consistent on closed
    surfaces), "+z" (towards +z, e.g. airborne LiDAR terrain), or "outward" (away from the
    centroid). Coordinates are shifted to the bounding-box centre first, so large offsets
    (UTM) do not cost precision.
    """
    import open3d as o3d

    if k < 3:
        raise InputError(f"k: expected at least 3 neighbours, got {k}")
    if orient not in ("consistent", "+z", "outward"):
        raise InputError(f"orient: expected 'consistent', '+z' or 'outward', got {orient!r}")
    lo, hi = model.bbox()
    centred = model.positions - (lo + hi) / 2
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centred))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k))
    if orient == "consistent" and model.n_points > k:
        cloud.orient_normals_consistent_tangent_plane(k)
    normals = np.asarray(cloud.normals, dtype=np.float64).copy()
    if orient == "+z":
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
