"""One upload of a model with its basis and one camera framing the whole motion."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np

from splatdeform.model import PointModel
from splatdeform.render.camera import Camera, frame_points
from splatdeform.render.renderer import GpuModel, Renderer, deformed_positions


@contextlib.contextmanager
def deformation_session(
    model: PointModel,
    values: np.ndarray,
    gradients: np.ndarray,
    delta_c: np.ndarray,
    *,
    size: tuple[int, int],
    azimuth: float,
    elevation: float,
    fov: float,
) -> Iterator[tuple[Renderer, GpuModel, Camera]]:
    """Upload ``model`` with its basis (values (N, k), gradients (N, k, 3)) once, frame the
    camera on the undeformed and the ``delta_c`` (k, 3)-deformed positions, and release the GL
    objects on exit. Yields (renderer, gpu model, camera)."""
    renderer = Renderer(size)
    gpu = renderer.upload(model, values, gradients)
    try:
        camera = frame_points(
            [model.positions, deformed_positions(model, values, delta_c)],
            azimuth=azimuth,
            elevation=elevation,
            fov=fov,
            aspect=renderer.size[0] / renderer.size[1],
        )
        yield renderer, gpu, camera
    finally:
        gpu.release()
        renderer.release()
