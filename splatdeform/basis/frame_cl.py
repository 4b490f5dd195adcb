"""OpenCL per-frame apply (host side of ``kernels/frame.cl``): deformed positions and normals
of N points from their precomputed basis, one work-item per point.

The context and queue come from :mod:`splatdeform.basis.opencl` (the one place that creates
them); the program is built once per (K, normals) and cached with that device's programs. The
host arrays are handed to the device as they are (``USE_HOST_PTR``): on a CPU device (PoCL)
nothing is copied, on a GPU the driver moves them per call.
"""

from __future__ import annotations

import numpy as np

from ..errors import DeviceError, InputError
from ..resources import resource_path
from .kernel_cache import noting_slow_build
from .opencl import _select_device, _state, cl

#: work-items per work-group (PoCL vectorises a group's work-items: 64 measured fastest)
WORK_GROUP = 64


def _program(state, k: int, normals: bool):
    key = ("frame", k, normals)
    with state.lock:
        program = state.programs.get(key)
        if program is None:
            source = resource_path("kernels", "frame.cl").read_text()
            try:
                with noting_slow_build("frames", state.device.platform.name):
                    program = cl.Program(state.context, source).build(
                        options=[f"-DK={k}", f"-DNORMALS={int(normals)}"])
            except cl.Error as exc:  # a broken kernel source is our bug, not the user's input
                raise RuntimeError(f"kernels/frame.cl failed to build: {exc}") from exc
            state.programs[key] = program
    return program


def _f32(name: str, a: np.ndarray | None, shape: tuple) -> np.ndarray | None:
    if a is None:
        return None
    arr = np.ascontiguousarray(a, dtype=np.float32)
    if arr.shape != shape:
        raise InputError(f"{name}: expected shape {shape}, got {arr.shape}")
    return arr


def deform_frame_opencl(positions: np.ndarray, normals: np.ndarray | None, values: np.ndarray,
                        gradients: np.ndarray | None, delta_c: np.ndarray, *,
                        device: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """``deform_frame`` on an OpenCL device, in float32: positions (N, 3), normals (N, 3) or
    None, values (N, k), gradients (N, k, 3) (needed with normals), delta_c (k, 3) ->
    (positions (N, 3) float32, normals (N, 3) float32 with each input normal's length, or
    None). Raises DeviceError without a device, InputError for mismatched shapes."""
    vals = np.ascontiguousarray(values, dtype=np.float32)
    if vals.ndim != 2 or vals.shape[1] < 1:
        raise InputError(f"values: expected shape (N, k) with k >= 1, got {vals.shape}")
    n, k = vals.shape
    pos = _f32("positions", positions, (n, 3))
    nrm = _f32("normals", normals, (n, 3))
    if nrm is not None and gradients is None:
        raise InputError("gradients: required to transform normals")
    grads = None if nrm is None else _f32("gradients", gradients, (n, k, 3))
    delta = _f32("delta_c", delta_c, (k, 3))
    out_p = np.empty((n, 3), np.float32)
    out_n = None if nrm is None else np.empty((n, 3), np.float32)
    if n == 0:
        return out_p, out_n
    dev = _select_device(device)
    largest = max(a.nbytes for a in (pos, nrm, vals, grads) if a is not None)
    if largest > int(dev.max_mem_alloc_size):  # ``auto`` then runs the numpy path
        raise DeviceError(f"deform_frame: {largest:,} bytes in one buffer exceed the device's "
                          f"largest allocation ({int(dev.max_mem_alloc_size):,})")
    state = _state(dev)
    kernel = cl.Kernel(_program(state, k, nrm is not None), "frame")
    mf = cl.mem_flags
    dummy = np.zeros(1, np.float32)

    def buf(a: np.ndarray | None, flags: int):
        return cl.Buffer(state.context, flags | mf.USE_HOST_PTR,
                         hostbuf=dummy if a is None else a)

    buffers = [buf(pos, mf.READ_ONLY), buf(nrm, mf.READ_ONLY), buf(vals, mf.READ_ONLY),
               buf(grads, mf.READ_ONLY),
               cl.Buffer(state.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=delta),
               buf(out_p, mf.WRITE_ONLY), buf(out_n, mf.WRITE_ONLY)]
    outs = [(buffers[5], out_p)] + ([] if out_n is None else [(buffers[6], out_n)])
    try:
        kernel.set_args(*buffers, np.int32(n))
        with state.lock:  # one frame at a time on the device's queue
            cl.enqueue_nd_range_kernel(state.queue, kernel,
                                       (-(-n // WORK_GROUP) * WORK_GROUP,), (WORK_GROUP,))
            for b, host in outs:  # mapping makes the results visible in the host arrays
                mapped, _ = cl.enqueue_map_buffer(state.queue, b, cl.map_flags.READ, 0,
                                                  host.shape, np.float32)
                mapped.base.release()
            state.queue.finish()
    finally:
        for b in buffers:
            b.release()
    return out_p, out_n
