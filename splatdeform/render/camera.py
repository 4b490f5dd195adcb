"""Cameras: orbit cameras about an up axis, auto-framing, camera files, view/projection matrices.

A :class:`Camera` is a position, a target, an up vector, a vertical field of view and clip
distances -- exactly what ``OUT.camera.json`` holds, so a camera file reproduces a render bit
for bit. Orbit conventions (:func:`orbit`): ``up`` is one of ``+x +y +z -x -y -z``; with ``+y``
azimuth 0 looks down -z (the eye on +z), azimuth turns the eye about the up axis, elevation
lifts it toward the up axis; the other axes are the same picture rotated so +y lands on ``up``
(``+z``: azimuth 0 looks along +y; ``-y``, the 3DGS convention: the y-up picture turned 180
degrees about x). ``roll`` turns the camera about its viewing direction (positive: the camera's
up leans to the right, so the picture turns counter-clockwise). Matrices are (4, 4) float64,
row-major in numpy (transpose them for GL's column-major upload, see :func:`gl_bytes`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.errors import InputError
from splatdeform.render import framing
from splatdeform.render.limits import MAX_IMAGE, MAX_ZOOM, MIN_IMAGE, MIN_ZOOM

UP_AXES = ("+x", "+y", "+z", "-x", "-y", "-z")
# rotation taking the y-up orbit frame to each up axis: columns are the images of x, y, z
_FRAMES = {
    "+y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "+z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "+x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
}
CAMERA_KEYS = ("position", "target", "up", "fov_y_degrees", "width", "height", "near", "far")
OPTIONAL_KEYS = ("near", "far")   # a hand-written file may omit them: computed from the model


@dataclass(frozen=True)
class Camera:
    """A perspective camera.

    position, target: (3,) float64 eye and looked-at point. up: (3,) float64 up direction (not
    parallel to target - position; cameras made by :func:`orbit` store it orthonormal to the
    viewing direction). fov: vertical field of view in degrees. near, far: clip distances
    (None: computed from the model before drawing, :func:`with_clip`). source: where
    the camera came from (a camera file's path), for messages.
    """

    position: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float = 35.0
    near: float | None = 0.01
    far: float | None = 100.0
    source: str | None = field(default=None, compare=False)

    def eye(self) -> np.ndarray:
        """(3,) float64 eye position."""
        return np.asarray(self.position, dtype=np.float64)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, true_up, forward): three (3,) float64 orthonormal vectors of the view."""
        forward = np.asarray(self.target, np.float64) - np.asarray(self.position, np.float64)
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(self.up, dtype=np.float64))
        norm = np.linalg.norm(right)
        if norm < 1e-12:  # up parallel to the view: any perpendicular will do
            helper = np.eye(3)[int(np.argmin(np.abs(forward)))]
            right = np.cross(forward, helper)
            norm = np.linalg.norm(right)
        right = right / norm
        return right, np.cross(right, forward), forward

    def view(self, origin: np.ndarray | None = None) -> np.ndarray:
        """(4, 4) world -> view matrix; ``origin`` (3,) is subtracted from world coordinates first
        (the renderer uploads positions relative to an origin to keep float32 precise)."""
        shift = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
        right, true_up, forward = self.basis()
        eye = self.eye() - shift
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, true_up, -forward
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def projection(self, aspect: float) -> np.ndarray:
        """(4, 4) OpenGL perspective projection for width / height ``aspect``."""
        if self.near is None or self.far is None:
            raise InputError("camera: near/far: not known yet (computed from the model when a "
                             "render frames it)")
        f = 1.0 / math.tan(math.radians(self.fov) / 2.0)
        n, fa = self.near, self.far
        m = np.zeros((4, 4))
        m[0, 0] = f / aspect
        m[1, 1] = f
        m[2, 2] = (fa + n) / (n - fa)
        m[2, 3] = 2.0 * fa * n / (n - fa)
        m[3, 2] = -1.0
        return m


@dataclass(frozen=True)
class View:
    """How a render looks at its models, one value for what used to be seven loose arguments.

    size: (W, H) pixels of one panel. azimuth, elevation: degrees of the orbit (:func:`orbit`;
    elevation None: 40 for flat scenes, else 20, see :mod:`.framing`). fov: the lens angle
    (vertical, degrees); the framing fills the picture whatever the angle. zoom: narrows the
    view about the target by this factor (2: twice as close-up). up: one of :data:`UP_AXES`,
    or None for the models' convention (:func:`default_up`). roll: degrees about the viewing
    direction. camera: a :class:`Camera` that replaces the framing (e.g. from a camera file),
    or None.
    """

    size: tuple[int, int] = (256, 256)
    azimuth: float = 30.0
    elevation: float | None = None
    fov: float = 35.0
    up: str | None = None
    roll: float = 0.0
    camera: Camera | None = None
    zoom: float = 1.0

    def framed(self, point_sets: Iterable[np.ndarray], models: Iterable[Any],
               aspect: float) -> Camera:
        """``camera`` when set (near / far it lacks computed from the points), else the
        framing of the (M_i, 3) ``point_sets`` about ``up`` (None: the convention of
        ``models``) at width / height ``aspect``."""
        if self.camera is not None:
            return with_clip(self.camera, point_sets)
        return frame_points(point_sets, replace(self, up=self.up or default_up(models)),
                            aspect=aspect)

    def with_options(self, up: str | None = None, roll: float | None = None,
                     camera_file: str | os.PathLike[str] | None = None,
                     zoom: float | None = None) -> View:
        """This view with the user's camera options: ``up`` (None: the file's convention),
        ``roll`` degrees (None: 0), ``zoom`` (None: 1), and a camera file, which wins: it brings
        ``camera`` and ``size`` (one panel, W x H). Raises InputError for a bad value or file."""
        if up is not None and up not in UP_AXES:
            raise InputError(f"--up/render.up: expected one of {' '.join(UP_AXES)}, got {up!r}")
        roll = 0.0 if roll is None else float(roll)
        if not math.isfinite(roll):
            raise InputError(
                f"--roll/render.roll: expected a finite number of degrees, got {roll}")
        zoom = 1.0 if zoom is None else float(zoom)
        if not (math.isfinite(zoom) and MIN_ZOOM <= zoom <= MAX_ZOOM):
            raise InputError(f"--zoom/render.zoom: expected a factor between {MIN_ZOOM:g} and "
                             f"{MAX_ZOOM:g}, got {zoom}")
        view = replace(self, up=up, roll=roll, zoom=zoom)
        if camera_file is not None:
            camera, size = load_camera(camera_file)
            view = replace(view, camera=camera, size=size)
        return view


DEFAULT_VIEW = View()


def up_frame(up: str) -> np.ndarray:
    """(3, 3) rotation taking the y-up orbit frame to the ``up`` axis (``+x`` ... ``-z``)."""
    if up not in _FRAMES:
        raise InputError(f"up: expected one of {' '.join(UP_AXES)}, got {up!r}")
    return np.array(_FRAMES[up], dtype=np.float64).T


def orbit(
    target: np.ndarray,
    distance: float,
    *,
    azimuth: float = 30.0,
    elevation: float = 20.0,
    fov: float = 35.0,
    up: str = "+y",
    roll: float = 0.0,
    near: float = 0.01,
    far: float = 100.0,
) -> Camera:
    """A camera ``distance`` from ``target`` (3,), placed by azimuth/elevation (degrees) about
    the ``up`` axis and rolled by ``roll`` degrees (see the module doc)."""
    frame = up_frame(up)
    az, el = math.radians(azimuth), math.radians(elevation)
    local = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    direction = frame @ local
    target = np.asarray(target, dtype=np.float64)
    position = target + float(distance) * direction
    forward = -direction
    hint = frame[:, 1]
    if abs(float(forward @ hint)) > 0.999:  # looking straight along the up axis
        hint = frame @ np.array([0.0, 0.0, -1.0 if local[1] > 0 else 1.0])
    right = np.cross(forward, hint)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    r = math.radians(roll)
    cam_up = math.cos(r) * true_up + math.sin(r) * right
    return Camera(position, target, cam_up, fov=fov, near=near, far=far)


def union_bbox(point_sets: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (min, max), two (3,) float64, of the union of (M_i, 3) point arrays."""
    los, his = [], []
    for pts in point_sets:
        a = np.asarray(pts, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise InputError(f"point set: expected a non-empty (M, 3) array, got shape {a.shape}")
        los.append(a.min(axis=0))
        his.append(a.max(axis=0))
    if not los:
        raise InputError("point_sets: expected at least one point array, got none")
    return np.min(los, axis=0), np.max(his, axis=0)


def frame_bbox(lo: np.ndarray, hi: np.ndarray, view: View = DEFAULT_VIEW, *, aspect: float = 1.0,
               margin: float = 1.05) -> Camera:
    """A camera that sees the whole box (lo, hi) from any direction: its bounding sphere fits the
    narrower of the two fields of view, times ``margin``. ``view``: azimuth, elevation, fov,
    up (None: ``+y``) and roll of the orbit (its size and camera are not used)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    fov = view.fov
    if not (fov > 0 and fov < 180):
        raise InputError(f"fov: expected degrees in (0, 180), got {fov}")
    center = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-9)
    half_v = math.radians(fov) / 2.0
    half = min(half_v, math.atan(math.tan(half_v) * aspect))
    distance = margin * radius / math.sin(half)
    return orbit(
        center,
        distance,
        azimuth=view.azimuth,
        elevation=20.0 if view.elevation is None else view.elevation,
        fov=fov,
        up=view.up or "+y",
        roll=view.roll,
        near=max(distance - 2.0 * radius, distance * 1e-3),
        far=distance + 2.0 * radius,
    )


def frame_points(point_sets: Iterable[np.ndarray], view: View = DEFAULT_VIEW, *,
                 aspect: float = 1.0) -> Camera:
    """Auto-framing on the robust projected extent of the union of (M_i, 3) point arrays (e.g.
    a model before and after a deformation, so both images share one camera): see
    :func:`splatdeform.render.framing.fit_frame`; ``view``'s azimuth, elevation, fov, zoom,
    up (None: ``+y``) and roll."""
    pts = framing.stacked(point_sets)
    up = view.up or "+y"
    local = pts - (pts.min(axis=0) + pts.max(axis=0)) / 2.0 if len(pts) else pts
    elevation = view.elevation
    if elevation is None:   # flat scenes (LiDAR, terrain) are seen obliquely
        elevation = framing.default_elevation(local, up) if len(pts) else 20.0
    probe = orbit(np.zeros(3), 1.0, azimuth=view.azimuth, elevation=elevation, fov=view.fov,
                  up=up, roll=view.roll)
    position, target, near, far = framing.fit_frame(pts, probe.basis(), float(view.fov),
                                                    aspect=aspect)
    return Camera(position, target, probe.up, fov=framing.zoomed_fov(view.fov, view.zoom),
                  near=near, far=far)


def with_clip(camera: Camera, point_sets: Iterable[np.ndarray]) -> Camera:
    """``camera`` with a missing near / far (None, e.g. a hand-written camera file without
    them) computed from the points (:func:`~.framing.clip_range`); given values are used as
    written."""
    if camera.near is not None and camera.far is not None:
        return camera
    computed = framing.clip_range(camera.eye(), camera.basis()[2], camera.target, point_sets)
    near, far = framing.complete_clip(camera.near, camera.far, computed)
    return replace(camera, near=near, far=far)


def default_up(models: Iterable[Any]) -> str:
    """The up axis of the models' file convention (:func:`splatdeform.render.upaxis.up_rule`):
    ``-y`` for 3D Gaussian splat scenes, ``+z`` for LiDAR and geo-referenced scans, else
    ``+y``."""
    from splatdeform.render.upaxis import up_rule

    return up_rule(models)[0]


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A (4, 4) numpy matrix as column-major float32 bytes for a GL ``mat4`` uniform."""
    return np.ascontiguousarray(np.asarray(matrix, dtype=np.float32).T).tobytes()


# -- camera files -----------------------------------------------------------------------------
def camera_sidecar(image_path: str | os.PathLike[str]) -> Path:
    """Where the camera of an image goes: ``OUT.png`` -> ``OUT.camera.json`` (also for a GIF, or
    ``FOLDER.camera.json`` beside a folder of frames)."""
    p = Path(image_path)
    return p.with_name(f"{p.stem if p.suffix else p.name}.camera.json")


def camera_dict(camera: Camera, size: tuple[int, int]) -> dict[str, Any]:
    """The JSON mapping of ``camera`` for a panel of ``size`` (W, H) pixels."""
    return {
        "position": [float(v) for v in camera.position],
        "target": [float(v) for v in camera.target],
        "up": [float(v) for v in camera.up],
        "fov_y_degrees": float(camera.fov),
        "width": int(size[0]),
        "height": int(size[1]),
        **({} if camera.near is None else {"near": float(camera.near)}),
        **({} if camera.far is None else {"far": float(camera.far)}),
    }


def write_camera(image_path: str | os.PathLike[str], camera: Camera,
                 size: tuple[int, int]) -> Path:
    """Write ``OUT.camera.json`` beside ``image_path`` atomically; returns its path."""
    from splatdeform.io.atomic import atomic_write

    out = camera_sidecar(image_path)
    text = json.dumps(camera_dict(camera, size), indent=2) + "\n"
    with atomic_write(out) as stream:
        stream.write(text.encode())
    return out


def _vector(data: dict[str, Any], key: str, where: str) -> np.ndarray:
    value = data.get(key)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{where}: {key}: expected a list of 3 finite numbers, got {value!r}")
    return arr


def _number(data: dict[str, Any], key: str, where: str, lo: float, hi: float) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo < value < hi:
        raise InputError(f"{where}: {key}: expected a number in ({lo:g}, {hi:g}), got {value!r}")
    return float(value)


def parse_camera(data: Any, where: str) -> tuple[Camera, tuple[int, int]]:
    """A camera mapping (the ``OUT.camera.json`` keys) -> (Camera, (width, height)).
    Raises InputError naming ``where`` and the key."""
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a JSON object with keys {', '.join(CAMERA_KEYS)}")
    unknown = sorted(set(data) - set(CAMERA_KEYS))
    missing = [k for k in CAMERA_KEYS if k not in data and k not in OPTIONAL_KEYS]
    if unknown or missing:
        what = "; ".join(filter(None, [missing and f"missing {', '.join(missing)}",
                                       unknown and f"unknown {', '.join(unknown)}"]))
        raise InputError(f"{where}: expected the keys {', '.join(CAMERA_KEYS)} (near and far "
                         f"may be omitted) ({what})")
    position, target = _vector(data, "position", where), _vector(data, "target", where)
    up = _vector(data, "up", where)
    if np.linalg.norm(target - position) == 0:
        raise InputError(f"{where}: position and target: expected two different points")
    forward = target - position
    if np.linalg.norm(np.cross(forward, up)) <= 1e-9 * np.linalg.norm(forward) * max(
            np.linalg.norm(up), 1e-300):
        raise InputError(f"{where}: up: expected a direction not parallel to target - position")
    # the lens as drawn (a zoomed view's is narrower than MIN_FOV): any open angle
    fov = _number(data, "fov_y_degrees", where, 0.0, 180.0)
    near = _number(data, "near", where, 0.0, math.inf) if "near" in data else None
    far = _number(data, "far", where, near or 0.0, math.inf) if "far" in data else None
    size = []
    for key in ("width", "height"):
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, int) or \
                not MIN_IMAGE <= value <= MAX_IMAGE:
            raise InputError(f"{where}: {key}: expected an integer pixel count in "
                             f"{MIN_IMAGE}..{MAX_IMAGE}, got {value!r}")
        size.append(value)
    return (Camera(position, target, up, fov=fov, near=near, far=far, source=where),
            (size[0], size[1]))


MAX_CAMERA_BYTES = 1 << 20  # a camera file is a few hundred bytes


def load_camera(path: str | os.PathLike[str]) -> tuple[Camera, tuple[int, int]]:
    """Read a camera file (the ``OUT.camera.json`` a render wrote) -> (Camera, (W, H) of one
    panel). Raises InputError naming the file."""
    from splatdeform.errors import FormatError
    from splatdeform.io.regular import read_regular

    try:   # the one opener: a regular file (no FIFO, device or folder), its size bounded first
        raw = read_regular(path, max_bytes=MAX_CAMERA_BYTES, what="camera file")
    except FormatError as exc:
        raise InputError(f"{exc}; expected a .camera.json file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the camera file ({exc.strerror})") from None
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{path}: the camera file is not text (binary data); expected a "
                         ".camera.json file") from None
    except (ValueError, RecursionError) as exc:
        msg = " ".join(str(exc).split())[:120] if not isinstance(exc, RecursionError) else \
            "nested too deeply"
        raise InputError(f"{path}: not valid JSON ({msg})") from None
    return parse_camera(data, str(path))
