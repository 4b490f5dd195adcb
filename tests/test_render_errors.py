"""Bad arguments to the renderer raise the project's InputError (a ValueError too), with a
message naming the argument and what was expected. The Renderer test uses the real EGL context."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import egl_renderer

from splatdeform.errors import InputError
from splatdeform.model import PointModel
from splatdeform.render.camera import View, frame_bbox, up_frame
from splatdeform.render.compare import side_by_side
from splatdeform.render.frames import render_frames
from splatdeform.render.renderer import Renderer


def _points(n: int = 50, seed: int = 0) -> PointModel:
    rng = np.random.default_rng(seed)
    return PointModel(positions=rng.uniform(-1, 1, size=(n, 3)), kind="cloud")


def test_camera_up_and_fov() -> None:
    with pytest.raises(InputError, match=r"^up: expected one of .*'\+w'"):
        up_frame("+w")
    with pytest.raises(InputError, match=r"^fov: expected degrees in \(0, 180\), got 180"):
        frame_bbox(np.zeros(3), np.ones(3), View(fov=180))


def test_frames_n_frames(tmp_path) -> None:
    model = _points()
    values = np.ones((model.n_points, 1), dtype=np.float32)
    gradients = np.zeros((model.n_points, 1, 3), dtype=np.float32)
    with pytest.raises(InputError, match=r"^n_frames: expected an integer >= 2, got 1"):
        render_frames(model, values, gradients, np.zeros((1, 3)), 1, tmp_path / "f.gif")
    assert not (tmp_path / "f.gif").exists()


def test_compare_labels() -> None:
    images = [np.zeros((4, 4, 3), np.uint8)] * 2
    with pytest.raises(InputError, match=r"^labels: expected 2 labels, got 1"):
        side_by_side(images, ["only one"])
    with pytest.raises(ValueError, match="^images"):  # still a ValueError for old callers
        side_by_side([])


def test_renderer_values_shape() -> None:
    renderer = egl_renderer((8, 8))
    try:
        model = _points()
        n = model.n_points
        with pytest.raises(InputError, match=rf"^values: expected shape \({n}, k\)"):
            renderer.upload(model, np.ones((n - 1, 2), np.float32),
                            np.zeros((n - 1, 2, 3), np.float32))
        with pytest.raises(InputError, match=r"^gradients: expected shape"):
            renderer.upload(model, np.ones((n, 2), np.float32), np.zeros((n, 3, 3), np.float32))
        with pytest.raises(InputError, match=r"^size: expected \(width, height\) >= 1"):
            Renderer((0, 8))
    finally:
        renderer.release()


def test_a_failed_upload_frees_the_gpu_buffers_it_made() -> None:
    renderer = egl_renderer((8, 8))
    made, make = [], renderer.ctx.buffer

    def spy(*args, **kwargs):
        made.append(make(*args, **kwargs))
        return made[-1]

    renderer.ctx.buffer = spy
    try:
        model = _points()
        n = model.n_points
        with pytest.raises(InputError, match=r"^gradients: expected shape"):
            renderer.upload(model, np.ones((n, 2), np.float32), np.zeros((n, 3, 3), np.float32))
        assert made and all(type(b.mglo).__name__ == "InvalidObject" for b in made)
    finally:
        renderer.ctx.buffer = make
        renderer.release()
