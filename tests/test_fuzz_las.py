"""Fuzzing the LAS/LAZ reader and the edit-config loader, seeded and bounded.

LAS: header fields set to hostile values (0, 1, the type's maximum, 2^31, NaN, +-inf, 1e300,
random) and random bytes flipped in the header, the VLR area and the point data of small files
made with laspy (LAS 1.2 format 3, LAS 1.4 format 6 with extra bytes and an EVLR, LAZ). Every
mutation must load with finite coordinates or raise the project's own error, with the memory
child process's peak resident memory (VmHWM, reset before each load: it sees lazrs and
laspy's buffers, which tracemalloc does not) bounded by 10x the file size + 8 MiB.

Configs: leaves of a valid edit config replaced by hostile values, and random byte edits of
its YAML text. Each must give an EditConfig whose transform is finite, or a ConfigError/
InputError. Derandomized by fixed seeds, so a failure reproduces.
"""

from __future__ import annotations

import copy
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import load_peaks, make_las

from splatdeform.deform.handle import compose_transform
from splatdeform.edit.config import load_edit
from splatdeform.errors import SplatdeformError

BASE_BYTES = 8 << 20    # page-granular slack of one load in a warm child (measured 0-5 MiB)
PER_FILE_BYTE = 10      # the target: <= 10x the input + a constant

# (struct format, byte offset) of the header fields a mutation targets
FIELDS = [("<B", 24), ("<B", 25), ("<H", 94), ("<I", 96), ("<I", 100), ("<B", 104),
          ("<H", 105), ("<I", 107), ("<d", 131), ("<d", 139), ("<d", 147), ("<d", 155),
          ("<d", 163), ("<d", 171), ("<Q", 235), ("<I", 243), ("<Q", 247)]
FLOATS = [0.0, -0.0, 1e-300, 1e300, -1e300, float("nan"), float("inf"), float("-inf"), 3.4e38]


def _value(rng: np.random.Generator, fmt: str):
    if fmt == "<d":
        return FLOATS[int(rng.integers(len(FLOATS)))] if rng.random() < 0.8 \
            else float(rng.normal() * 10 ** int(rng.integers(-10, 10)))
    top = 2 ** (8 * struct.calcsize(fmt)) - 1
    picks = [0, 1, 2, 3, 4, 5, 11, 255, 2**15, 2**31, top, top - 1]
    v = picks[int(rng.integers(len(picks)))] if rng.random() < 0.7 else int(rng.integers(0, 2**31))
    return min(v, top)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> list[bytes]:
    root = tmp_path_factory.mktemp("lasfuzz")
    return [make_las(root / "a12.las", n=400).read_bytes(),
            make_las(root / "a14.las", "1.4", 6, n=400, extra=True, evlr=True).read_bytes(),
            make_las(root / "a.laz", n=400).read_bytes()]


def _mutations(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    kind = rng.integers(3)
    offset = struct.unpack_from("<I", out, 96)[0]
    if kind == 0:   # one or two header fields set to hostile values
        for _ in range(int(rng.integers(1, 3))):
            fmt, at = FIELDS[int(rng.integers(len(FIELDS)))]
            if at + struct.calcsize(fmt) <= len(out):
                struct.pack_into(fmt, out, at, _value(rng, fmt))
    elif kind == 1:  # random bytes in the header and VLR area
        for _ in range(int(rng.integers(1, 6))):
            out[int(rng.integers(0, min(offset, len(out))))] = int(rng.integers(256))
    else:            # bit flips in the point data (LAZ: in the compressed chunks)
        for _ in range(int(rng.integers(1, 12))):
            i = int(rng.integers(offset, len(out)))
            out[i] ^= 1 << int(rng.integers(8))
    return bytes(out)


@pytest.mark.parametrize("which", [0, 1, 2], ids=["las12", "las14", "laz"])
def test_fuzz_las(which, seeds, tmp_path: Path) -> None:
    rng = np.random.default_rng(20 + which)
    data = seeds[which]
    suffix = ".laz" if which == 2 else ".las"
    paths = []
    for case in range(120):
        path = tmp_path / f"m{case}{suffix}"
        path.write_bytes(_mutations(data, rng))
        paths.append(path)
    warm = tmp_path / f"seed{suffix}"   # the first load imports the readers: not counted
    warm.write_bytes(data)
    outcomes = {"loaded": 0, "refused": 0}
    for case, row in enumerate(load_peaks([warm, *paths])[1:]):   # one child, VmHWM per load
        assert "escaped" not in row, (case, row["escaped"])
        if "error" in row:
            assert "\n" not in row["error"] and str(paths[case]) in row["error"], (case, row)
            outcomes["refused"] += 1
        else:
            assert row["finite"], case
            outcomes["loaded"] += 1
        size = paths[case].stat().st_size
        assert row["peak"] <= BASE_BYTES + PER_FILE_BYTE * size, (case, row["peak"], size)
    assert outcomes["refused"] > 0 and outcomes["loaded"] > 0, outcomes


# ------------------------------------------------------------------------------ configs

HOSTILE = [0, -1, 1e-300, 1e300, -1e300, ".nan", ".inf", "-.inf", "", "x", None, True, [],
           {}, [1e300, 1e300, 0], [0, 0, 0], [1, 2], list(range(50)), {"file": "/dev/zero"},
           "*", 2**70, -(2**70), "1e39", {"a": [1] * 5}]


def _base(tmp_path: Path) -> dict:
    return {"input": str(tmp_path / "bar.ply"), "output": "out/bent.ply",
            "regions": {"units": "model",
                        "fixed": [{"box": {"min": [-1, -1, -1], "max": [1.0, 1, 1]}}],
                        "handle": [{"box": {"min": [3.0, -1, -1], "max": [5, 1, 1]}}]},
            "handle": {"transform": {"pivot": [0, 0, 0], "scale": [1, 1, 1],
                                     "rotate": {"axis": [0, 0, 1], "degrees": 20},
                                     "translate": [0, 0.2, 0]}},
            "fit": {"tolerance": 1e-3}, "backend": "numpy"}


def _leaves(node, path=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(node, list) and node and isinstance(node[0], dict | list):
        for i, v in enumerate(node):
            yield from _leaves(v, (*path, i))
    else:
        yield path


def _set(node, path, value):
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _check(path: Path) -> str:
    try:
        cfg = load_edit(path)
    except SplatdeformError as exc:
        assert "\n" not in str(exc), str(exc)
        return "refused"
    except Exception as exc:  # noqa: BLE001
        raise AssertionError(f"{path.read_text()[:300]!r}: {type(exc).__name__}: {exc}") from exc
    t = cfg.handle.transform if cfg.handle is not None else None
    if t is not None:
        m = compose_transform(pivot=np.zeros(3) if t.pivot == "centroid" else np.array(t.pivot),
                              scale=t.scale, axis=t.rotate.axis, degrees=t.rotate.degrees,
                              translate=t.translate)
        assert np.isfinite(m).all() and abs(np.linalg.det(m[:3, :3])) > 0, (t, m)
        assert math.isfinite(t.rotate.degrees) and abs(t.rotate.degrees) <= 1e6
    return "loaded"


def test_fuzz_config_values(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    base = _base(tmp_path)
    leaves = list(_leaves(base))
    seen = {"loaded": 0, "refused": 0}
    for case in range(300):
        cfg = copy.deepcopy(base)
        for _ in range(int(rng.integers(1, 3))):
            value = HOSTILE[int(rng.integers(len(HOSTILE)))]
            _set(cfg, leaves[int(rng.integers(len(leaves)))], copy.deepcopy(value))
        text = yaml.safe_dump(cfg).replace("'.nan'", ".nan").replace("'.inf'", ".inf") \
            .replace("'-.inf'", "-.inf")
        path = tmp_path / f"c{case}.yaml"
        path.write_text(text)
        seen[_check(path)] += 1
    assert seen["refused"] > 0 and seen["loaded"] > 0, seen


def test_fuzz_config_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    raw = yaml.safe_dump(_base(tmp_path)).encode()
    alphabet = b" \t\n:-[]{}&*!|>'\"#%@`,.0123456789e\x00\xff"
    for case in range(300):
        data = bytearray(raw)
        for _ in range(int(rng.integers(1, 6))):
            at = int(rng.integers(len(data)))
            op = rng.integers(3)
            byte = alphabet[int(rng.integers(len(alphabet)))]
            if op == 0:
                data[at] = byte
            elif op == 1:
                data.insert(at, byte)
            else:
                del data[at]
        path = tmp_path / f"b{case}.yaml"
        path.write_bytes(bytes(data))
        _check(path)
