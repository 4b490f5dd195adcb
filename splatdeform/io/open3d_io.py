"""Point cloud formats read and written through Open3D: .xyz .xyzn .pts (PCD: ``pcd.py``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PointModel, classify
from .checks import nonfinite_points


def _o3d():
    import open3d  # imported lazily: it takes a second

    # Open3D prints warnings on stdout, which would corrupt `info --json`; errors are ours to report
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a point cloud through Open3D (positions, normals and colors when present)."""
    o3d = _o3d()
    cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=False,
                                    remove_infinite_points=False)
    positions = np.asarray(cloud.points, dtype=np.float64)
    if positions.shape[0] == 0:
        raise FormatError(f"{path}: no points could be read (empty or malformed "
                          f"{Path(path).suffix} file)")
    normals = np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None
    colors = None
    if cloud.has_colors():
        colors = np.clip(np.asarray(cloud.colors) * 255 + 0.5, 0, 255).astype(np.uint8)
    tiny = (positions != 0) & (np.abs(positions) < np.finfo(np.float64).tiny)
    if tiny.any():  # denormals: what Open3D returns for rows it could not read
        raise FormatError(f"{path}: malformed or truncated {Path(path).suffix} body")
    bad = nonfinite_points(path, positions, drop_nonfinite)
    if bad.any():
        positions = positions[~bad]
        normals = None if normals is None else normals[~bad]
        colors = None if colors is None else colors[~bad]
    kind = classify(has_faces=False, has_normals=normals is not None, has_radius=False,
                    has_axes=False, has_gaussians=False)
    return PointModel(positions=positions, normals=normals, colors=colors, kind=kind,
                      path=str(path))


def write_model(model: PointModel, path: Path) -> None:
    """Write positions (+ normals, colors) through Open3D; ``path``'s suffix picks the format."""
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.positions))
    if model.normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(model.normals)
    if model.colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(model.colors.astype(np.float64) / 255.0)
    if not o3d.io.write_point_cloud(str(path), cloud, write_ascii=True):
        raise FormatError(f"{path}: Open3D could not write this file")
