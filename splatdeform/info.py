"""What the loader sees in a model: ``splatdeform info``."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from .model import PointModel


def describe(model: PointModel) -> dict[str, Any]:
    """A JSON-ready summary: kind, counts, properties with types, bbox, normal lengths.

    Non-finite values (a bbox diagonal beyond float64, NaN normals) stay floats here;
    :func:`to_json` writes them as null.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return _describe(model)


def _describe(model: PointModel) -> dict[str, Any]:
    lo, hi = model.bbox()
    info: dict[str, Any] = {
        "path": model.path,
        "kind": model.kind,
        "points": model.n_points,
        "faces": model.n_faces,
        "bbox_min": lo.tolist(),
        "bbox_max": hi.tolist(),
        "diagonal": model.diagonal(),
    }

    if model.source is not None:
        src = model.source
        info["format"] = getattr(src, "format_name", None) or ("ascii" if src.text else (
            "binary_big_endian" if src.byte_order == ">" else "binary_little_endian"))
        info["elements"] = [
            {"name": el.name, "count": el.count, "properties": [
                {"name": p.name,
                 "type": f"list {p.len_type_name} {p.type_name}" if p.is_list else p.type_name}
                for p in el.properties]}
            for el in src.elements]
        info["comments"] = list(src.comments)
    if model.normals is None:
        info["normals"] = "none"
    else:
        length = np.linalg.norm(model.normals, axis=1)
        unit = bool(np.all(np.abs(length - 1) < 1e-3))
        info["normals"] = "unit" if unit else "not unit length"
        info["normal_length_range"] = [float(length.min()), float(length.max())]
    if model.radius is not None:
        info["radius_median"] = float(np.median(model.radius))
    g = model.gaussians
    if g is not None:
        n_rest = 0 if g.sh_rest is None else g.sh_rest.shape[1]
        degrees = {0: 0, 9: 1, 24: 2, 45: 3}
        info["sh_degree"] = degrees.get(n_rest)  # None: not a standard 3DGS layout
        info["sh_rest_coefficients"] = n_rest
    return info


def json_ready(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, +-Inf) replaced by None (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    return value


def to_json(info: dict[str, Any]) -> str:
    """:func:`describe`'s dict as strict JSON (non-finite numbers become null)."""
    return json.dumps(json_ready(info), indent=2, allow_nan=False)


def format_text(info: dict[str, Any]) -> str:
    """Human-readable rendering of :func:`describe`'s dict."""
    fmt = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"  # noqa: E731
    lines = [
        f"file:     {info['path']}",
        f"kind:     {info['kind']}" + (f" ({info['format']})" if "format" in info else ""),
        f"points:   {info['points']:,}",
        f"faces:    {info['faces']:,}",
        f"bbox:     {fmt(info['bbox_min'])} .. {fmt(info['bbox_max'])}"
        f"  (diagonal {info['diagonal']:.6g})",
        f"normals:  {info['normals']}",
    ]
    if "up_axis" in info:   # added by `info` (render's rule): what render, thumbnails and
        # the editor use unless --up / render.up say otherwise
        lines.append(f"up:       {info['up_axis']} ({info['up_reason']}; --up/render.up win)")
    if "radius_median" in info:
        lines.append(f"radius:   median {info['radius_median']:.6g}")
    if "sh_degree" in info:
        degree = info["sh_degree"]
        lines.append(f"SH:       degree {degree if degree is not None else '? (non-standard)'} "
                     f"({info['sh_rest_coefficients']} f_rest values)")
    if info.get("format_fields"):
        fields = ", ".join(f"{k} {v}" for k, v in info["format_fields"].items())
        lines.append(f"format:   {fields}")
    for el in info.get("elements", []):
        props = ", ".join(f"{p['name']}:{p['type']}" for p in el["properties"])
        lines.append(f"element {el['name']} ({el['count']:,}): {props}")
    for c in info.get("comments", []):
        lines.append(f"comment:  {c}")
    return "\n".join(lines)
