"""Cameras: auto-framing on bounding boxes, view and projection matrices.

Conventions: y is up; azimuth rotates the eye about the y axis (0 deg looks down -z, from +z),
elevation lifts it toward +y. Matrices are (4, 4) float64, row-major in numpy (transpose them
for GL's column-major upload, see :func:`gl_bytes`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A perspective camera looking at ``target`` from ``distance``.

    target: (3,) float64 point looked at. distance: eye-target distance (> 0).
    azimuth, elevation, fov: degrees (fov is vertical). near, far: clip distances (> 0).
    """

    target: np.ndarray
    distance: float
    azimuth: float = 30.0
    elevation: float = 20.0
    fov: float = 35.0
    near: float = 0.01
    far: float = 100.0

    def eye(self) -> np.ndarray:
        """(3,) float64 eye position."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        direction = np.array(
            [math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)]
        )
        return np.asarray(self.target, dtype=np.float64) + self.distance * direction

    def view(self, origin: np.ndarray | None = None) -> np.ndarray:
        """(4, 4) world -> view matrix; ``origin`` (3,) is subtracted from world coordinates first
        (the renderer uploads positions relative to an origin to keep float32 precise)."""
        shift = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
        eye = self.eye() - shift
        target = np.asarray(self.target, dtype=np.float64) - shift
        forward = target - eye
        forward /= np.linalg.norm(forward)
        up = np.array([0.0, 1.0, 0.0])
        if abs(float(forward @ up)) > 0.999:  # looking straight up or down
            up = np.array([0.0, 0.0, -1.0 if forward[1] < 0 else 1.0])
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        true_up = np.cross(right, forward)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, true_up, -forward
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def projection(self, aspect: float) -> np.ndarray:
        """(4, 4) OpenGL perspective projection for width / height ``aspect``."""
        f = 1.0 / math.tan(math.radians(self.fov) / 2.0)
        n, fa = self.near, self.far
        m = np.zeros((4, 4))
        m[0, 0] = f / aspect
        m[1, 1] = f
        m[2, 2] = (fa + n) / (n - fa)
        m[2, 3] = 2.0 * fa * n / (n - fa)
        m[3, 2] = -1.0
        return m


def union_bbox(point_sets: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (min, max), two (3,) float64, of the union of (M_i, 3) point arrays."""
    los, his = [], []
    for pts in point_sets:
        a = np.asarray(pts, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise ValueError(f"point set: expected a non-empty (M, 3) array, got shape {a.shape}")
        los.append(a.min(axis=0))
        his.append(a.max(axis=0))
    if not los:
        raise ValueError("point_sets: expected at least one point array, got none")
    return np.min(los, axis=0), np.max(his, axis=0)


def frame_bbox(
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    azimuth: float = 30.0,
    elevation: float = 20.0,
    fov: float = 35.0,
    aspect: float = 1.0,
    margin: float = 1.05,
) -> Camera:
    """A camera that sees the whole box (lo, hi) from any direction: its bounding sphere fits the
    narrower of the two fields of view, times ``margin``."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if not (fov > 0 and fov < 180):
        raise ValueError(f"fov: expected degrees in (0, 180), got {fov}")
    center = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-9)
    half_v = math.radians(fov) / 2.0
    half = min(half_v, math.atan(math.tan(half_v) * aspect))
    distance = margin * radius / math.sin(half)
    return Camera(
        target=center,
        distance=distance,
        azimuth=azimuth,
        elevation=elevation,
        fov=fov,
        near=max(distance - 2.0 * radius, distance * 1e-3),
        far=distance + 2.0 * radius,
    )


def frame_points(
    point_sets: Iterable[np.ndarray],
    *,
    azimuth: float = 30.0,
    elevation: float = 20.0,
    fov: float = 35.0,
    aspect: float = 1.0,
) -> Camera:
    """Auto-framing on the union of the bounding boxes of (M_i, 3) point arrays (e.g. a model
    before and after a deformation, so both images share one camera)."""
    lo, hi = union_bbox(point_sets)
    return frame_bbox(lo, hi, azimuth=azimuth, elevation=elevation, fov=fov, aspect=aspect)


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A (4, 4) numpy matrix as column-major float32 bytes for a GL ``mat4`` uniform."""
    return np.ascontiguousarray(np.asarray(matrix, dtype=np.float32).T).tobytes()
