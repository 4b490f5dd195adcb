"""Before/after images side by side, same camera, labelled (Pillow's default font)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from splatdeform.errors import InputError
from splatdeform.io.image import save_png
from splatdeform.model import PointModel
from splatdeform.render.camera import Camera, View, write_camera
from splatdeform.render.overlay import Overlay, draw_overlays
from splatdeform.render.renderer import Renderer, deformation_session
from splatdeform.render.visibility import check_drawn

LABEL_HEIGHT = 18
LABEL_COLOR = (20, 20, 20)


def side_by_side(images: Sequence[np.ndarray], labels: Sequence[str] | None = None) -> np.ndarray:
    """Concatenate (H, W, 3) uint8 images left to right, each with its label in a strip above.
    Returns (H + LABEL_HEIGHT, sum W, 3) uint8 (no strip when ``labels`` is None)."""
    from PIL import Image, ImageDraw

    if not images:
        raise InputError("images: expected at least one image, got none")
    if labels is not None and len(labels) != len(images):
        raise InputError(f"labels: expected {len(images)} labels, got {len(labels)}")
    height = max(im.shape[0] for im in images)
    strip = LABEL_HEIGHT if labels is not None else 0
    width = sum(im.shape[1] for im in images)
    canvas = Image.new("RGB", (width, height + strip), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    x = 0
    for i, im in enumerate(images):
        canvas.paste(Image.fromarray(np.asarray(im, dtype=np.uint8)[:, :, :3]), (x, strip))
        if labels is not None:
            draw.text((x + 4, 3), str(labels[i]), fill=LABEL_COLOR)
        x += im.shape[1]
    return np.asarray(canvas)


PANEL = View(size=(512, 512))  # the comparisons' default view: one 512 x 512 panel


def render_comparison(
    before: PointModel,
    after: PointModel | None,
    out_path: str | os.PathLike[str] | None,
    view: View = PANEL,
    *,
    labels: Sequence[str] = ("before", "after"),
    overlays: Sequence[Overlay] = (),
) -> np.ndarray:
    """Render two CPU-side models side by side, or ``before`` alone when ``after`` is None.
    ``view.size`` is one panel (W, H). One camera frames both when they are one scene before
    and after an edit (:func:`same_scene`: the same number of points); two different models
    each get their own framing. ``view.up`` (None: the models' convention), ``view.roll``: see
    :func:`splatdeform.render.camera.orbit`; ``view.camera`` replaces the framing (both
    panels). ``overlays`` (model coordinates, framed too) are drawn over every panel. Writes a
    PNG to ``out_path`` (atomically) and the first panel's camera to ``OUT.camera.json`` when
    given; returns the composed (H', W', 3) uint8 image."""
    models = [before] if after is None else [before, after]
    renderer = Renderer(view.size)
    try:
        extra = [np.asarray(o.points, np.float64) for o in overlays]
        aspect = renderer.size[0] / renderer.size[1]

        def framed(group: list[PointModel]) -> Camera:
            return view.framed([m.positions for m in group] + extra, models, aspect)

        if after is None or same_scene(before, after):
            cameras = [framed(models)] * len(models)
        else:
            cameras = [framed([m]) for m in models]
        images = []
        for model, cam in zip(models, cameras, strict=True):
            gpu = renderer.upload(model)
            try:
                rgba = renderer.draw_rgba(gpu, cam)
            finally:
                gpu.release()
            check_drawn(rgba, cam, [model.positions])
            image = np.ascontiguousarray(rgba[:, :, :3])
            images.append(draw_overlays(image, cam, list(overlays)) if overlays else image)
    finally:
        renderer.release()
    return _compose(images, list(labels)[: len(images)], out_path, cameras[0], renderer.size)


def _compose(images: list[np.ndarray], labels: Sequence[str],
             out_path: str | os.PathLike[str] | None, camera: Camera,
             panel: tuple[int, int]) -> np.ndarray:
    """The panels side by side under their ``labels``; written as PNG with its
    ``OUT.camera.json`` (the first panel's ``camera`` and ``panel`` size) when ``out_path`` is
    given."""
    image = side_by_side(images, list(labels))
    if out_path is not None:
        save_png(image, Path(out_path))
        write_camera(out_path, camera, panel)
    return image


def same_scene(before: PointModel, after: PointModel) -> bool:
    """True when two models are one scene before and after an edit (a deformation keeps every
    point, so the counts match): one camera then shows the change. Different models differ."""
    return before.n_points == after.n_points


def render_deformation_comparison(
    model: PointModel,
    values: np.ndarray,
    gradients: np.ndarray,
    delta_c: np.ndarray,
    out_path: str | os.PathLike[str] | None,
    view: View = PANEL,
    *,
    labels: Sequence[str] = ("before", "after"),
    covariance: str = "jacobian",
) -> np.ndarray:
    """Before (delta C = 0) and after (``delta_c`` (k, 3)) from ONE upload of the basis
    ``values`` (N, k) / ``gradients`` (N, k, 3): the shader deforms, the CPU only frames
    (``view`` as in :func:`render_comparison`). Writes a PNG to ``out_path`` and its
    ``OUT.camera.json`` when given; returns the composed image."""
    with deformation_session(model, values, gradients, delta_c, view,
                             covariance=covariance) as (renderer, gpu, camera):
        rgba = [renderer.draw_rgba(gpu, camera, None), renderer.draw_rgba(gpu, camera, delta_c)]
        panel = renderer.size
    check_drawn(rgba[0], camera, [model.positions])
    images = [np.ascontiguousarray(im[:, :, :3]) for im in rgba]
    return _compose(images, labels, out_path, camera, panel)
