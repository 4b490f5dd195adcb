"""A render that draws nothing says so: one warning line naming the camera, its clip
distances and where the model lies along the view."""

from __future__ import annotations

import warnings
from collections.abc import Iterable

import numpy as np

from splatdeform.render.camera import Camera
from splatdeform.render.framing import stacked


class BlankRenderWarning(UserWarning):
    """No part of the model landed in the picture (one line on stderr)."""


def why_blank(camera: Camera, point_sets: Iterable[np.ndarray]) -> str:
    """The warning line of a ``camera`` that draws none of the (M_i, 3) ``point_sets``."""
    pts = stacked(point_sets)
    _, _, forward = camera.basis()
    depth = (pts - camera.eye()) @ forward
    near, far = float(camera.near or 0.0), float(camera.far or 0.0)
    lo, hi = (float(depth.min()), float(depth.max())) if depth.size else (0.0, 0.0)
    if hi <= 0:
        where = "behind the camera"
    elif hi < near:
        where = "nearer than near"
    elif lo > far:
        where = "beyond far"
    else:
        where = "outside the field of view"
    name = camera.source or "the camera"
    return (f"{name}: near {near:.6g}, far {far:.6g} draws no part of the model, which lies "
            f"{lo:.6g} .. {hi:.6g} along the view ({where}); move the camera, or omit near/far "
            "in the camera file to have them computed from the model")


def check_drawn(rgba: np.ndarray, camera: Camera, point_sets: Iterable[np.ndarray]) -> None:
    """Warn (:class:`BlankRenderWarning`) when the (H, W, 4) ``rgba`` render has no coverage."""
    if rgba.ndim == 3 and rgba.shape[2] == 4 and not np.any(rgba[:, :, 3]):
        warnings.warn(BlankRenderWarning(why_blank(camera, point_sets)), stacklevel=3)
