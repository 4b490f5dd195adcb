"""Lines and markers drawn over a rendered panel (e.g. ``select -o``'s curve before and after,
its snapped control points), projected with the panel's camera; Pillow draws them.

Overlays are in model coordinates; points behind the camera are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.render.camera import Camera


@dataclass
class Overlay:
    """points: (M, 3) float64 model coordinates; kind ``line`` (a polyline through them) or
    ``markers`` (a dot at each); color: RGB 0..255; width: line width / dot radius in pixels."""

    points: np.ndarray
    kind: str = "line"
    color: tuple[int, int, int] = (200, 0, 0)
    width: int = 2


def project(camera: Camera, points: np.ndarray, size: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (M, 2) float64 (x right, y down, top-left origin) of (M, 3) points in a
    (W, H) image, and (M,) bool: in front of the camera."""
    w, h = size
    p = np.concatenate([np.asarray(points, np.float64), np.ones((len(points), 1))], axis=1)
    clip = p @ (camera.projection(w / h) @ camera.view()).T
    front = clip[:, 3] > 0
    ndc = clip[:, :2] / np.where(front, clip[:, 3], 1.0)[:, None]
    return np.stack([(ndc[:, 0] + 1) * 0.5 * w, (1 - ndc[:, 1]) * 0.5 * h], axis=1), front


def draw_overlays(image: np.ndarray, camera: Camera, overlays: list[Overlay]) -> np.ndarray:
    """(H, W, 3) uint8 ``image`` with ``overlays`` drawn on a copy."""
    from PIL import Image, ImageDraw

    canvas = Image.fromarray(np.ascontiguousarray(image[:, :, :3]))
    draw = ImageDraw.Draw(canvas)
    size = (image.shape[1], image.shape[0])
    for ov in overlays:
        xy, front = project(camera, ov.points, size)
        if ov.kind == "markers":
            r = ov.width
            for (x, y), ok in zip(xy, front, strict=True):
                if ok:
                    draw.ellipse((x - r, y - r, x + r, y + r), fill=tuple(ov.color),
                                 outline=(0, 0, 0))
            continue
        run: list[tuple[float, float]] = []
        for (x, y), ok in zip(xy, front, strict=True):
            if ok:
                run.append((float(x), float(y)))
            elif len(run) > 1:
                draw.line(run, fill=tuple(ov.color), width=ov.width)
                run = []
            else:
                run = []
        if len(run) > 1:
            draw.line(run, fill=tuple(ov.color), width=ov.width, joint="curve")
    return np.asarray(canvas)
