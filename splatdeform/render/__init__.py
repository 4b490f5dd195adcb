"""Rendering: splats and meshes through the deforming vertex stage (moderngl, headless EGL).

A :class:`View` says how a render looks (size, orbit angles, up, roll, or a camera);
:class:`Renderer` uploads a model once and draws it through its pipeline (:mod:`.surfels`,
:mod:`.meshes`, :mod:`.gaussians`). Importing this package creates no GL context; the first
render does (see :mod:`.context`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from splatdeform.lazy import lazy_exports

# Imported on first use: the CLI's parser reads render.camera / render.colors (the --up and
# --color choices) without loading the renderer, the GL programs or the deformation.
_LAZY = {
    "save_png": "splatdeform.io.image", "Camera": "camera", "View": "camera",
    "frame_bbox": "camera", "frame_points": "camera", "render_comparison": "compare",
    "render_deformation_comparison": "compare", "render_frames": "frames",
    "GpuModel": "renderer", "Renderer": "renderer", "render_image": "renderer",
}

if TYPE_CHECKING:  # pragma: no cover
    from splatdeform.io.image import save_png  # the PNG writer, exported here as before
    from splatdeform.render.camera import Camera, View, frame_bbox, frame_points
    from splatdeform.render.compare import render_comparison, render_deformation_comparison
    from splatdeform.render.frames import render_frames
    from splatdeform.render.renderer import GpuModel, Renderer, render_image

__getattr__ = lazy_exports(__name__, _LAZY)

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
