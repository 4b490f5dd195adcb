"""Write a PlayCanvas ``.compressed.ply`` from 3DGS fields (test fixtures for the reader).

The quantisation splat-transform uses: splats in chunks of 256; per chunk the min/max of
position, log scale and colour; position and scale 11/10/11 bits, rotation as the index of the
largest quaternion component (made positive) plus the other three in 10 bits, colour and
opacity 8 bits; optional SH rest coefficients 8 bits each in an ``sh`` element.
"""

from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814


def _quantise(t: np.ndarray, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    return np.clip(np.round(t * mask), 0, mask).astype(np.uint32)


def _chunk_range(values: np.ndarray, owner: np.ndarray, chunks: int) -> tuple[np.ndarray, ...]:
    low = np.full(chunks, np.inf)
    high = np.full(chunks, -np.inf)
    np.minimum.at(low, owner, values)
    np.maximum.at(high, owner, values)
    return low, high


def _normalised(values: np.ndarray, owner: np.ndarray, low: np.ndarray,
                high: np.ndarray) -> np.ndarray:
    span = high[owner] - low[owner]
    return np.where(span > 0, (values - low[owner]) / np.where(span > 0, span, 1), 0.0)


def compressed_ply(positions: np.ndarray, scale_log: np.ndarray, rotation: np.ndarray,
                   opacity: np.ndarray, sh_dc: np.ndarray,
                   sh_rest: np.ndarray | None = None) -> bytes:
    """The bytes of a compressed PLY. positions/scale_log/sh_dc: (N, 3); rotation: (N, 4)
    (w first); opacity: (N,) logit; sh_rest: (N, M) or None."""
    n = len(positions)
    chunks = -(-n // 256)
    owner = np.arange(n) // 256
    chunk_cols: dict[str, np.ndarray] = {}
    packed = {}
    for name, values, bits in (("", positions, (11, 10, 11)), ("scale_", scale_log, (11, 10, 11))):
        word = np.zeros(n, dtype=np.uint32)
        for axis, (column, b, shift) in enumerate(zip(values.T, bits, (21, 11, 0), strict=True)):
            low, high = _chunk_range(column, owner, chunks)
            chunk_cols[f"min_{name}{'xyz'[axis]}"] = low
            chunk_cols[f"max_{name}{'xyz'[axis]}"] = high
            word |= _quantise(_normalised(column, owner, low, high), b) << np.uint32(shift)
        packed["packed_position" if not name else "packed_scale"] = word
    color = sh_dc * SH_C0 + 0.5
    word = np.zeros(n, dtype=np.uint32)
    for i, c in enumerate("rgb"):
        low, high = _chunk_range(color[:, i], owner, chunks)
        chunk_cols[f"min_{c}"], chunk_cols[f"max_{c}"] = low, high
        word |= _quantise(_normalised(color[:, i], owner, low, high), 8) << np.uint32(24 - 8 * i)
    word |= _quantise(1 / (1 + np.exp(-opacity)), 8)
    packed["packed_color"] = word
    q = rotation / np.linalg.norm(rotation, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.sign(q[np.arange(n), largest])[:, None]
    others = np.stack([np.delete(row, k) for row, k in zip(q, largest, strict=True)])
    word = largest.astype(np.uint32) << np.uint32(30)
    for i, shift in enumerate((20, 10, 0)):
        word |= _quantise(others[:, i] * (np.sqrt(2) * 0.5) + 0.5, 10) << np.uint32(shift)
    packed["packed_rotation"] = word
    order = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"] + [
        f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"] + [
        f"{m}_{c}" for m in ("min", "max") for c in "rgb"]
    head = ["ply", "format binary_little_endian 1.0", "comment test fixture (splat-transform "
            "layout)", f"element chunk {chunks}"] + [f"property float {c}" for c in order]
    head += [f"element vertex {n}"] + [f"property uint {p}" for p in (
        "packed_position", "packed_rotation", "packed_scale", "packed_color")]
    chunk = np.empty(chunks, dtype=[(c, "<f4") for c in order])
    for c in order:
        chunk[c] = chunk_cols[c]
    vertex = np.empty(n, dtype=[(p, "<u4") for p in (
        "packed_position", "packed_rotation", "packed_scale", "packed_color")])
    for p in vertex.dtype.names:
        vertex[p] = packed[p]
    body = chunk.tobytes() + vertex.tobytes()
    if sh_rest is not None:
        head += [f"element sh {n}"] + [f"property uchar f_rest_{i}"
                                       for i in range(sh_rest.shape[1])]
        q8 = np.clip(np.trunc((sh_rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
        body += np.ascontiguousarray(q8).tobytes()
    return ("\n".join(head + ["end_header"]) + "\n").encode() + body
