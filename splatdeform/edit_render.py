"""Before/after images of an edit from its precomputed basis (no second load or fit)."""

from __future__ import annotations

import time
from pathlib import Path

from .config import EditConfig, RenderCfg
from .deform import full_basis
from .edit import EditResult


def render_result(result: EditResult, cfg: EditConfig, out: str | Path, *,
                  frames: int = 0) -> Path:
    """Write the before/after PNG (or, with frames >= 2, a GIF/PNG sequence of the handle
    moving from identity to the target). The vertex shader deforms, for any number of control
    DOFs k (k > 4, e.g. curves, reads the basis from a storage buffer); one basis upload."""
    from .render import render_deformation_comparison, render_frames

    opts = cfg.render or RenderCfg(output=str(out))
    frames = frames or opts.frames
    values, gradients = full_basis(result.deformation)
    t0 = time.perf_counter()
    view = dict(azimuth=opts.azimuth, elevation=opts.elevation, fov=opts.fov)
    out = Path(out)
    if frames >= 2:
        target = out if out.suffix.lower() == ".gif" or not out.suffix else out.with_suffix(".gif")
        render_frames(result.model, values, gradients, result.delta_c, frames, target,
                      size=(opts.size[0] // 2, opts.size[1]), **view)
        out = target
    else:
        render_deformation_comparison(result.model, values, gradients, result.delta_c, out,
                                      size=(opts.size[0] // 2, opts.size[1]), **view)
    result.timings["render"] = time.perf_counter() - t0
    return out
