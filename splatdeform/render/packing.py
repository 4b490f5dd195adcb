"""The deformation basis as the vertex stage reads it (see ``shaders/deform.glsl``).

For k <= MAX_K, 16 float32 per point as vertex attributes: values b_0..b_3 then gradients
grad b_0 .. grad b_3; k < 4 is zero-padded. For MAX_K < k <= MAX_STORAGE_K (curve edits), a
shader storage buffer (GL 4.3+) of 4k float32 per point, k values then 3k gradient components,
read by ``gl_VertexID``; delta C is then ``uniform vec3 u_delta[K]`` with K a compile-time
define (one cached program per K).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.errors import InputError
from splatdeform.render.programs import MAX_K, MAX_STORAGE_K, program

ATTRIBUTE_LAYOUT = ("4f 3f 3f 3f 3f", "in_basis", "in_grad0", "in_grad1", "in_grad2", "in_grad3")


def _checked(values: np.ndarray, gradients: np.ndarray, n_points: int, max_k: int,
             too_many: str) -> tuple[np.ndarray, np.ndarray, int]:
    """values (N, k), gradients (N, k, 3) checked against ``n_points`` and 1 <= k <= max_k
    (``too_many``: the message when k is outside, formatted with k)."""
    vals = np.asarray(values)
    grads = np.asarray(gradients)
    if vals.ndim != 2 or vals.shape[0] != n_points:
        raise InputError(f"values: expected shape ({n_points}, k), got {vals.shape}")
    k = vals.shape[1]
    if not 1 <= k <= max_k:
        raise InputError(too_many.format(k=k))
    if grads.shape != (n_points, k, 3):
        raise InputError(f"gradients: expected shape ({n_points}, {k}, 3), got {grads.shape}")
    return vals, grads, k


def pack_basis(values: np.ndarray, gradients: np.ndarray, n_points: int) -> np.ndarray:
    """(N, 16) float32: values (N, k) then gradients (N, k, 3), k <= 4 zero-padded to 4."""
    vals, grads, k = _checked(
        values, gradients, n_points, MAX_K,
        f"values: the attribute path renders k <= {MAX_K} control DOFs, got k = {{k}} "
        "(larger k needs the storage-buffer path, see shaders/deform.glsl)")
    packed = np.zeros((n_points, 16), dtype=np.float32)
    packed[:, :k] = vals
    packed[:, 4 : 4 + 3 * k] = grads.reshape(n_points, 3 * k)
    return packed


def pack_basis_storage(values: np.ndarray, gradients: np.ndarray, n_points: int) -> np.ndarray:
    """(N, 4k) float32 for the storage-buffer path: per point the k values, then the 3k
    gradient components (grad b_0, grad b_1, ...). Any 1 <= k <= MAX_STORAGE_K."""
    vals, grads, k = _checked(
        values, gradients, n_points, MAX_STORAGE_K,
        f"values: expected 1 <= k <= {MAX_STORAGE_K} control DOFs, got k = {{k}}")
    packed = np.empty((n_points, 4 * k), dtype=np.float32)
    packed[:, :k] = vals
    packed[:, k:] = grads.reshape(n_points, 3 * k)
    return packed


def upload_basis(ctx: Any, values: np.ndarray, gradients: np.ndarray, n_points: int,
                 buffers: list[Any]) -> tuple[int, tuple[Any, ...] | None, Any]:
    """Send the basis to the GPU on the path its k needs (the new buffer is appended to
    ``buffers``, for the caller to free on failure). Returns (k, the vertex-array entry of
    the attribute path or None, the storage buffer or None)."""
    k = int(np.asarray(values).shape[1]) if np.ndim(values) == 2 else 0
    if k > MAX_K:
        packed = pack_basis_storage(values, gradients, n_points)
        program("feedback_deform", k)  # compile early: DeviceError below GL 4.3
        buffers.append(ctx.buffer(packed.tobytes()))
        return k, None, buffers[-1]
    packed = pack_basis(values, gradients, n_points)
    buffers.append(ctx.buffer(packed.tobytes()))
    return int(np.asarray(values).shape[1]), (buffers[-1], *ATTRIBUTE_LAYOUT), None


def pad_delta(delta_c: np.ndarray | None, k: int) -> np.ndarray:
    """(max(k, 4), 3) float32 delta C for the shader: ``delta_c`` (k, 3), zero-padded to 4 rows
    for the attribute path (k <= 4); None -> zeros."""
    out = np.zeros((max(int(k), MAX_K), 3), dtype=np.float32)
    if delta_c is None:
        return out
    d = np.asarray(delta_c, dtype=np.float64)
    if d.shape != (k, 3):
        raise InputError(f"delta_c: expected shape ({k}, 3) for a {k}-column basis, got {d.shape}")
    out[:k] = d
    return out
