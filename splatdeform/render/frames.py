"""Animations: the handle moving from identity to its target in N steps.

delta C is interpolated linearly, t = 0 .. 1; the basis is uploaded ONCE and each frame only
changes the 12-float uniform. Output: an animated GIF (``*.gif``) or a folder of PNGs
(``frame_0000.png`` ...) for any other path without a suffix.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from splatdeform.deform.gaussians import DEFAULT_COVARIANCE
from splatdeform.errors import InputError
from splatdeform.io.image import save_gif, save_png
from splatdeform.model import PointModel
from splatdeform.render.camera import DEFAULT_VIEW, View, write_camera
from splatdeform.render.renderer import deformation_session
from splatdeform.render.visibility import check_drawn


def render_frames(
    model: PointModel,
    values: np.ndarray,
    gradients: np.ndarray,
    delta_c: np.ndarray,
    n_frames: int,
    out_path: str | os.PathLike[str],
    view: View = DEFAULT_VIEW,
    *,
    duration_ms: int = 80,
    covariance: str = DEFAULT_COVARIANCE,
) -> list[Path]:
    """Render ``n_frames`` (>= 2) frames with delta C = t * ``delta_c`` (k, 3), t = i / (n - 1),
    one camera framing the whole motion. ``out_path``: ``*.gif`` (one animated GIF, looping,
    ``duration_ms`` per frame) or a folder (PNG sequence), plus one ``OUT.camera.json`` beside it
    (``view`` as in :func:`~splatdeform.render.compare.render_comparison`).
    Returns the written image paths."""
    if int(n_frames) < 2:
        raise InputError(f"n_frames: expected an integer >= 2, got {n_frames}")
    out = Path(out_path)
    if out.suffix and out.suffix.lower() != ".gif":
        raise InputError(f"out_path: expected a .gif file or a folder, got {out}")
    d = np.asarray(delta_c, dtype=np.float64)
    with deformation_session(model, values, gradients, delta_c, view,
                             covariance=covariance) as (renderer, gpu, camera):
        rgba = [renderer.draw_rgba(gpu, camera, d * (i / (n_frames - 1)))
                for i in range(int(n_frames))]
        panel = renderer.size
    check_drawn(rgba[0], camera, [model.positions])
    frames = [np.ascontiguousarray(im[:, :, :3]) for im in rgba]
    if out.suffix.lower() == ".gif":
        save_gif(frames, out, duration_ms=duration_ms)
        write_camera(out, camera, panel)
        return [out]
    out.mkdir(parents=True, exist_ok=True)
    written = [save_png(f, out / f"frame_{i:04d}.png") for i, f in enumerate(frames)]
    write_camera(out, camera, panel)
    return written
