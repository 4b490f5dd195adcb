"""Rendering: splats and meshes through the deforming vertex stage (moderngl, headless EGL).

A :class:`View` says how a render looks (size, orbit angles, up, roll, or a camera);
:class:`Renderer` uploads a model once and draws it through its pipeline (:mod:`.surfels`,
:mod:`.meshes`, :mod:`.gaussians`). Importing this package creates no GL context; the first
render does (see :mod:`.context`).
"""

from __future__ import annotations

from splatdeform.io.image import save_png  # the PNG writer, exported here as before
from splatdeform.render.camera import Camera, View, frame_bbox, frame_points
from splatdeform.render.compare import render_comparison, render_deformation_comparison
from splatdeform.render.frames import render_frames
from splatdeform.render.renderer import GpuModel, Renderer, render_image

__all__ = [
    "Camera",
    "GpuModel",
    "Renderer",
    "View",
    "frame_bbox",
    "frame_points",
    "render_comparison",
    "render_deformation_comparison",
    "render_frames",
    "render_image",
    "save_png",
]
