"""Before/after images side by side, same camera, labelled (Pillow's default font); on request
a second before/after framed on the edit's changed part (:func:`closeup_camera`)."""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.deform.gaussians import DEFAULT_COVARIANCE
from splatdeform.errors import InputError
from splatdeform.io.image import save_png
from splatdeform.model import PointModel
from splatdeform.render import framing
from splatdeform.render.camera import Camera, View, default_up, orbit, write_camera
from splatdeform.render.overlay import Overlay, draw_overlays
from splatdeform.render.renderer import Renderer, deformation_session, deformed_positions
from splatdeform.render.visibility import check_drawn

LABEL_HEIGHT = 18   # the strip of one line of label text
LABEL_COLOR = (20, 20, 20)
LABEL_FONT_SIZE = 12   # Pillow's own font (FreeType) at 12 px: '.' and ':' stay legible


def _label_font():
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=LABEL_FONT_SIZE)
    except (TypeError, ImportError, OSError):   # Pillow < 10.1 or no FreeType: its bitmap font
        return ImageFont.load_default()


def _wrap(draw, text: str, font, width: float) -> list[str]:
    """``text`` in lines of at most ``width`` pixels, broken at spaces (a longer word alone)."""
    lines, line = [], ""
    for word in text.split(" "):
        trial = f"{line} {word}" if line else word
        if line and draw.textlength(trial, font=font) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return [*lines, line]


def side_by_side(images: Sequence[np.ndarray], labels: Sequence[str] | None = None) -> np.ndarray:
    """Concatenate (H, W, 3) uint8 images left to right, each with its label in a strip above.
    Returns (H + LABEL_HEIGHT * L, sum W, 3) uint8: L lines, 1 unless a label wider than its
    panel wraps (no strip when ``labels`` is None)."""
    from PIL import Image, ImageDraw

    if not images:
        raise InputError("images: expected at least one image, got none")
    if labels is not None and len(labels) != len(images):
        raise InputError(f"labels: expected {len(images)} labels, got {len(labels)}")
    height = max(im.shape[0] for im in images)
    width = sum(im.shape[1] for im in images)
    font = _label_font()
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines = [] if labels is None else [_wrap(measure, str(label), font, im.shape[1] - 8)
                                       for label, im in zip(labels, images, strict=True)]
    strip = LABEL_HEIGHT * max((len(ln) for ln in lines), default=0)
    canvas = Image.new("RGB", (width, height + strip), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    x = 0
    for i, im in enumerate(images):
        canvas.paste(Image.fromarray(np.asarray(im, dtype=np.uint8)[:, :, :3]), (x, strip))
        for row, text in enumerate(lines[i] if lines else []):
            draw.text((x + 4, 2 + row * LABEL_HEIGHT), text, fill=LABEL_COLOR, font=font)
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
    closeup: str | os.PathLike[str] | None = None,
    one_scene: bool | None = None,
) -> np.ndarray:
    """Render two CPU-side models side by side, or ``before`` alone when ``after`` is None.
    ``view.size`` is one panel (W, H). One camera frames both when they are one scene before
    and after an edit (:func:`same_scene`: the same number of points); two different models
    each get their own framing. ``view.up`` (None: the models' convention), ``view.roll``: see
    :func:`splatdeform.render.camera.orbit`; ``view.camera`` replaces the framing (both
    panels). ``overlays`` (model coordinates, framed too) are drawn over every panel. Writes a
    PNG to ``out_path`` (atomically) and the first panel's camera to ``OUT.camera.json`` when
    given; returns the composed (H', W', 3) uint8 image. ``closeup``: a second PNG (and its
    camera file) of the same scene framed on the points that moved (:func:`closeup_camera`),
    written only when ``after`` is the same scene and something moved. ``one_scene``: True
    when ``after`` is ``before`` edited even though the counts differ (split splats: the
    children after the original rows; None: :func:`same_scene`)."""
    models = [before] if after is None else [before, after]
    if after is not None and one_scene is None:
        one_scene = same_scene(before, after)
    renderer = Renderer(view.size)
    try:
        extra = [np.asarray(o.points, np.float64) for o in overlays]
        aspect = renderer.size[0] / renderer.size[1]

        def framed(group: list[PointModel]) -> Camera:
            return view.framed([m.positions for m in group] + extra, models, aspect)

        if after is None or one_scene:
            cameras = [framed(models)] * len(models)
        else:
            cameras = [framed([m]) for m in models]
        close = None
        if closeup is not None and after is not None and one_scene:
            close = closeup_camera(view, before.positions,  # the original rows come first
                                   after.positions[:before.n_points], models, aspect,
                                   cameras[0])
        images, close_images = [], []
        for model, cam in zip(models, cameras, strict=True):
            gpu = renderer.upload(model)
            try:
                rgba = renderer.draw_rgba(gpu, cam)
                near = None if close is None else renderer.draw_rgba(gpu, close)
            finally:
                gpu.release()
            check_drawn(rgba, cam, [model.positions])
            image = np.ascontiguousarray(rgba[:, :, :3])
            images.append(draw_overlays(image, cam, list(overlays)) if overlays else image)
            if near is not None:
                close_images.append(np.ascontiguousarray(near[:, :, :3]))
    finally:
        renderer.release()
    if close is not None:
        _compose(close_images, closeup_labels(labels), closeup, close, renderer.size)
    return _compose(images, list(labels)[: len(images)], out_path, cameras[0], renderer.size)


CLOSEUP_LABEL = "changed part"


def closeup_labels(labels: Sequence[str]) -> list[str]:
    """The close-up's panel labels: ``labels`` followed by ": changed part"."""
    return [f"{label}: {CLOSEUP_LABEL}" for label in list(labels)[:2]]


CLOSEUP_GAIN = 1.3   # a close-up only when it shows the changed part 1.3 times larger


def closeup_camera(view: View, before: np.ndarray, after: np.ndarray, models: Iterable[Any],
                   aspect: float, whole_camera: Camera | None = None) -> Camera | None:
    """The camera of an edit's changed part: the points that moved
    (:func:`~splatdeform.render.framing.moved_mask` of the (N, 3) ``before`` / ``after``
    positions), before and after together, framed as the whole model is
    (:func:`~splatdeform.render.framing.fit_frame`: robust projected extent) from the same
    direction: ``view``'s orbit with the elevation the whole scene gets (flat scenes 40
    degrees), or its camera's direction and lens. ``zoom`` is left out (the close-up fills its
    panel). The near plane sits just in front of the changed part, so nearer geometry is cut
    away rather than hiding it; far reaches the back of the whole model. None when nothing
    moved (or the point counts differ), or when the whole model's ``whole_camera`` already
    shows the changed part nearly as large (less than :data:`CLOSEUP_GAIN` times smaller)."""
    mask = framing.moved_mask(before, after)
    if mask is None:
        return None
    whole = [np.asarray(before), np.asarray(after)]
    if view.camera is not None:
        basis, fov, up_vector = view.camera.basis(), float(view.camera.fov), view.camera.up
    else:
        up = view.up or default_up(models)
        elevation = view.elevation
        if elevation is None:
            elevation = framing.default_elevation(framing.stacked(whole), up)
        probe = orbit(np.zeros(3), 1.0, azimuth=view.azimuth, elevation=elevation,
                      fov=view.fov, up=up, roll=view.roll)
        basis, fov, up_vector = probe.basis(), float(view.fov), probe.up
    changed = framing.stacked([whole[0][mask], whole[1][mask]])
    with warnings.catch_warnings():   # the whole model's framing reports its outliers
        warnings.simplefilter("ignore", framing.FramingNote)
        position, target, near, far = framing.fit_frame(changed, basis, fov, aspect=aspect)
    _, back = framing.clip_range(position, basis[2], target, whole)
    camera = Camera(position, target, np.asarray(up_vector, np.float64), fov=fov, near=near,
                    far=max(far, back))
    if whole_camera is not None and whole_camera.near is not None and whole_camera.far \
            is not None and _span(camera, changed, aspect) < CLOSEUP_GAIN * _span(
                whole_camera, changed, aspect):
        return None
    return camera


def _span(camera: Camera, points: np.ndarray, aspect: float) -> float:
    """How much of the picture the (M, 3) ``points`` in front of ``camera`` span: the larger
    of their width and height as fractions of the panel's (0 when none is in front)."""
    homo = np.c_[points, np.ones(len(points))]
    clip = homo @ (camera.projection(aspect) @ camera.view()).T
    front = clip[:, 3] > 0
    if not front.any():
        return 0.0
    ndc = clip[front, :2] / clip[front, 3:4]
    return float(np.max(ndc.max(axis=0) - ndc.min(axis=0)) / 2.0)


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
    covariance: str = DEFAULT_COVARIANCE,
    closeup: str | os.PathLike[str] | None = None,
) -> np.ndarray:
    """Before (delta C = 0) and after (``delta_c`` (k, 3)) from ONE upload of the basis
    ``values`` (N, k) / ``gradients`` (N, k, 3): the shader deforms, the CPU only frames
    (``view`` as in :func:`render_comparison`). Writes a PNG to ``out_path`` and its
    ``OUT.camera.json`` when given; returns the composed image. ``closeup``: a second PNG (and
    its camera file) framed on the points that moved (:func:`closeup_camera`), from the same
    upload; not written when nothing moved."""
    with deformation_session(model, values, gradients, delta_c, view,
                             covariance=covariance) as (renderer, gpu, camera):
        rgba = [renderer.draw_rgba(gpu, camera, None), renderer.draw_rgba(gpu, camera, delta_c)]
        panel = renderer.size
        close, close_rgba = None, []
        if closeup is not None:
            close = closeup_camera(view, model.positions,
                                   deformed_positions(model, values, delta_c), [model],
                                   panel[0] / panel[1], camera)
        if close is not None:
            close_rgba = [renderer.draw_rgba(gpu, close, None),
                          renderer.draw_rgba(gpu, close, delta_c)]
    check_drawn(rgba[0], camera, [model.positions])
    if close is not None:
        _compose([np.ascontiguousarray(im[:, :, :3]) for im in close_rgba],
                 closeup_labels(labels), closeup, close, panel)
    images = [np.ascontiguousarray(im[:, :, :3]) for im in rgba]
    return _compose(images, labels, out_path, camera, panel)
