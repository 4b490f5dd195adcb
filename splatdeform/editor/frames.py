"""The editor's per-frame deformation (no web imports): what one pose change produces.

After a fit, :func:`prepare` lays out the arrays a pose needs over the non-fixed points (fixed
points never move): local positions, normals, Gaussian covariances and the basis values and
gradients. :func:`deform` then applies a delta_c to them
(:func:`splatdeform.deform.arrays.deform_frame`: positions and normals on the OpenCL device
when there is one, else numpy on one BLAS thread); :func:`base_frame` is the
undeformed model. Everything is in *local* coordinates (model coordinates minus the
controller's ``origin``, so large scan offsets stay precise).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import deform as df
from ..blas import blas_threads
from ..deform import arrays as ap
from ..geometry import full_from_triu6, triu6
from ..model import PointModel


@dataclass
class Frame:
    """What one pose change produces for the viewer (float32, ``local`` coordinates: model
    coordinates minus :attr:`EditorController.origin`, so large scan offsets stay precise).

    positions: (M, 3) float32. normals: (M, 3) float32 unit or None. axes: (M, 2, 3) float32
    surfel/splat tangent axes or None. cov6: (M, 6) float32 upper triangles (xx, xy, xz, yy,
    yz, zz) of the Gaussian covariances or None (:attr:`covariances` gives (M, 3, 3)).
    index: None when the rows are all N points, else (M,) int64: the points these rows are
    (the non-fixed ones; fixed points never move). delta_c: (k, 3) float64. seconds: compute.
    """

    positions: np.ndarray
    normals: np.ndarray | None
    axes: np.ndarray | None
    cov6: np.ndarray | None
    delta_c: np.ndarray
    seconds: float = 0.0
    index: np.ndarray | None = None

    @property
    def covariances(self) -> np.ndarray | None:
        """(M, 3, 3) float32 covariances, or None."""
        return None if self.cov6 is None else full_from_triu6(self.cov6)


def gaussian_cov6(model: PointModel) -> np.ndarray:
    """(N, 6) float32 upper triangles of the covariances R S^2 R^T of a 3DGS model."""
    from splatdeform.deform.gaussians import scale_rotation_to_factor

    g = model.gaussians
    f = scale_rotation_to_factor(g.scale_log, g.rotation)
    return triu6(f @ f.transpose(0, 2, 1))


def base_frame(model: PointModel, origin: np.ndarray) -> Frame:
    """The undeformed model as a :class:`Frame` (what the viewer shows before a fit)."""
    m = model
    return Frame(
        positions=(m.positions - origin).astype(np.float32),
        normals=None if m.normals is None else m.normals.astype(np.float32),
        axes=None if m.axes is None else m.axes.astype(np.float32),
        cov6=None if m.gaussians is None else gaussian_cov6(m),
        delta_c=np.zeros((4, 3)))


def prepare(model: PointModel, d: df.Deformation, origin: np.ndarray) -> dict[str, Any]:
    """Per-frame arrays over the non-fixed points (fixed points never move)."""
    m = model
    active = np.flatnonzero(~d.fixed)
    values, grads = df.full_basis(d)
    need_grads = any(a is not None for a in (m.normals, m.axes, m.gaussians))
    data: dict[str, Any] = {
        "active": active,
        "base": (m.positions - origin).astype(np.float32),
        "values": np.ascontiguousarray(values[active]),
        "grads": np.ascontiguousarray(grads[active]) if need_grads else None,
    }
    data["base_active"] = np.ascontiguousarray(data["base"][active])
    if m.normals is not None:
        data["normals"] = m.normals.astype(np.float32)
        data["normals_active"] = np.ascontiguousarray(data["normals"][active])
    if m.axes is not None:
        data["axes"] = m.axes.astype(np.float32)
    if m.gaussians is not None:
        data["cov6"] = gaussian_cov6(m)
        data["cov6_active"] = np.ascontiguousarray(data["cov6"][active])
    return data


def deform(fd: dict[str, Any], delta: np.ndarray, *, full: bool = True,
           t0: float | None = None) -> Frame:
    """``delta`` (k, 3) applied to the arrays of :func:`prepare`: all points (``full``) or the
    non-fixed ones only (``frame.index``). ``t0``: the ``perf_counter`` the frame's
    ``seconds`` count from (default: now)."""
    t0 = time.perf_counter() if t0 is None else t0
    active = fd["active"]
    with blas_threads(1):  # oversubscribed: 10-30x slower
        p, n = ap.deform_frame(fd["base_active"], fd.get("normals_active"), fd["values"],
                               fd["grads"], delta, backend="auto")
        axes = cov6 = None
        if "axes" in fd:
            jac = ap.jacobians(fd["grads"], delta.astype(np.float32))
            axes = ap.transform_axes(jac, fd["axes"][active]).astype(np.float32)
        if "cov6" in fd:
            cov6 = ap.covariance_frame(fd["grads"], delta, fd["cov6_active"])
    if not full:
        return Frame(p, n, axes, cov6, delta, time.perf_counter() - t0, index=active)

    def scatter(whole: np.ndarray | None, rows: np.ndarray | None) -> np.ndarray | None:
        if whole is None:
            return None
        out = whole.copy()
        out[active] = rows
        return out

    return Frame(scatter(fd["base"], p), scatter(fd.get("normals"), n),
                 scatter(fd.get("axes"), axes), scatter(fd.get("cov6"), cov6), delta,
                 time.perf_counter() - t0)
