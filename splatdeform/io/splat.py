"""``.splat``: the web viewers' 32-byte splat records (little-endian, no header).

Per splat: position x y z (float32), linear scale (float32 x3, the exponent of the log scale),
colour r g b and opacity a (uint8: round(255 * (0.5 + SH_C0 * f_dc)) and 255 * sigmoid(opacity)),
rotation w x y z (uint8: 128 + 128 * q of the unit quaternion, clamped). Axes as PLY space (the
files are converted from 3DGS PLYs without a flip). No SH rest: higher bands are dropped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PointModel
from .checks import check_fits
from .splat_model import to_model
from .splats import (
    SplatFields,
    alpha_logit,
    color_to_dc,
    dc_to_color,
    fields_of,
    normalised_quaternions,
    note_lossy,
    read_bytes,
    sigmoid,
)

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                   ("rot", "u1", 4)])


def decode(raw: bytes | np.ndarray, path: str | Path) -> SplatFields:
    if len(raw) % RECORD.itemsize:
        raise FormatError(f"{path}: .splat size {len(raw):,} bytes is not a multiple of the "
                          f"{RECORD.itemsize}-byte splat record")
    rec = np.frombuffer(raw, dtype=RECORD)
    n = len(rec)
    with np.errstate(divide="ignore"):
        scale_log = np.log(rec["scale"].astype(np.float64))
    rgba = rec["rgba"].astype(np.float64) / 255
    return SplatFields(positions=rec["position"].astype(np.float64),
                       scale_log=scale_log.astype(np.float32),
                       rotation=((rec["rot"].astype(np.float64) - 128) / 128).astype(np.float32),
                       opacity=alpha_logit(rgba[:, 3]).astype(np.float32),
                       sh_dc=color_to_dc(rgba[:, :3]).astype(np.float32),
                       sh_rest=np.zeros((n, 3, 0), np.float32))


def encode(f: SplatFields) -> np.ndarray:
    """(N,) RECORD array of the splat fields."""
    rec = np.empty(f.count, dtype=RECORD)
    rec["position"] = f.positions
    with np.errstate(over="ignore"):
        scale = np.exp(f.scale_log.astype(np.float64))
    check_fits("scale (exp of scale_log)", scale, np.float32, ".splat")
    rec["scale"] = scale
    color = np.clip(np.round(dc_to_color(f.sh_dc) * 255), 0, 255)
    alpha = np.clip(np.round(sigmoid(f.opacity) * 255), 0, 255)
    rec["rgba"] = np.concatenate([color, alpha[:, None]], axis=1).astype(np.uint8)
    q = normalised_quaternions(f.rotation)
    rec["rot"] = np.clip(np.round(q * 128 + 128), 0, 255).astype(np.uint8)
    return rec


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    fields = decode(read_bytes(path), path)
    return to_model(fields, path, ["read from a .splat file by splatdeform"],
                    drop_nonfinite=drop_nonfinite)


def write_model(model: PointModel, path: Path, stream) -> None:
    fields = fields_of(model, path, ".splat")
    note_lossy(path, ".splat", "colour and opacity 8 bits, rotation 8 bits per component, "
               "position and scale float32", model, sh_kept=0)
    stream.write(encode(fields).tobytes())
