"""What the editor page uploads to its GPU, as plain numpy arrays (no web imports).

Once per model: positions, display normals, base colours, faces, Gaussian covariances, opacity
and SH (:func:`model_arrays`). Once per fit: the basis of every point, ``values`` then
``gradients`` in the layout of ``shaders/deform.glsl``'s storage buffer (per point K values then
3K gradient components, float32; fixed points all zero) and the fit's control points
(:func:`basis_arrays`). A pose is then only delta C = T(C) - C, computed by the page.

Everything is in *local* coordinates (model coordinates minus ``controller.origin``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..deform import full_basis
from ..deform.normals import pca_normals
from ..render.camera import default_up
from ..render.gaussian_data import log_scale_shape, warn_band4_not_drawn
from . import view
from .controller import EditorController
from .frames import gaussian_cov6

UP_VECTORS = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
              "+z": (0, 0, 1), "-z": (0, 0, -1)}


def up_axis(ed: EditorController) -> str:
    """``render.up`` of the loaded YAML, else the renderer's default-up rule
    (:func:`splatdeform.render.camera.default_up`), so the page and ``render`` agree."""
    r = ed.settings.render
    if r is not None and r.up is not None:
        return r.up
    return default_up([ed.model])


def display_normals(ed: EditorController) -> tuple[np.ndarray | None, str]:
    """(N, 3) float32 unit normals for shading and where they came from: the file's, PCA
    estimates for a point cloud without them (display only, never saved), or None for a mesh
    (the page shades faces by their own normals)."""
    m = ed.model
    if m.normals is not None:
        return m.normals.astype(np.float32), "file"
    if m.n_faces or m.gaussians is not None or m.n_points < 4:
        return None, "none"
    local = np.asarray(m.positions, np.float64) - ed.origin
    return pca_normals(local, min(12, m.n_points - 1)).astype(np.float32), "estimated"


def model_kind(ed: EditorController) -> str:
    m = ed.model
    return "splats" if m.gaussians is not None else "mesh" if m.n_faces else "points"


def model_arrays(ed: EditorController, normals: np.ndarray | None = None
                 ) -> dict[str, np.ndarray]:
    """The page's per-model arrays: positions (N, 3) float32 local, colors (N, 4) uint8 (RGB
    as stored or neutral grey; alpha the 3DGS opacity), and when present normals (N, 3) float32,
    faces (F, 3) uint32, cov6 (N, 6) float32 (xx, xy, xz, yy, yz, zz), shape (N, 2) float32
    (spread and mean of the float64 log-scales, for the ``limited`` covariance mode), sh_rest
    (N, 3 * R) float32 channel-major. ``normals``: :func:`display_normals` when already
    computed."""
    m = ed.model
    out: dict[str, np.ndarray] = {
        "positions": (np.asarray(m.positions, np.float64) - ed.origin).astype(np.float32),
        "colors": view.splat_rgba(m, view.base_colors(m).astype(np.float32)),
    }
    if normals is None:
        normals, _ = display_normals(ed)
    if normals is not None:
        out["normals"] = normals
    if m.n_faces:
        out["faces"] = np.ascontiguousarray(m.faces, dtype=np.uint32)
    g = m.gaussians
    if g is not None:
        out["cov6"] = gaussian_cov6(m)
        out["shape"] = log_scale_shape(g.scale_log)
        if g.sh_rest is not None and g.sh_rest.shape[1] >= 9:
            rest = np.asarray(g.sh_rest, dtype=np.float32)
            if rest.shape[1] > 45:   # SH band 4: the page draws bands 0-3 (and says so once)
                warn_band4_not_drawn()
                rest = rest.reshape(len(rest), 3, -1)[:, :, :15].reshape(len(rest), 45)
            out["sh_rest"] = np.ascontiguousarray(rest)
    return out


def sh_degree(ed: EditorController) -> int:
    g = ed.model.gaussians
    if g is None or g.sh_rest is None:
        return 0
    per_channel = g.sh_rest.shape[1] // 3
    return {3: 1, 8: 2, 15: 3, 24: 3}.get(per_channel, 0)   # band 4 (24) is drawn as 3


def scene_info(ed: EditorController, arrays: dict[str, np.ndarray] | None = None,
               normals_from: str | None = None) -> dict[str, Any]:
    """JSON-able description of the model for the page (``arrays``, ``normals_from``: from
    :func:`model_arrays` / :func:`display_normals` when already computed)."""
    if arrays is None or normals_from is None:
        normals, normals_from = display_normals(ed)
        arrays = model_arrays(ed, normals)
    return {
        "name": ed.model_path.name, "kind": model_kind(ed), "n": int(ed.model.n_points),
        "n_faces": int(ed.model.n_faces), "diagonal": float(max(ed.model.diagonal(), 1e-9)),
        "origin": [float(v) for v in ed.origin], "up": up_axis(ed),
        "up_vector": list(UP_VECTORS[up_axis(ed)]), "point_size": view.point_size(ed.model),
        "normals": normals_from, "sh_degree": sh_degree(ed),
        "covariance": ed.covariance,
        "arrays": {k: {"dtype": a.dtype.str, "shape": list(a.shape)}
                   for k, a in arrays.items()},
    }


def basis_arrays(ed: EditorController) -> tuple[np.ndarray, np.ndarray]:
    """Per fit: basis (N, 4K) float32 (per point K values then 3K gradient components, the
    storage layout of ``shaders/deform.glsl``) and control points (K, 3) float64 local (4 per
    handle, in handle order: delta C rows 4h..4h+3 belong to handle h)."""
    d = ed.deformation
    values, grads = full_basis(d)
    n, k = values.shape
    basis = np.empty((n, 4 * k), np.float32)
    basis[:, :k] = values
    basis[:, k:] = grads.reshape(n, 3 * k)
    return basis, np.asarray(basis_arrays_meta(ed)[1])


def basis_arrays_meta(ed: EditorController) -> tuple[int, list[list[float]]]:
    """(k, the handles' control points (4 per handle, local) as lists) without building the
    basis; the columns after them are the curve's (delta = moved_to - control_points)."""
    d = ed.deformation
    frames = [g.frame.control_points for g in d.handle_groups()]
    control = np.vstack(frames) - ed.origin if frames else np.zeros((0, 3))
    return int(d.k), control.tolist()


def local_to_model(ed: EditorController, matrix: np.ndarray) -> np.ndarray:
    """(4, 4) pose in the page's local frame -> the same map in model coordinates."""
    shift, back = np.eye(4), np.eye(4)
    shift[:3, 3] = ed.origin
    back[:3, 3] = -ed.origin
    return shift @ np.asarray(matrix, np.float64) @ back


def model_to_local(ed: EditorController, matrix: np.ndarray) -> np.ndarray:
    shift, back = np.eye(4), np.eye(4)
    shift[:3, 3] = -ed.origin
    back[:3, 3] = ed.origin
    return shift @ np.asarray(matrix, np.float64) @ back
