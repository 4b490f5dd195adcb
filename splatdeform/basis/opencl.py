"""OpenCL evaluation of the deformation basis (host side of ``kernels/basis.cl``).

The one place in the package that creates an OpenCL context. Device choice, in order: the
``device`` argument ("P:D" platform:device indices, "P" for the first device of platform P, or a
case-insensitive substring of the device or platform name), the ``PYOPENCL_CTX`` environment
variable (same syntax), then the first GPU, then the first CPU (then any) device.

Contexts, queues and built programs are cached per device for the life of the process; on disk,
PoCL's cache (pyopencl leaves PoCL's builds to it) or pyopencl's (which follows the ``-I``
includes) makes later processes skip the build (:mod:`.kernel_cache`: the first build's note).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..errors import DeviceError, InputError
from ..rbf.result import RbfFit
from ..resources import resource_dir, resource_path
from .checks import check_fit, check_points
from .kernel_cache import noting_slow_build
from .result import Basis

try:  # pyopencl is a hard dependency, but a broken install must read as "no device"
    import pyopencl as cl
except ImportError:  # pragma: no cover - exercised only on broken installs
    cl = None

NO_DEVICE_HINT = (
    "install an OpenCL driver, e.g. Debian's pocl-opencl-icd (apt-get install pocl-opencl-icd)"
)
DEFAULT_MAX_CHUNK_POINTS = 1 << 20
#: device bytes one chunk may use (points in, values and gradients out)
CHUNK_BYTE_BUDGET = 256 << 20
PRECISIONS = ("auto", "double", "float")
#: largest K whose k loops are unrolled (accumulators in registers). Above it the rolled loop is
#: faster on PoCL (K = 16: 73 vs 95 ms per 128k x 200) and builds in 1 s instead of 3-18 s.
MAX_UNROLLED_K = 12


@dataclass
class _DeviceState:
    device: object
    context: object
    queue: object
    programs: dict = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


_STATES: dict[tuple[str, str, int], _DeviceState] = {}
_STATES_LOCK = threading.Lock()


# ----------------------------------------------------------------------------- device choice


def _all_devices() -> list[tuple[int, int, object]]:
    """Every (platform index, device index, device); [] when no ICD or platform exists."""
    if cl is None:
        return []
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # CL_PLATFORM_NOT_FOUND_KHR when no ICD is installed
        return []
    found = []
    for p_index, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:  # a platform with no device raises CL_DEVICE_NOT_FOUND
            continue
        found.extend((p_index, d_index, dev) for d_index, dev in enumerate(devices))
    return found


def _listing(devices: list[tuple[int, int, object]]) -> str:
    return ", ".join(f"{p}:{d} {dev.name.strip()!r}" for p, d, dev in devices) or "none"


def _match(spec: str, devices: list[tuple[int, int, object]], source: str) -> object:
    """The device named by ``spec`` ("P:D", "P" or a name substring); DeviceError otherwise."""
    text = spec.strip()
    parts = text.split(":")
    if parts and all(part.strip().isdigit() for part in parts) and len(parts) <= 2:
        p_index = int(parts[0])
        d_index = int(parts[1]) if len(parts) == 2 else 0
        for p, d, dev in devices:
            if p == p_index and d == d_index:
                return dev
    else:
        needle = text.lower()
        for _, _, dev in devices:
            if needle in dev.name.lower() or needle in dev.platform.name.lower():
                return dev
    raise DeviceError(
        f"{source}: no OpenCL device matches {spec!r}; available: {_listing(devices)}"
    )


def _select_device(device: str | None) -> object:
    devices = _all_devices()
    if not devices:
        raise DeviceError(f"backend 'opencl': no OpenCL device found; {NO_DEVICE_HINT}")
    if device is not None:
        if not isinstance(device, str) or not device.strip():
            raise InputError(
                f"device: expected 'P:D', 'P' or a device-name substring, got {device!r}"
            )
        return _match(device, devices, "device")
    env = os.environ.get("PYOPENCL_CTX", "").strip()
    if env:
        return _match(env, devices, "PYOPENCL_CTX")
    for wanted in (cl.device_type.GPU, cl.device_type.CPU):
        for _, _, dev in devices:
            if dev.type & wanted:
                return dev
    return devices[0][2]


def opencl_available(device: str | None = None) -> bool:
    """True when an OpenCL device (the one ``device`` names, if given) can be found."""
    try:
        _select_device(device)
    except DeviceError:
        return False
    return True


def describe_device(device: str | None = None) -> str:
    """One line naming the device ``compute_basis(..., device=device)`` would use.

    Raises DeviceError when there is none.
    """
    dev = _select_device(device)
    fp64 = "fp64" if _has_fp64(dev) else "no fp64 (compensated float32)"
    return (
        f"{dev.name.strip()} [{dev.platform.name.strip()}; {dev.version.strip()}; "
        f"{dev.max_compute_units} compute units; {fp64}]"
    )


def _has_fp64(dev: object) -> bool:
    return "cl_khr_fp64" in dev.extensions.split()


def _state(dev: object) -> _DeviceState:
    key = (dev.platform.name, dev.name, int(dev.int_ptr))
    with _STATES_LOCK:
        state = _STATES.get(key)
        if state is None:
            try:
                context = cl.Context([dev])
                queue = cl.CommandQueue(context)
            except cl.Error as exc:
                raise DeviceError(
                    f"backend 'opencl': cannot open device {dev.name.strip()!r}: {exc}"
                ) from exc
            state = _STATES[key] = _DeviceState(dev, context, queue)
    return state


def prepare_device(device: str | None = None, k: int | None = None,
                   gradients: bool = True) -> None:
    """Open ``device`` (context and queue) and, given ``k``, build the basis kernel for k
    columns (with ``gradients``) at the default precision, ahead of the first
    :func:`compute_basis` (see :func:`splatdeform.basis.warm_up`). Raises DeviceError without
    a device."""
    dev = _select_device(device)
    state = _state(dev)
    if k is not None and k >= 1:
        _kernel(state, _config(dev, int(k), bool(gradients), "auto"))


# ----------------------------------------------------------------------------- kernel build


@dataclass(frozen=True)
class _Config:
    k: int
    gradients: bool
    fp64: bool
    vw: int  # points per work-item (vector width)
    wg: int  # work-items per work-group
    tile: int  # centers per local-memory tile

    @property
    def points_per_group(self) -> int:
        return self.vw * self.wg

    def options(self) -> list[str]:
        return [
            "-I",
            str(resource_dir("kernels")),
            f"-DK={self.k}",
            f"-DGRADIENTS={int(self.gradients)}",
            f"-DUSE_FP64={int(self.fp64)}",
            f"-DVW={self.vw}",
            f"-DWG={self.wg}",
            f"-DTILE={self.tile}",
            f"-DUNROLL_K={int(self.k <= MAX_UNROLLED_K)}",
        ]


def _config(dev: object, k: int, gradients: bool, precision: str) -> _Config:
    if precision == "double" and not _has_fp64(dev):
        raise DeviceError(
            f"precision: 'double' needs cl_khr_fp64, which {dev.name.strip()!r} lacks"
        )
    fp64 = _has_fp64(dev) if precision == "auto" else precision == "double"
    if dev.type & cl.device_type.CPU:
        # One SIMD lane per point: explicit vectors beat PoCL's implicit work-item vectorisation
        # (1M x 200 x k=4 with gradients on 2 cores: 0.076 s as double8 vs 0.88 s scalar).
        width = dev.preferred_vector_width_double if fp64 else dev.preferred_vector_width_float
        vw = max(w for w in (1, 2, 4, 8, 16) if w <= max(1, width))
        wg = 8
    else:  # GPUs are SIMT already: one point per work-item, larger groups share the tile
        vw, wg = 1, 64
    wg = min(wg, dev.max_work_group_size)
    tile = 64
    local_bytes = tile * (3 + k) * (8 if fp64 else 4)
    while tile > 1 and local_bytes > dev.local_mem_size // 2:
        tile //= 2
        local_bytes //= 2
    return _Config(k=k, gradients=gradients, fp64=fp64, vw=vw, wg=wg, tile=tile)


def _kernel(state: _DeviceState, config: _Config) -> object:
    with state.lock:
        program = state.programs.get(config)
        if program is None:
            source = resource_path("kernels", "basis.cl").read_text()
            try:
                with noting_slow_build("basis", state.device.platform.name):
                    program = cl.Program(state.context, source).build(options=config.options())
            except cl.Error as exc:  # a broken kernel source is our bug, not the user's input
                raise RuntimeError(f"kernels/basis.cl failed to build: {exc}") from exc
            state.programs[config] = program
    return cl.Kernel(program, "basis")


# ----------------------------------------------------------------------------- validation


_check_points = check_points  # one input check for both backends (basis/checks.py)
_check_fit = check_fit


# ----------------------------------------------------------------------------- evaluation


def compute_basis(
    points: np.ndarray,
    fit: RbfFit,
    *,
    gradients: bool = True,
    device: str | None = None,
    max_chunk_points: int = DEFAULT_MAX_CHUNK_POINTS,
    precision: str = "auto",
) -> Basis:
    """Evaluate the basis of ``fit`` at ``points`` on an OpenCL device.

    points: (N, 3) float/int array in model units. fit: the fitted field (normalised coords).
    gradients: also return the (N, k, 3) gradients, in model units.
    device: which device (see the module docstring); None = ``PYOPENCL_CTX`` or the first one.
    max_chunk_points: points per device round trip; device memory stays bounded by it (and by
    256 MiB per chunk), host memory holds only the float32 results and one normalised chunk.
    precision: "auto" (double where the device has cl_khr_fp64, else compensated float32),
    "double" or "float" (Kahan-compensated float32 accumulation). Results are float32 either way.

    Returns Basis(values (N, k) float32, gradients (N, k, 3) float32 or None).
    Raises InputError for bad arguments (before any device work), DeviceError without a device.
    """
    arr = _check_points(points)
    centers, weights, center, scale = _check_fit(fit)
    if precision not in PRECISIONS:
        raise InputError(f"precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    if isinstance(max_chunk_points, bool) or not isinstance(max_chunk_points, (int, np.integer)):
        raise InputError(f"max_chunk_points: expected an integer >= 1, got {max_chunk_points!r}")
    if max_chunk_points < 1:
        raise InputError(f"max_chunk_points: expected an integer >= 1, got {max_chunk_points}")

    dev = _select_device(device)
    config = _config(dev, weights.shape[1], bool(gradients), precision)
    return _run(_state(dev), config, arr, centers, weights, center, scale, int(max_chunk_points))


def _run(
    state: _DeviceState,
    config: _Config,
    arr: np.ndarray,
    centers: np.ndarray,
    weights: np.ndarray,
    center: np.ndarray,
    scale: float,
    max_chunk_points: int,
) -> Basis:
    """Evaluate validated inputs with one kernel configuration, chunk by chunk.

    arr (N, 3) model units; centers (n, 3) and weights (4 + n, k) float64; center (3,), scale."""
    n_points, k = arr.shape[0], weights.shape[1]
    values = np.empty((n_points, k), dtype=np.float32)
    grads = np.empty((n_points, k, 3), dtype=np.float32) if config.gradients else None
    for _ in _chunks(state, config, arr, centers, weights, center, scale, max_chunk_points,
                     values, grads):
        pass
    return Basis(values=values, gradients=grads)


def chunks(
    points: np.ndarray,
    fit: RbfFit,
    *,
    gradients: bool = True,
    device: str | None = None,
    max_chunk_points: int = DEFAULT_MAX_CHUNK_POINTS,
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray | None]]:
    """The basis of ``fit`` at ``points`` (N, 3) one device chunk at a time, never all N rows:
    yields (start, stop, values (m, k) float32, gradients (m, k, 3) float32 or None) for rows
    start:stop, in views of host buffers the step after next reuses. Precision
    ``auto`` (double where the device has it). What one-shot evaluation
    (:mod:`splatdeform.basis.oneshot`) runs with k = 3 columns W delta_c."""
    arr = _check_points(points)
    centers, weights, center, scale = _check_fit(fit)
    dev = _select_device(device)
    config = _config(dev, weights.shape[1], bool(gradients), "auto")
    yield from _chunks(_state(dev), config, arr, centers, weights, center, scale,
                       max(1, int(max_chunk_points)))


def _chunks(
    state: _DeviceState,
    config: _Config,
    arr: np.ndarray,
    centers: np.ndarray,
    weights: np.ndarray,
    center: np.ndarray,
    scale: float,
    max_chunk_points: int,
    values: np.ndarray | None = None,
    grads: np.ndarray | None = None,
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray | None]]:
    """Run the kernel chunk by chunk and yield (start, stop, values (m, k), grads (m, k, 3) or
    None) float32: rows of ``values`` / ``grads`` when given (the whole (N, ...) outputs), else
    views of two chunk-sized host slots in turn. Chunk i + 1 is uploaded and its kernel started
    before chunk i is yielded, so the device computes while the caller applies chunk i."""
    n_points, k, n_centers = arr.shape[0], weights.shape[1], centers.shape[0]
    gradients = config.gradients
    if n_points == 0:
        return
    dev = state.device
    kernel = _kernel(state, config)
    real = np.float64 if config.fp64 else np.float32

    # chunk size: a multiple of the work-group's points, bounded by the byte budget
    group = config.points_per_group
    out_bytes = 4 * k * (4 if gradients else 1)
    per_point = 3 * np.dtype(real).itemsize + out_bytes
    chunk = min(max_chunk_points, n_points, max(1, CHUNK_BYTE_BUDGET // per_point))
    chunk = min(chunk, max(1, int(dev.max_mem_alloc_size) // out_bytes))
    chunk = -(-chunk // group) * group
    own = values is None
    if own:  # two chunk-sized host slots: one handed out while the next chunk computes
        values = np.empty((2, chunk, k), dtype=np.float32)
        grads = np.empty((2, chunk, k, 3), dtype=np.float32) if gradients else None

    mf = cl.mem_flags
    ctx, queue = state.context, state.queue
    packed = np.zeros((max(n_centers, 1), 3 + k), dtype=real)  # zero-size buffers are illegal
    packed[:n_centers, :3] = centers
    packed[:n_centers, 3:] = weights[4:]
    poly = np.ascontiguousarray(weights[:4], dtype=real)
    d_centers = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=packed)
    d_poly = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=poly)
    d_points = cl.Buffer(ctx, mf.READ_ONLY, 3 * chunk * np.dtype(real).itemsize)
    d_values = cl.Buffer(ctx, mf.WRITE_ONLY, chunk * k * 4)
    d_grads = cl.Buffer(ctx, mf.WRITE_ONLY, chunk * k * 12 if gradients else 4)
    host_points = np.zeros((3, chunk), dtype=real)  # structure of arrays, zero padded

    kernel.set_args(
        d_points,
        np.int32(chunk),
        np.int32(0),
        d_centers,
        np.int32(n_centers),
        d_poly,
        real(1.0 / scale),
        d_values,
        d_grads,
    )

    def launch(start: int) -> None:
        """Upload chunk ``start`` and start its kernel (returns without waiting for it)."""
        stop = min(start + chunk, n_points)
        m = stop - start
        launched = -(-m // group) * group
        block = host_points[:, :m]  # normalise straight into the (3, m) upload buffer
        if config.fp64:
            np.subtract(arr[start:stop].T, center[:, None], out=block, casting="unsafe")
            block *= 1.0 / scale
        else:  # normalise in float64, round to float32 once
            block[...] = (arr[start:stop] - center).T / scale
        host_points[:, m:launched] = 0.0
        cl.enqueue_copy(queue, d_points, host_points)  # in order: after the previous kernel
        kernel.set_arg(2, np.int32(m))
        cl.enqueue_nd_range_kernel(queue, kernel, (launched // config.vw,), (config.wg,))
        queue.flush()

    starts = range(0, n_points, chunk)
    try:
        launch(0)
        for i, start in enumerate(starts):
            stop = min(start + chunk, n_points)
            if own:
                out_v = values[i % 2, : stop - start]
                out_g = None if grads is None else grads[i % 2, : stop - start]
            else:
                out_v = values[start:stop]
                out_g = None if grads is None else grads[start:stop]
            cl.enqueue_copy(queue, out_v, d_values)  # blocking: waits for chunk i's kernel
            if out_g is not None:
                cl.enqueue_copy(queue, out_g, d_grads)
            if i + 1 < len(starts):  # the next chunk computes while the caller uses this one
                launch(starts[i + 1])
            yield start, stop, out_v, out_g
        queue.finish()
    finally:
        with contextlib.suppress(Exception):  # a caller that stopped early: a kernel may run
            queue.finish()
        for buf in (d_centers, d_poly, d_points, d_values, d_grads):
            buf.release()
