"""Hostile glTF / GLB inputs (issue #32, round three): a glTF's JSON is checked as glTF 2.0
requires before any value in it is used.

- indices: a negative ``bufferView``/accessor index is refused, never Python's index from the
  end; a bool is not an integer; out-of-range, fractional and huge numbers are refused;
- each attribute's accessor type and component type against its semantic (POSITION VEC3 FLOAT,
  ROTATION VEC4, SCALE VEC3, OPACITY SCALAR, SH coefficients VEC3 FLOAT);
- ``byteStride`` at least one element, at most 252, a multiple of 4; accessors inside their
  bufferView, bufferViews inside their buffer, offsets aligned; ``sparse`` refused;
- a missing SH coefficient of a degree is named (never a silent lower degree);
- every file a glTF names is a plain name beside it, a regular file (a FIFO or /dev/zero is
  refused without hanging), no larger than the buffer's byteLength; a data: URI is bounded;
- an SPZ-compressed glb whose SPZ stream is a bomb declaring 10M splats is refused before it is
  inflated (the count against the accessors, the declared size against the blob and memory);
- a seeded fuzz of a small valid glb (byte flips and JSON mutations) with a value oracle.

Every regression case runs the real CLI (``info``) in a subprocess with a timeout: exit 2, one
error line naming the file, no traceback, the input unchanged.
"""

from __future__ import annotations

import copy
import gzip
import json
import os
import struct
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import cpu_time, one_error_line, run_cli_peak
from helpers import run_cli as run
from splat_oracle import write_scene

from splatdeform.errors import FormatError, InputError
from splatdeform.io import gltf, load, save, spz

EXT = gltf.EXT
N = 40
TIMEOUT = 60


# --------------------------------------------------------------------------------------------
# fixtures and helpers


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A small valid SH degree-3 glb written by the project's own writer."""
    root = tmp_path_factory.mktemp("gltf3")
    src = write_scene(root / "scene.ply", N, 3, seed=32)
    return save(load(src), root / "good.glb")


def split(path: Path) -> tuple[dict, bytes]:
    raw = path.read_bytes()
    size = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20:20 + size])
    bin_size = struct.unpack_from("<I", raw, 20 + size)[0]
    return doc, raw[28 + size:28 + size + bin_size]


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A GLB container of ``doc`` and ``binary`` (the chunk as given, whatever the JSON says)."""
    text = json.dumps(doc).encode()
    text += b" " * ((-len(text)) % 4)
    binary += b"\0" * ((-len(binary)) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<III", gltf.GLB_MAGIC, 2, total)
            + struct.pack("<II", len(text), gltf.JSON_CHUNK) + text
            + struct.pack("<II", len(binary), gltf.BIN_CHUNK) + binary)


def variant(good: Path, folder: Path, name: str, change) -> Path:
    doc, binary = split(good)
    doc = copy.deepcopy(doc)
    result = change(doc)  # a change may return new binary chunk bytes
    binary = result if isinstance(result, bytes) else binary
    out = folder / name
    out.write_bytes(glb_bytes(doc, binary))
    return out


def prim(doc: dict) -> dict:
    return doc["meshes"][0]["primitives"][0]


def acc(doc: dict, name: str) -> dict:
    return doc["accessors"][prim(doc)["attributes"][name]]


def view_of(doc: dict, name: str) -> dict:
    return doc["bufferViews"][acc(doc, name)["bufferView"]]


def refused(path: Path, *needles: str, cwd: Path | None = None) -> str:
    """The CLI's ``info`` on ``path``: exit 2, one line naming the file (and ``needles``), no
    traceback; the file is unchanged and nothing is written beside it."""
    before = path.read_bytes() if path.is_file() else None
    listing = sorted(p.name for p in path.parent.iterdir())
    res = run("info", path, cwd=cwd or path.parent, timeout=TIMEOUT)
    line = one_error_line(res, 2, (str(path), *needles))
    if before is not None:
        assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == listing
    return line


ROT, SCALE, OPACITY = f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY"
SH3 = f"{EXT}:SH_DEGREE_3_COEF_4"


def _set(*keys_value):
    """change(doc): set doc[...][...] = value along ``keys`` (callables pick a sub-object)."""
    *keys, value = keys_value

    def change(doc):
        at = doc
        for k in keys[:-1]:
            at = k(at) if callable(k) else at[k]
        at[keys[-1]] = value
    return change


# --------------------------------------------------------------------------------------------
# item 3: accessors, bufferViews, buffers as glTF 2.0 requires


CASES = {
    # indices: negative, bool, out of range, not an integer
    "neg_view": (lambda d: acc(d, "POSITION").__setitem__("bufferView", -1),
                 "bufferView index of accessor 0 (POSITION) is -1"),
    "neg_accessor": (lambda d: prim(d)["attributes"].__setitem__("POSITION", -1),
                     "accessor index of attribute POSITION is -1"),
    "neg_buffer": (lambda d: view_of(d, "POSITION").__setitem__("buffer", -1),
                   "bufferViews[0].buffer is -1"),
    "bool_accessor": (lambda d: prim(d)["attributes"].__setitem__("POSITION", True),
                      "is true; expected an integer"),
    "bool_view": (lambda d: acc(d, ROT).__setitem__("bufferView", False),
                  "is false; expected an integer"),
    "far_accessor": (lambda d: prim(d)["attributes"].__setitem__(SCALE, 10**6),
                     "accessor index of attribute"),
    "float_view": (lambda d: acc(d, "POSITION").__setitem__("bufferView", 0.0),
                   "expected an integer"),
    "string_count": (lambda d: acc(d, "POSITION").__setitem__("count", "40"),
                     "count is '40'; expected an integer"),
    "huge_digits": (lambda d: acc(d, "POSITION").__setitem__("byteOffset", 10**300),
                    "an integer of 301 digits"),
    # component type and type for each semantic
    "position_scalar": (lambda d: acc(d, "POSITION").__setitem__("type", "SCALAR"),
                        "POSITION must be VEC3"),
    "position_ubyte": (lambda d: acc(d, "POSITION").update(componentType=gltf.UBYTE,
                                                            normalized=True),
                       "POSITION must be VEC3 of FLOAT"),
    "rotation_vec3": (lambda d: acc(d, ROT).__setitem__("type", "VEC3"), "must be VEC4"),
    "scale_vec4": (lambda d: acc(d, SCALE).__setitem__("type", "VEC4"), "must be VEC3"),
    "opacity_vec3": (lambda d: acc(d, OPACITY).__setitem__("type", "VEC3"),
                     "must be SCALAR"),
    "sh_vec4": (lambda d: acc(d, SH3).__setitem__("type", "VEC4"), "must be VEC3 of FLOAT"),
    "rotation_unnormalized": (lambda d: acc(d, ROT).update(componentType=gltf.SHORT),
                              "must be VEC4 of FLOAT, normalized BYTE, normalized SHORT"),
    "bad_component": (lambda d: acc(d, "POSITION").__setitem__("componentType", 5127),
                      "componentType 5127 is not a glTF component type"),
    "bad_type": (lambda d: acc(d, "POSITION").__setitem__("type", "VEC5"),
                 "type is 'VEC5'"),
    "normalized_float": (lambda d: acc(d, "POSITION").__setitem__("normalized", True),
                         "is normalized FLOAT"),
    # counts
    "count_zero": (lambda d: acc(d, "POSITION").__setitem__("count", 0),
                   "count is 0; expected 1.."),
    "count_huge": (lambda d: acc(d, "POSITION").__setitem__("count", 2**40),
                   "past its bufferView"),
    "counts_differ": (lambda d: acc(d, OPACITY).__setitem__("count", N - 1),
                      f"different counts (POSITION {N}, {OPACITY} {N - 1})"),
    # strides
    "stride_4_on_vec3": (lambda d: view_of(d, "POSITION").__setitem__("byteStride", 4),
                         "byteStride 4 is less than the 12 bytes of each element"),
    "stride_253": (lambda d: view_of(d, "POSITION").__setitem__("byteStride", 253),
                   "byteStride is 253; expected 4..252"),
    "stride_256": (lambda d: view_of(d, "POSITION").__setitem__("byteStride", 256),
                   "byteStride is 256; expected 4..252"),
    "stride_14": (lambda d: view_of(d, "POSITION").__setitem__("byteStride", 14),
                  "expected a multiple of 4"),
    "stride_past_view": (lambda d: view_of(d, "POSITION").__setitem__("byteStride", 16),
                         "past its bufferView"),
    # views inside buffers, accessors inside views, alignment
    "view_1e9_past": (lambda d: view_of(d, "POSITION").__setitem__("byteLength", 10**9),
                      "bufferView 0 runs past its buffer 0"),
    "view_2_62_past": (lambda d: view_of(d, OPACITY).__setitem__("byteLength", 2**62),
                       "runs past its buffer 0"),
    "view_offset_2_62": (lambda d: view_of(d, SCALE).__setitem__("byteOffset", 2**62),
                         "runs past its buffer 0"),
    "view_length_float": (lambda d: view_of(d, SCALE).__setitem__("byteLength", 1e9),
                          "byteLength is 1000000000.0; expected an integer"),
    "accessor_offset_past": (lambda d: acc(d, "POSITION").__setitem__("byteOffset", 400),
                             "past its bufferView"),
    "misaligned": (lambda d: acc(d, "POSITION").__setitem__("byteOffset", 2),
                   "expected a multiple of its 4-byte components"),
    "view_misaligned": (lambda d: view_of(d, "POSITION").__setitem__("byteOffset", 1),
                        "expected a multiple of its 4-byte components"),
    "buffer_2_62": (lambda d: d["buffers"][0].__setitem__("byteLength", 2**62),
                    "fewer than its byteLength"),
    "no_view": (lambda d: acc(d, ROT).pop("bufferView"), "has no bufferView"),
    "sparse": (lambda d: acc(d, "POSITION").__setitem__(
        "sparse", {"count": 1, "indices": {"bufferView": 0, "componentType": 5123},
                   "values": {"bufferView": 0}}), "sparse accessors are not supported"),
    # document structure of the wrong JSON type
    "attributes_list": (lambda d: prim(d).__setitem__("attributes", [0, 1]),
                        "attributes is an array; expected an object"),
    "accessors_object": (lambda d: d.__setitem__("accessors", {"0": {}}),
                         "accessors is an object; expected an array"),
    "mode_bool": (lambda d: prim(d).__setitem__("mode", False), "mode is false"),
    "used_not_strings": (lambda d: d["extensionsUsed"].append(7), "holds a non-string"),
    "node_not_object": (lambda d: d["nodes"].append(3), "nodes[1] is an integer"),
    "asset_string": (lambda d: d.__setitem__("asset", "2.0"), "asset is a string"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_gltf_json_is_checked_before_it_is_used(good, tmp_path, case):
    change, needle = CASES[case]
    refused(variant(good, tmp_path, f"{case}.glb", change), needle)


def test_the_valid_glb_loads_with_its_values(good):
    """The file the cases mutate is valid: it loads with its count and finite values."""
    model = load(good)
    assert model.n_points == N and model.gaussians.sh_rest.shape[1] == 45
    assert np.isfinite(model.positions).all()


def test_a_missing_sh_coefficient_is_named(good, tmp_path):
    """One SH degree-3 attribute left out: one line naming it, never a silent degree 2."""
    for name in (SH3, f"{EXT}:SH_DEGREE_1_COEF_0", f"{EXT}:SH_DEGREE_3_COEF_6"):
        out = variant(good, tmp_path, f"no_{name.rsplit(':', 1)[1]}.glb",
                      lambda d, name=name: prim(d)["attributes"].pop(name))
        refused(out, f"lacks {name}")
    # a coefficient outside degrees 0-3 (or n > 2l) is not taken for one
    for bad in ("SH_DEGREE_4_COEF_0", "SH_DEGREE_1_COEF_3", "SH_DEGREE_01_COEF_0"):
        out = variant(good, tmp_path, f"{bad}.glb",
                      lambda d, bad=bad: prim(d)["attributes"].__setitem__(f"{EXT}:{bad}", 0))
        refused(out, "is not an SH coefficient")


def test_shared_accessors_cannot_multiply_a_small_file(tmp_path):
    """Primitives that all name the same accessors (allowed by glTF) cannot turn a small file
    into gigabytes of splats: refused from the declared counts before anything is decoded."""
    src = write_scene(tmp_path / "scene.ply", 2000, 3, seed=5)
    one = save(load(src), tmp_path / "one.glb")

    def many(d):
        d["meshes"][0]["primitives"] *= 1000

    out = variant(one, tmp_path, "many.glb", many)
    refused(out, "primitives sharing accessors")
    # a few primitives sharing them are fine (the scene twice)
    twice = variant(one, tmp_path, "twice.glb", lambda d: d["meshes"][0]["primitives"].__imul__(2))
    assert load(twice).n_points == 4000


def test_deeply_nested_json_is_one_line(tmp_path):
    out = tmp_path / "nested.gltf"
    out.write_text("[" * 100_000 + "]" * 100_000)
    refused(out, "nested too deeply")


# --------------------------------------------------------------------------------------------
# item 2: files a glTF names, data: URIs


@pytest.fixture()
def external(good, tmp_path) -> tuple[dict, bytes]:
    """(the JSON of a .gltf whose buffer is a file beside it, the buffer's bytes)."""
    doc, binary = split(good)
    return doc, binary[:doc["buffers"][0]["byteLength"]]


def _gltf(folder: Path, doc: dict, uri: str, name: str = "x.gltf") -> Path:
    d = copy.deepcopy(doc)
    d["buffers"][0]["uri"] = uri
    out = folder / name
    out.write_text(json.dumps(d))
    return out


def test_an_external_buffer_beside_the_model_loads(tmp_path, external):
    doc, blob = external
    (tmp_path / "data%20x.bin").write_bytes(blob)
    (tmp_path / "data x.bin").write_bytes(blob)
    assert load(_gltf(tmp_path, doc, "data%20x.bin")).n_points == N  # percent-encoded URI
    # a link inside the model's folder is fine
    os.symlink("data x.bin", tmp_path / "inside.bin")
    assert load(_gltf(tmp_path, doc, "inside.bin", "y.gltf")).n_points == N


def test_external_buffers_must_be_regular_files_beside_the_model(tmp_path, external):
    doc, blob = external
    model = tmp_path / "model"
    model.mkdir()
    (tmp_path / "outside.bin").write_bytes(blob)
    os.symlink(tmp_path / "outside.bin", model / "out.bin")
    refused(_gltf(model, doc, "out.bin", "link.gltf"), "link leading out of its folder")
    os.symlink("/dev/zero", model / "zero.bin")
    refused(_gltf(model, doc, "zero.bin", "zero.gltf"), "zero.bin")
    os.mkfifo(model / "fifo.bin")
    refused(_gltf(model, doc, "fifo.bin", "fifo.gltf"), "named pipe (FIFO)")  # a hang: timeout
    (model / "sub").mkdir()
    refused(_gltf(model, doc, "sub", "dir.gltf"), "is a directory")
    refused(_gltf(model, doc, "../outside.bin", "dots.gltf"), "is not a plain file name")
    refused(_gltf(model, doc, "%2E%2E%2Foutside.bin", "encoded.gltf"),
            "is not a plain file name")
    refused(_gltf(model, doc, "/etc/passwd", "absolute.gltf"), "is not a plain file name")
    refused(_gltf(model, doc, "missing.bin", "missing.gltf"), "missing.bin")
    # larger than its byteLength: refused before it is read
    (model / "big.bin").write_bytes(blob + b"\0" * 4096)
    refused(_gltf(model, doc, "big.bin", "big.gltf"), "more than the")
    # shorter than its byteLength
    (model / "short.bin").write_bytes(blob[:-40])
    refused(_gltf(model, doc, "short.bin", "short.gltf"), "fewer than its byteLength")


def test_data_uris_are_bounded_by_their_byte_length(tmp_path, external):
    import base64

    doc, blob = external
    text = base64.b64encode(blob + b"\0" * 3000).decode()
    refused(_gltf(tmp_path, doc, "data:application/octet-stream;base64," + text, "long.gltf"),
            "holds more than its byteLength")
    refused(_gltf(tmp_path, doc, "data:application/octet-stream," + text, "plain.gltf"),
            "bad data URI")
    refused(_gltf(tmp_path, doc, "data:;base64,@@@@", "chars.gltf"), "bad data URI")


# --------------------------------------------------------------------------------------------
# item 4: an SPZ-compressed glb whose SPZ stream is a gzip bomb

def _spz_glb(path: Path, blob: bytes, count: int) -> Path:
    """An SPZ-compressed glb (the layout of data_tools.gltf_spz) holding ``blob`` and declaring
    ``count`` splats in its accessors."""
    attributes = {"POSITION": "VEC3", f"{EXT}:SCALE": "VEC3", f"{EXT}:ROTATION": "VEC4"}
    name = gltf.SPZ_EXTS[0]
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": [EXT, name],
           "extensionsRequired": [name], "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{
               "attributes": {a: i for i, a in enumerate(attributes)}, "mode": 0,
               "extensions": {EXT: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                    "extensions": {name: {"bufferView": 0}}}}}]}],
           "accessors": [{"componentType": gltf.FLOAT, "count": count, "type": t}
                         for t in attributes.values()],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(blob)}],
           "buffers": [{"byteLength": len(blob) + (-len(blob)) % 4}]}
    path.write_bytes(glb_bytes(doc, blob))
    return path


def _bomb(megabytes_of_zeros: int, splats: int, degree: int = 0) -> bytes:
    """gzip of an SPZ v3 header declaring ``splats`` followed by that many MB of zeros."""
    head = spz.HEADER.pack(spz.MAGIC, 3, splats, degree, 12, 0, 0)
    z = gzip.GzipFile  # streamed: the test itself never holds the zeros
    import io
    out = io.BytesIO()
    with z(fileobj=out, mode="wb", compresslevel=9, mtime=0) as gz:
        gz.write(head)
        chunk = bytes(1 << 20)
        for _ in range(megabytes_of_zeros):
            gz.write(chunk)
    return out.getvalue()


def _peak(path: Path) -> tuple[int, subprocess.CompletedProcess]:
    res, peak = run_cli_peak("info", path, cwd=path.parent, timeout=TIMEOUT)
    return peak, res


def _refused_early(out: Path, *needles: str) -> None:
    """``info`` on ``out`` fails with one line within a few CPU seconds, its peak RSS within
    10x the file + 300 MB (the declared arrays are never allocated)."""
    with cpu_time() as cpu:
        peak, res = _peak(out)
    assert cpu.seconds < 20
    one_error_line(res, 2, (str(out), *needles))
    assert peak <= 10 * out.stat().st_size + (300 << 20), peak


def test_spz_glb_bomb_declaring_10m_splats_is_refused_early(tmp_path):
    """A 1 MB gzip bomb (1 GB of zeros) declaring 10M degree-3 splats (650 MB of SPZ arrays),
    inside a glb whose accessors agree: refused as soon as the stream passes what its header
    declares, before the arrays are allocated (spz.py's bounded inflation)."""
    out = _spz_glb(tmp_path / "bomb.glb", _bomb(1024, 10_000_000, degree=3), 10_000_000)
    assert out.stat().st_size < 2 << 20
    _refused_early(out, "SPZ")


def test_spz_glb_declaring_more_than_its_bytes_can_hold_is_refused_before_inflating(tmp_path):
    """10M splats (650 MB) or 2^32 - 1 (a memory bound) declared in a 100-byte gzip stream:
    more than deflate can expand those bytes to, refused from the header alone."""
    for splats in (10_000_000, 2**32 - 1):
        blob = _bomb(0, splats, degree=3)
        assert len(blob) < 200
        _refused_early(_spz_glb(tmp_path / f"tiny{splats}.glb", blob, splats), "SPZ")


def test_spz_glb_count_other_than_the_accessors_is_refused_before_inflating(tmp_path):
    """The SPZ header says 10M splats, the glTF's accessors 40: refused from the header alone
    (16 bytes inflated), whatever the stream holds."""
    out = _spz_glb(tmp_path / "liar.glb", _bomb(64, 10_000_000), N)
    _refused_early(out, f"POSITION accessor count {N} differs from the 10000000 splats")


# --------------------------------------------------------------------------------------------
# item 5: seeded fuzz with a value oracle

HOSTILE = [-1, -2**31, 0, 1, 2, 3, 7, 2**31, 2**62, 10**30, 1.5, 1e300, "0", "VEC3", True,
           False, None, [], {}, [0], {"a": 1}]
FIELDS = {
    "accessor": ["bufferView", "byteOffset", "componentType", "count", "type", "normalized",
                 "sparse"],
    "view": ["buffer", "byteOffset", "byteLength", "byteStride"],
    "buffer": ["byteLength", "uri"],
    "attribute": None,  # an attribute's accessor index
    "primitive": ["mode", "attributes", "extensions"],
}
#: how often each part is mutated (the one buffer's uri or length mostly just fails)
WEIGHTS = {"accessor": 0.4, "view": 0.25, "buffer": 0.05, "attribute": 0.22, "primitive": 0.08}
TYPES = ["SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT4"]
COMPONENTS = [5120, 5121, 5122, 5123, 5125, 5126, 5127, 0]


def _mutate_json(doc: dict, rng: np.random.Generator) -> None:
    for _ in range(int(rng.integers(1, 4))):
        where = str(rng.choice(list(WEIGHTS), p=list(WEIGHTS.values())))
        value = HOSTILE[int(rng.integers(len(HOSTILE)))]
        if where == "attribute":
            attrs = prim(doc)["attributes"]
            if not isinstance(attrs, dict) or not attrs:
                continue
            name = list(attrs)[int(rng.integers(len(attrs)))]
            if rng.random() < 0.2:
                del attrs[name]
            else:
                attrs[name] = value
            continue
        target = {"accessor": doc["accessors"], "view": doc["bufferViews"],
                  "buffer": doc["buffers"], "primitive": [prim(doc)]}[where]
        item = target[int(rng.integers(len(target)))]
        key = FIELDS[where][int(rng.integers(len(FIELDS[where])))]
        if key == "type" and rng.random() < 0.7:
            value = TYPES[int(rng.integers(len(TYPES)))]
        elif key == "componentType" and rng.random() < 0.7:
            value = COMPONENTS[int(rng.integers(len(COMPONENTS)))]
        elif key in ("byteOffset", "byteStride", "byteLength", "count") and rng.random() < 0.5:
            value = int(item.get(key, 0) or 0) + int(rng.integers(-16, 17))
        if rng.random() < 0.15:
            item.pop(key, None)
        else:
            item[key] = value


def _declared(raw: bytes) -> int:
    """The splat count the (mutated) file's JSON declares: its splat primitives' POSITION
    accessor counts."""
    if raw[:4] == b"glTF":
        raw = raw[20:20 + struct.unpack_from("<I", raw, 12)[0]]
    doc = json.loads(raw)
    return sum(doc["accessors"][p["attributes"]["POSITION"]]["count"]
               for m in doc["meshes"] for p in m["primitives"] if EXT in p.get("extensions", {}))


def test_fuzzed_glb_fails_with_one_line_or_loads_its_declared_finite_values(good, tmp_path):
    """400 seeded mutations of a small valid glb (byte flips, truncations, JSON field
    mutations: negative indices, huge counts, wrong types, missing keys) and of the same
    scene as a .gltf with a data: URI. Each either fails with one FormatError/InputError line
    naming the file, or loads with the count its JSON declares and finite values. Bounded
    time."""
    import base64

    rng = np.random.default_rng(32)
    doc, binary = split(good)
    raw = good.read_bytes()
    json_end = 20 + struct.unpack_from("<I", raw, 12)[0]
    loaded = failed = 0
    with cpu_time() as cpu:   # CPU seconds, this process's: the loads are bounded work
        for i in range(400):
            kind = i % 4
            bad = tmp_path / ("fuzz.gltf" if kind == 3 else "fuzz.glb")
            if kind == 0:  # JSON field mutations
                d = copy.deepcopy(doc)
                _mutate_json(d, rng)
                case = glb_bytes(d, binary)
            elif kind == 1:  # byte flips, half of them in the JSON chunk
                b = bytearray(raw)
                for _ in range(int(rng.integers(1, 5))):
                    at = int(rng.integers(20, json_end)) if rng.random() < 0.5 else \
                        int(rng.integers(0, len(b)))
                    b[at] = int(rng.integers(0, 256))
                case = bytes(b)
            elif kind == 3:  # .gltf: JSON mutations, the buffer a data: URI
                d = copy.deepcopy(doc)
                d["buffers"][0]["uri"] = "data:application/octet-stream;base64," + \
                    base64.b64encode(binary[:d["buffers"][0]["byteLength"]]).decode()
                _mutate_json(d, rng)
                case = json.dumps(d).encode()
            else:  # a JSON mutation with a truncated or flipped binary chunk
                d = copy.deepcopy(doc)
                _mutate_json(d, rng)
                cut = bytearray(binary if rng.random() < 0.7 else
                                binary[:int(rng.integers(0, len(binary) + 1))])
                for _ in range(int(rng.integers(0, 4)) if cut else 0):
                    cut[int(rng.integers(len(cut)))] ^= 0xFF
                case = glb_bytes(d, bytes(cut))
            bad.write_bytes(case)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    model = load(bad)
            except (FormatError, InputError) as exc:
                text = str(exc)
                assert str(bad) in text and "\n" not in text, (i, text)
                failed += 1
                continue
            loaded += 1
            assert model.n_points == _declared(case), i
            assert np.isfinite(model.positions).all(), i
            g = model.gaussians
            for name in ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
                values = getattr(g, name)
                assert values is None or np.isfinite(values).all(), (i, name)
    assert cpu.seconds < 30
    assert loaded and failed > 100, (loaded, failed)
