"""Seeded fuzzing of the splat readers (issue #32): a few hundred mutations of a small valid file
per format (SPZ, SOG, PlayCanvas compressed PLY, .splat), each written by the project's own writer
from a small generated splat model (``data_tools.synth.gaussian_bar``).

Value oracle: a mutated file either fails with the project's FormatError/InputError (one line,
naming the file) or loads with the splat count its own header declares (read here independently:
the SPZ header through Python's gzip, the SOG meta.json through zipfile/json, the PLY header's
vertex count, the .splat size / 32) and finite values (opacity may be +-inf). Loads run
in-process for speed; a handful of cases per format also run the CLI (``info``) in a subprocess
with a timeout: exit 0 or 2, no traceback, one error line. Seeded (numpy), so a failure names
the case that reproduces it. (``.ksplat`` is not read by this project: no fuzzer for it.)
"""

from __future__ import annotations

import gzip
import io
import json
import re
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

import splatdeform as sd
from data_tools.synth import gaussian_bar
from splatdeform.errors import FormatError, InputError
from splatdeform.io.splats import LossyWriteWarning

CASES = 300  # per format, every run: the same cases whatever the machine's load
CLI_CASES = 4  # per format, run through the CLI in a subprocess
CLI_TIMEOUT = 60
INTERESTING = [b"\x00", b"\xff", b"\x7f", b"\x80", b"\xff\xff\xff\xff", b"\xff\xff\xff\x7f",
               b"\x00\x00\xc0\x7f", b"\x00\x00\x80\x7f", b"\x00\x00\x80\xff", b"\xff\xff\x7f\x7f",
               b"\x01\x00\x00\x00", b"\x00\x00\x00\x80"]


def _model(n: int, degree: int, seed: int):
    return gaussian_bar(n, sh_degree=degree, seed=seed)


def _written(model, path: Path) -> bytes:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        sd.save(model, path)
    return path.read_bytes()


# --------------------------------------------------------------------------------------------
# byte mutations


def mutate_bytes(raw: bytes, rng: np.random.Generator, low: int = 0, times: int | None = None
                 ) -> bytes:
    """1-4 byte-level mutations at or after ``low``: bit flips, random or interesting bytes,
    inserts, deletes, truncation, a repeated run."""
    b = bytearray(raw)
    for _ in range(times or int(rng.integers(1, 5))):
        if len(b) <= low:
            b += bytes(rng.integers(0, 256, 4, dtype=np.uint8))
            continue
        at = int(rng.integers(low, len(b)))
        op = rng.choice(["flip", "byte", "word", "insert", "delete", "truncate", "repeat"],
                        p=[0.25, 0.2, 0.25, 0.08, 0.08, 0.06, 0.08])
        if op == "flip":
            b[at] ^= 1 << int(rng.integers(0, 8))
        elif op == "byte":
            b[at] = int(rng.integers(0, 256))
        elif op == "word":
            word = INTERESTING[int(rng.integers(0, len(INTERESTING)))]
            b[at:at + len(word)] = word
        elif op == "insert":
            b[at:at] = bytes(rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8))
        elif op == "delete":
            del b[at:at + int(rng.integers(1, 17))]
        elif op == "truncate":
            del b[at:]
        else:
            b[at:at] = b[at:at + int(rng.integers(1, 65))]
    return bytes(b)


# --------------------------------------------------------------------------------------------
# the oracle


def _finite_load(path: Path, declared: Callable[[bytes], int | None]) -> str:
    """Load ``path``: 'error' (a one-line project error naming it) or 'loaded' (the declared
    count, finite values); anything else fails the test."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = sd.load(path)
    except (FormatError, InputError) as exc:
        text = str(exc)
        assert "\n" not in text and str(path) in text, text
        return "error"
    want = declared(path.read_bytes())
    assert want is not None, "loaded a file whose declared count cannot be read"
    assert model.n_points == want, (model.n_points, want)
    assert np.isfinite(model.positions).all()
    g = model.gaussians
    assert g is not None
    for name in ("scale_log", "rotation", "sh_dc", "sh_rest"):
        value = getattr(g, name)
        assert value is None or np.isfinite(value).all(), name
    assert not np.isnan(g.opacity).any()  # +-inf allowed (a saturated opacity)
    return "loaded"


def _cli_info(path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "splatdeform.cli", "info", str(path)],
                         capture_output=True, text=True, timeout=CLI_TIMEOUT, cwd=path.parent)
    assert res.returncode in (0, 2), (res.returncode, res.stderr)
    assert "Traceback" not in res.stdout + res.stderr, res.stderr
    if res.returncode == 2:
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("splatdeform: error: "), res.stderr


def fuzz(tmp_path: Path, ext: str, seeds: list[bytes], mutate, declared, seed: int) -> dict:
    """Run the cases: (case index, mutated bytes) from ``mutate(seed bytes, rng)``; returns how
    many loaded and failed. A failing case is named by its index."""
    rng = np.random.default_rng(seed)
    path = tmp_path / f"fuzz{ext}"
    outcomes = {"error": 0, "loaded": 0}
    cli = []
    for case in range(CASES):
        raw = mutate(seeds[int(rng.integers(0, len(seeds)))], rng)
        path.write_bytes(raw)
        try:
            outcome = _finite_load(path, declared)
        except AssertionError as exc:
            raise AssertionError(f"{ext} case {case} (seed {seed}): {exc}") from exc
        except Exception as exc:  # noqa: BLE001 - any other exception is the bug looked for
            raise AssertionError(f"{ext} case {case} (seed {seed}): "
                                 f"{type(exc).__name__}: {exc}") from exc
        outcomes[outcome] += 1
        if len(cli) < CLI_CASES and (outcome == "error") == (len(cli) % 2 == 0):
            keep = tmp_path / f"cli{len(cli)}{ext}"
            keep.write_bytes(raw)
            cli.append(keep)
    for keep in cli:
        _cli_info(keep)
    assert sum(outcomes.values()) == CASES, outcomes
    assert outcomes["error"] >= 10, outcomes  # the mutations do reach the checks
    return outcomes


# --------------------------------------------------------------------------------------------
# SPZ: mutate the decompressed stream (header fields and arrays) and re-gzip it, or the gzip


def _spz_declared(raw: bytes) -> int | None:
    if raw[:4] == b"NGSP":  # v4: a plaintext header
        return int.from_bytes(raw[8:12], "little") if len(raw) >= 32 else None
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as f:
            head = f.read(16)
    except (OSError, EOFError):
        return None
    return int.from_bytes(head[8:12], "little") if len(head) == 16 else None


def _spz_mutate(raw: bytes, rng: np.random.Generator) -> bytes:
    if rng.random() < 0.2:
        return mutate_bytes(raw, rng)
    stream = bytearray(gzip.decompress(raw))
    if rng.random() < 0.4:  # a header field
        field = int(rng.choice([4, 8, 12, 13, 14, 15]))
        if field == 8:
            count = int.from_bytes(stream[8:12], "little")
            value = int(rng.choice([0, 1, count - 1, count + 1, 2 * count, 10**7, 2**32 - 1]))
            stream[8:12] = max(value, 0).to_bytes(4, "little")
        elif field == 4:
            stream[4:8] = int(rng.choice([1, 2, 3, 4, 5, 2**31])).to_bytes(4, "little")
        else:
            stream[field] = int(rng.choice([0, 1, 2, 3, 4, 12, 23, 24, 255]))
        if rng.random() < 0.5:
            return gzip.compress(bytes(stream), mtime=0)
    return gzip.compress(mutate_bytes(bytes(stream), rng, low=16), mtime=0)


def test_fuzz_spz(tmp_path):
    from splatdeform.io import spz
    from splatdeform.io.splats import fields_of

    model = _model(60, 1, seed=321)
    with spz.writing_version(3):  # the gzip seeds this mutator works on (v4: test_spz_v4)
        v3 = _written(model, tmp_path / "seed.spz")
        sh0 = _written(_model(40, 0, seed=322), tmp_path / "seed0.spz")
    v2 = gzip.compress(bytes(spz.encode(fields_of(model, "x", ".spz"), version=2)), mtime=0)
    for raw in (v3, v2, sh0):
        (tmp_path / "ok.spz").write_bytes(raw)
        assert _finite_load(tmp_path / "ok.spz", _spz_declared) == "loaded"
    out = fuzz(tmp_path, ".spz", [v3, v2, sh0], _spz_mutate, _spz_declared, seed=3201)
    assert out["loaded"] >= 10, out


# --------------------------------------------------------------------------------------------
# SOG: mutate meta.json values, an image's pixels or size, a member's bytes, or the archive


JSON_VALUES = [0, -1, 1, 2, 3, 255, 256, 65536, 10**9, 2**63, -2**63, 1e308, -1e308, 1e39,
               float("nan"), float("inf"), 0.5, "x", "", None, True, [], {}, [0.0] * 3,
               [1e30] * 3, [-100.0, -100.0, -100.0], [100.0] * 3, "../x.webp", "meta.json",
               "means_l.webp"]


def _json_paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _json_paths(item, (*prefix, key))
    elif isinstance(value, list) and len(value) <= 8:
        for i, item in enumerate(value):
            yield from _json_paths(item, (*prefix, i))
    elif isinstance(value, list):  # a codebook: a few entries
        for i in (0, 1, len(value) - 1):
            yield (*prefix, i)


def _set(doc, path, value):
    if not path:
        return value
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


def _sog_members(raw: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        return {name: z.read(name) for name in z.namelist()}


def _sog_zip(members: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:
        for name, data in members.items():
            z.writestr(zipfile.ZipInfo(name, (2020, 1, 1, 0, 0, 0)), data)
    return out.getvalue()


def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(out, "WEBP", lossless=True, exact=True, quality=0,
                                       method=0)
    return out.getvalue()


def _sog_mutate(raw: bytes, rng: np.random.Generator) -> bytes:
    from PIL import Image

    kind = rng.choice(["meta", "meta", "pixels", "size", "member", "archive", "drop"])
    if kind == "archive":
        return mutate_bytes(raw, rng)
    members = _sog_members(raw)
    if kind == "meta":
        meta = json.loads(members["meta.json"])
        paths = list(_json_paths(meta))
        for _ in range(int(rng.integers(1, 3))):
            target = paths[int(rng.integers(1, len(paths)))]
            try:
                meta = _set(meta, target, JSON_VALUES[int(rng.integers(0, len(JSON_VALUES)))])
            except (KeyError, IndexError, TypeError):
                pass
        members["meta.json"] = json.dumps(meta).encode()
        return _sog_zip(members)
    names = [m for m in members if m.endswith(".webp")]
    name = names[int(rng.integers(0, len(names)))]
    if kind == "drop":
        del members[name]
    elif kind == "member":
        members[name] = mutate_bytes(members[name], rng)
    else:
        rgba = np.asarray(Image.open(io.BytesIO(members[name])).convert("RGBA")).copy()
        if kind == "pixels":
            for _ in range(int(rng.integers(1, 6))):
                y, x = int(rng.integers(0, rgba.shape[0])), int(rng.integers(0, rgba.shape[1]))
                rgba[y, x, int(rng.integers(0, 4))] = int(rng.choice([0, 1, 127, 251, 252,
                                                                      255]))
        else:
            h, w = rgba.shape[:2]
            h2, w2 = (max(1, h + int(rng.integers(-3, 9))), max(1, w + int(rng.integers(-3, 9))))
            grown = np.zeros((h2, w2, 4), np.uint8)
            grown[:min(h, h2), :min(w, w2)] = rgba[:h2, :w2]
            rgba = grown
        members[name] = _webp(rgba)
    return _sog_zip(members)


def _sog_declared(raw: bytes) -> int | None:
    try:
        with zipfile.ZipFile(io.BytesIO(raw)) as z:
            count = json.loads(z.read("meta.json")).get("count")
    except (zipfile.BadZipFile, KeyError, ValueError, OSError, EOFError, AttributeError):
        return None
    return count if isinstance(count, int) else None


def test_fuzz_sog(tmp_path):
    sh1 = _written(_model(60, 1, seed=331), tmp_path / "seed.sog")
    sh0 = _written(_model(30, 0, seed=332), tmp_path / "seed0.sog")
    for raw in (sh1, sh0):
        (tmp_path / "ok.sog").write_bytes(raw)
        assert _finite_load(tmp_path / "ok.sog", _sog_declared) == "loaded"
    out = fuzz(tmp_path, ".sog", [sh1, sh0], _sog_mutate, _sog_declared, seed=3301)
    assert out["loaded"] >= 10, out


# --------------------------------------------------------------------------------------------
# PlayCanvas compressed PLY: header counts and words, body bytes (chunk bounds, packed words)


def _ply_declared(raw: bytes) -> int | None:
    end = raw.find(b"end_header")
    found = re.findall(rb"^element vertex (\d+)\s*$", raw[:max(end, 0)], re.M)
    return int(found[0]) if len(found) == 1 else None


def _ply_mutate(raw: bytes, rng: np.random.Generator) -> bytes:
    end = raw.index(b"end_header")
    body = raw.index(b"\n", end) + 1
    if rng.random() < 0.3:
        lines = raw[:end].split(b"\n")
        i = int(rng.integers(1, len(lines)))
        words = lines[i].split(b" ")
        if words[0] == b"element" and len(words) == 3 and rng.random() < 0.7:
            count = int(words[2])
            words[2] = str(max(0, count + int(rng.choice([-256, -1, 1, 255, 256, 10**6,
                                                          10**12])))).encode()
        else:
            j = int(rng.integers(0, len(words)))
            words[j] = [b"float", b"uint", b"uchar", b"double", b"int", b"list", b"vertex",
                        b"chunk", b"sh", b"packed_position", b"min_x", b"f_rest_0",
                        b"0"][int(rng.integers(0, 13))]
        lines[i] = b" ".join(words)
        return b"\n".join(lines) + raw[end:]
    return mutate_bytes(raw, rng, low=body)


def test_fuzz_compressed_ply(tmp_path):
    sh1 = _written(_model(300, 1, seed=341), tmp_path / "seed.compressed.ply")
    sh0 = _written(_model(20, 0, seed=342), tmp_path / "seed0.compressed.ply")
    for raw in (sh1, sh0):
        assert b"element chunk" in raw and b"packed_position" in raw
        (tmp_path / "ok.compressed.ply").write_bytes(raw)
        assert _finite_load(tmp_path / "ok.compressed.ply", _ply_declared) == "loaded"
    out = fuzz(tmp_path, ".compressed.ply", [sh1, sh0], _ply_mutate, _ply_declared,
               seed=3401)
    assert out["loaded"] >= 10, out


# --------------------------------------------------------------------------------------------
# .splat: 32-byte records, no header


def _splat_declared(raw: bytes) -> int | None:
    return len(raw) // 32 if raw and len(raw) % 32 == 0 else None


def _splat_mutate(raw: bytes, rng: np.random.Generator) -> bytes:
    if rng.random() < 0.7:  # keep whole records: the values are what is fuzzed
        b = bytearray(raw)
        for _ in range(int(rng.integers(1, 5))):
            record = int(rng.integers(0, len(b) // 32))
            field = int(rng.choice([0, 4, 8, 12, 16, 20, 24, 28]))
            word = INTERESTING[int(rng.integers(0, len(INTERESTING)))]
            word = (word * 4)[:4] if field < 24 else word[:4]
            at = 32 * record + field
            b[at:at + len(word)] = word
        return bytes(b)
    return mutate_bytes(raw, rng)


def test_fuzz_splat(tmp_path):
    seed = _written(_model(80, 0, seed=351), tmp_path / "seed.splat")
    (tmp_path / "ok.splat").write_bytes(seed)
    assert _finite_load(tmp_path / "ok.splat", _splat_declared) == "loaded"
    out = fuzz(tmp_path, ".splat", [seed], _splat_mutate, _splat_declared, seed=3501)
    assert out["loaded"] >= 10, out
