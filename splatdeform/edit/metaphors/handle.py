"""Handles: ``handle:`` with ``regions.handle`` (one), or ``handles:`` (each with its own
``region``). k = 4 columns each (affine frame coordinates); a pose is a 4x4 transform."""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.deform.handle import compose_transform, delta_for_transform
from splatdeform.deform.metaphor import Metaphor, handle_metaphor
from splatdeform.edit import units as u
from splatdeform.edit.config import EditConfig, HandleCfg, TransformCfg, check_handle_matrix
from splatdeform.edit.metaphors.capabilities import Capabilities
from splatdeform.model import PointModel

CAPABILITIES = Capabilities(streams=1, keys={"streams": ("handle",)}, why={
    "streams": "handles: several handles do not stream yet"})


def entries(cfg: EditConfig) -> list[tuple[str, tuple[HandleCfg, list, str]]]:
    """(key, (handle config, region selector entries, region key)) of every handle."""
    if cfg.handle is not None:
        return [("handle", (cfg.handle, cfg.regions.handle or [], "regions.handle"))]
    return [(f"handles[{i}]", (h, h.region, f"handles[{i}].region"))
            for i, h in enumerate(cfg.handles or [])]


def basis_key(entry: tuple[HandleCfg, list, str]) -> dict:
    """What of a handle determines the basis (``--reuse``): its region, not its transform."""
    return {"region": [s.model_dump() for s in entry[1]]}


def label(n: int) -> str:
    """What ``n`` handles are called in the counts line."""
    return "handle" if n == 1 else "handles"


def columns(entry: tuple[HandleCfg, list, str]) -> int:
    """A handle's basis columns: its 4 affine frame coordinates."""
    return 4


def as_applied(cfg: EditConfig, matrices: list[np.ndarray]
               ) -> np.ndarray | list[np.ndarray] | None:
    """The handle matrices as apply takes them: one 4x4 for the ``handle:`` form, the list
    (one per handle) for ``handles:``, None without handles."""
    if cfg.handle is not None:
        return matrices[0]
    return matrices or None


def metaphor(key: str, entry: tuple[HandleCfg, list, str], ctx: Any) -> Metaphor:
    _, region, region_key = entry
    return handle_metaphor(ctx.model.positions, ctx.mask(region), region_key)


def delta(key: str, entry: tuple[HandleCfg, list, str], group: Any, deformation: Any,
          ctx: Any) -> tuple[np.ndarray, np.ndarray]:
    """T(C) - C of this handle's frame for its configured transform, and T."""
    points = deformation.moving_idx[group.rows]
    matrix = transform_matrix(entry[0], key, ctx.units, ctx.model, points)
    return delta_for_transform(group.frame.control_points, matrix), matrix


def single_matrix(cfg: EditConfig, model: PointModel, points: np.ndarray) -> np.ndarray:
    """The 4x4 transform of the single ``handle:`` form; ``points`` as in
    :func:`transform_matrix`."""
    return transform_matrix(cfg.handle, "handle", cfg.regions.units, model, points)


def transform_matrix(h: HandleCfg, key: str, units: str, model: PointModel,
                     handle: np.ndarray) -> np.ndarray:
    """The 4x4 transform of one handle from its ``transform`` or ``matrix`` (config key
    ``key``); ``handle`` (N,) bool or (M,) int64 selects its points (for a centroid pivot).
    Checked like the config (:func:`check_handle_matrix`) whoever built ``h``: a singular or
    non-finite transform is a ConfigError naming the key."""
    if h.matrix is not None:
        m = np.asarray(h.matrix, dtype=np.float64)
        check_handle_matrix(m, f"{key}.matrix")
        return m
    t: TransformCfg = h.transform
    frame = u.Frame.of(model)
    if t.pivot == "centroid":
        pivot = model.positions[handle].mean(axis=0)
    else:
        pivot = u.point(t.pivot, units, frame)
    m = compose_transform(pivot=pivot, scale=t.scale, axis=t.rotate.axis,
                          degrees=t.rotate.degrees, translate=u.vector(t.translate, units, frame))
    check_handle_matrix(m[:3, :3], f"{key}.transform", bound=None)  # the pivot: not checked
    return m
