"""A saved field is untrusted input (issue 43 items 1-3): a generated, seeded corpus of malformed
fields each ends with exit 2, one line naming the field file and the member, no output, and
bounded memory; selectors are rebuilt by kind name (never imported by a name in the file) and
paths in a field are never opened; version 1 fields still load; ``apply`` knows its support
(a model entirely outside is refused unless ``--extrapolate``) and its warnings name the
output, never a temporary file."""

from __future__ import annotations

import copy
import io
import json
import os
import shutil
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from splatdeform.cli import main
from splatdeform.field import Field
from splatdeform.field_apply import naming_output
from splatdeform.io import load, save
from splatdeform.model import PointModel
from tests.conftest import shared_file

ROOT = Path(__file__).resolve().parents[1]
EDIT = """input: in.ply
output: out.ply
backend: numpy
regions:
  units: relative
  fixed: [{box: {min: [0,0,0], max: [1,0.2,1]}}]
  handle: [{all: [{box: {min: [0,0.8,0], max: [1,1,1]}}, {not: {sphere: {center: [0,0,0],
           radius: 0.01}}}]}]
handle:
  transform: {rotate: {axis: [0,0,1], degrees: 15}, translate: [0.05, 0, 0]}
"""
INDICES = """input: in.ply
output: oi.ply
backend: numpy
regions:
  fixed: [{indices: {file: picked.txt}}]
points:
  pairs: [[-0.02,0.1,0.0,-0.018,0.1,0.0]]
"""


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """A folder with the bunny (in.ply), a handle field (f.npz), an indices field (fi.npz)
    and the deform outputs (out.ply)."""
    d = tmp_path_factory.mktemp("field")
    shutil.copy(shared_file("scans/bunny_res2.ply"), d / "in.ply")
    (d / "e.yaml").write_text(EDIT)
    assert main(["deform", str(d / "e.yaml"), "--save-field", str(d / "f.npz"),
                 "--quiet"]) == 0
    (d / "picked.txt").write_text(" ".join(str(i) for i in range(0, 400, 7)))
    (d / "i.yaml").write_text(INDICES)
    assert main(["deform", str(d / "i.yaml"), "--save-field", str(d / "fi.npz"),
                 "--quiet"]) == 0
    return d


def members(path: Path) -> tuple[dict, dict]:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads(str(arrays.pop("meta")))


def write(path: Path, arrays: dict, meta: dict | str | None) -> Path:
    out = dict(arrays)
    if meta is not None:
        out["meta"] = np.array(meta if isinstance(meta, str) else json.dumps(meta))
    with open(path, "wb") as fh:
        np.savez(fh, **out)
    return path


def refused(capsys, field: Path, model: Path, out: Path, member: str | None) -> str:
    """Apply and check the refusal: exit 2, one line naming the field (and the member), no
    output. Returns the line."""
    code = main(["apply", str(field), str(model), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert str(field) in err, err
    if member is not None:
        assert f"member {member!r}" in err, err
    assert "Traceback" not in err and "internal error" not in err
    assert not out.exists()
    return err


# ----------------------------------------------------------------- arrays (dtype, shape, values)

def _set(name, value):
    def fn(a, m):
        a[name] = value(a[name]) if callable(value) else value
    return fn


def _drop(name):
    def fn(a, m):
        a.pop(name)
    return fn


def _matrix(row):
    def fn(a, m):
        mat = a["matrices"].copy()
        mat[0] = row
        a["matrices"] = mat
    return fn


SINGULAR = np.diag([1.0, 1.0, 0.0, 1.0])
PERSPECTIVE = np.eye(4)
PERSPECTIVE[3] = [0, 0, 0.5, 1]
ARRAY_CASES = {
    "centers complex": ("centers", _set("centers", lambda c: c.astype(np.complex128))),
    "centers strings": ("centers", _set("centers", lambda c: c.astype(str))),
    "centers bool": ("centers", _set("centers", lambda c: c > 0)),
    "centers datetime": ("centers", _set("centers", lambda c: np.zeros(c.shape, "M8[s]"))),
    "centers float16": ("centers", _set("centers", lambda c: c.astype(np.float16))),
    "centers (n, 4)": ("centers", _set("centers", lambda c: np.zeros((c.shape[0], 4)))),
    "centers NaN": ("centers", _set("centers", lambda c: np.where(c > 0, np.nan, c))),
    "weights transposed": ("weights", _set("weights", lambda w: w.T.copy())),
    "weights inf": ("weights", _set("weights", lambda w: w * np.inf)),
    "delta_c (k, 4)": ("delta_c", _set("delta_c", lambda d: np.zeros((d.shape[0], 4)))),
    "norm_scale zero": ("norm_scale", _set("norm_scale", np.float64(0.0))),
    "norm_scale negative": ("norm_scale", _set("norm_scale", np.float64(-2.0))),
    "norm_center (2,)": ("norm_center", _set("norm_center", np.zeros(2))),
    "frames NaN": ("frames", _set("frames", lambda f: f * np.nan)),
    "frames count": ("inverses", _set("frames", lambda f: np.concatenate([f, f]))),
    "inverses altered": ("inverses", _set("inverses", lambda v: v * 1.5)),
    "matrices zero": ("matrices", _matrix(np.zeros((4, 4)))),
    "matrices singular": ("matrices", _matrix(SINGULAR)),
    "matrices perspective": ("matrices", _matrix(PERSPECTIVE)),
    "matrices count": ("matrices", _set("matrices", lambda x: x[:0])),
    "support reversed": ("support", _set("support", lambda s: s[::-1].copy())),
    "support (3,)": ("support", _set("support", np.zeros(3))),
    "missing centers": ("centers", _drop("centers")),
    "missing weights": ("weights", _drop("weights")),
    "missing delta_c": ("delta_c", _drop("delta_c")),
    "missing frames": ("frames", _drop("frames")),
    "missing inverses": ("inverses", _drop("inverses")),
    "missing matrices": ("matrices", _drop("matrices")),
    "missing meta": ("meta", None),
    "missing support": ("support", _drop("support")),
    "extra member": ("extra", _set("extra", np.zeros(3))),
    "fixed_idx without indices": ("fixed_idx", _set("fixed_idx", np.arange(5))),
    "handle_idx_7 of no handle": ("handle_idx_7", _set("handle_idx_7", np.arange(5))),
    "centers huge": ("centers", _set("centers", lambda c: c * 1e10)),
    "norm_center huge": ("norm_center", _set("norm_center", np.full(3, 1e20))),
    "support huge": ("support", _set("support", lambda x: x * 1e20)),
    "matrices huge": ("matrices", _matrix(np.diag([1e20, 1e20, 1e20, 1.0]))),
    "200k centers": ("centers", _set("centers", np.zeros((200_000, 3)))),
    "1000 columns": ("weights", _set("weights", lambda w: np.zeros((w.shape[0], 1000)))),
}


@pytest.mark.parametrize("case", list(ARRAY_CASES))
def test_malformed_arrays_are_refused_naming_the_member(made, tmp_path, capsys, case):
    member, change = ARRAY_CASES[case]
    arrays, meta = members(made / "f.npz")
    if change is None:
        meta = None
    else:
        change(arrays, meta)
    field = write(tmp_path / "bad.npz", arrays, meta)
    refused(capsys, field, made / "in.ply", tmp_path / "o.ply", member)


@pytest.mark.parametrize("scale", [{"delta_c": 1e300}, {"delta_c": 1e300, "weights": 1e300}],
                         ids=["displacements", "weights and displacements"])
def test_finite_but_overflowing_values_are_refused_naming_the_field(made, tmp_path, capsys,
                                                                    scale):
    arrays, meta = members(made / "f.npz")
    for name, factor in scale.items():
        arrays[name] = arrays[name] * factor
    field = write(tmp_path / "bad.npz", arrays, meta)
    refused(capsys, field, made / "in.ply", tmp_path / "o.ply", None)


def test_an_object_array_is_never_unpickled(made, tmp_path, capsys):
    arrays, meta = members(made / "f.npz")
    arrays["centers"] = np.array([object()] * 3, dtype=object)
    out = dict(arrays, meta=np.array(json.dumps(meta)))
    with open(tmp_path / "bad.npz", "wb") as fh:
        np.savez(fh, **out)  # np.savez pickles object arrays
    err = refused(capsys, tmp_path / "bad.npz", made / "in.ply", tmp_path / "o.ply", "centers")
    assert "object" in err


# -------------------------------------------------------------------------------- the meta

def _meta(path, value):
    """Set (value not None) or delete (value None) the key path in the meta."""
    def fn(m):
        node = m
        for k in path[:-1]:
            node = node[k]
        if value is _DELETE:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return fn


_DELETE = object()
BOX = ["handles", 0, "selectors", 0, "all", 0, "box"]
META_CASES = {
    **{f"missing {k}": _meta([k], _DELETE) for k in ("fixed", "handles", "backend", "gaussians",
                                                     "method", "transferable")},
    "fixed a string": _meta(["fixed"], "box"),
    "handles a string": _meta(["handles"], "all of them"),
    "handles a mapping": _meta(["handles"], {"name": "x"}),
    "handle without columns": _meta(["handles", 0, "columns"], _DELETE),
    "columns out of order": _meta(["handles", 0, "columns"], [4, 0]),
    "columns out of range": _meta(["handles", 0, "columns"], [100, 104]),
    "columns floats": _meta(["handles", 0, "columns"], [0.0, 4.0]),
    "columns strings": _meta(["handles", 0, "columns"], ["0", "4"]),
    "handle name a list": _meta(["handles", 0, "name"], ["x"]),
    "box without max": _meta(BOX + ["max"], _DELETE),
    "box min a string": _meta(BOX + ["min"], "0 0 0"),
    "box min exceeds max": _meta(BOX + ["min"], [9.0, 9.0, 9.0]),
    "box min NaN-like": _meta(BOX + ["min"], [1e400, 0, 0]),
    "box origin only": _meta(BOX + ["scale"], None),
    "box scale zero": _meta(BOX + ["scale"], [0.0, 1.0, 1.0]),
    "box unknown key": _meta(BOX + ["code"], "import os"),
    "sphere radius negative": _meta(["handles", 0, "selectors", 0, "all", 1, "not", "sphere",
                                     "radius"], -1.0),
    "sphere without center": _meta(["handles", 0, "selectors", 0, "all", 1, "not", "sphere",
                                    "center"], _DELETE),
    "all empty": _meta(["handles", 0, "selectors", 0, "all"], []),
    "unknown kind": _meta(["fixed"], [{"cube": {"size": 1}}]),
    "two kinds": _meta(["fixed"], [{"box": {}, "sphere": {}}]),
    "importable name": _meta(["fixed"], [{"__selector__": "os:system", "command": "true"}]),
    "property without condition": _meta(["fixed"], [{"property": {"name": "x"}}]),
    "property huge name": _meta(["fixed"], [{"property": {"name": "x" * 5000, "min": 0}}]),
    "indices list": _meta(["fixed"], [{"indices": [0, 1, 2]}]),
    "indices file": _meta(["fixed"], [{"indices": {"file": "/etc/passwd"}}]),
    "nested too deep": _meta(["fixed"], [json.loads('{"not": ' * 40 + '{"sphere": {"center": '
                                                    '[0, 0, 0], "radius": 1}}' + "}" * 40)]),
    "backend unknown": _meta(["backend"], "cuda"),
    "method a number": _meta(["method"], 3),
    "gaussians bogus": _meta(["gaussians", "covariance"], "bogus"),
    "gaussians a list": _meta(["gaussians"], ["jacobian"]),
    "transferable a string": _meta(["transferable"], "yes"),
    "transferable false without indices": _meta(["transferable"], False),
    "unknown key": _meta(["plugin"], "x"),
    "format other": _meta(["format"], "numpy"),
    "version 3": _meta(["version"], 3),
    "version true": _meta(["version"], True),
    "input a mapping": _meta(["input"], {"file": "/etc/passwd"}),
}


@pytest.mark.parametrize("case", list(META_CASES))
def test_malformed_meta_is_refused_naming_the_key(made, tmp_path, capsys, case):
    arrays, meta = members(made / "f.npz")
    META_CASES[case](meta)
    field = write(tmp_path / "bad.npz", arrays, meta)
    err = refused(capsys, field, made / "in.ply", tmp_path / "o.ply", "meta")
    assert "root:" not in err


@pytest.mark.parametrize("text", ["not json", "[1, 2]", "[" * 100_000 + "]" * 100_000, "null"])
def test_meta_that_is_not_a_json_mapping(made, tmp_path, capsys, text):
    arrays, _ = members(made / "f.npz")
    field = write(tmp_path / "bad.npz", arrays, text)
    refused(capsys, field, made / "in.ply", tmp_path / "o.ply", "meta")


def _junk_for(value, rng) -> object:
    """A JSON value of another type than ``value`` (numbers are one type)."""
    def kind(v):
        return "number" if isinstance(v, (int, float)) and not isinstance(v, bool) else \
            type(v).__name__
    pool = [None, True, 2.5, "text", [], [[1]], {"x": 1}]
    options = [j for j in pool if kind(j) != kind(value)]
    return options[int(rng.integers(len(options)))]


def _paths(node, prefix=()):
    """Every key path of the meta below ``format``/``version``/``input``."""
    items = node.items() if isinstance(node, dict) else enumerate(node) \
        if isinstance(node, list) else []
    for k, v in items:
        if prefix == () and k in ("format", "version", "input"):
            continue
        yield (*prefix, k)
        yield from _paths(v, (*prefix, k))


def test_a_seeded_corpus_of_wrong_types(made, tmp_path, capsys):
    """60 cases: one key of the meta replaced by a value of another type; every one refused
    with one line naming the meta."""
    arrays, meta = members(made / "f.npz")
    paths = sorted(_paths(meta), key=str)
    rng = np.random.default_rng(43)
    for i in range(60):
        path = paths[int(rng.integers(len(paths)))]
        m = copy.deepcopy(meta)
        node = m
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = _junk_for(node[path[-1]], rng)
        field = write(tmp_path / f"bad{i}.npz", arrays, m)
        refused(capsys, field, made / "in.ply", tmp_path / "o.ply", "meta")


# ------------------------------------------------------------------------ the zip itself

def test_a_seeded_corpus_of_flipped_bytes(made, tmp_path, capsys):
    """150 copies of a field with 1 to 5 bytes changed: each is applied (exit 0) or refused
    with one line naming the file (exit 2, no output); never an internal error."""
    raw = (made / "f.npz").read_bytes()
    rng = np.random.default_rng(4302)
    for i in range(150):
        b = bytearray(raw)
        for _ in range(int(rng.integers(1, 6))):
            b[int(rng.integers(len(b)))] = int(rng.integers(256))
        field = tmp_path / f"flip{i}.npz"
        field.write_bytes(bytes(b))
        out = tmp_path / f"o{i}.ply"
        code = main(["apply", str(field), str(made / "in.ply"), "-o", str(out)])
        err = capsys.readouterr().err.strip()
        assert code in (0, 2) and "internal error" not in err, err
        if code == 2:
            assert len(err.splitlines()) == 1 and str(field) in err and not out.exists(), err


def _zip(path: Path, entries: list[tuple[str, bytes]], method=zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, "w", compression=method) as zf:
        for name, data in entries:
            zf.writestr(name, data)
    return path


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


@pytest.mark.filterwarnings("ignore:Duplicate name")
def test_files_that_are_no_npz(made, tmp_path, capsys):
    rng = np.random.default_rng(1)
    (tmp_path / "noise.npz").write_bytes(rng.bytes(5000))
    refused(capsys, tmp_path / "noise.npz", made / "in.ply", tmp_path / "o.ply", None)
    raw = (made / "f.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    refused(capsys, tmp_path / "cut.npz", made / "in.ply", tmp_path / "o.ply", None)
    _zip(tmp_path / "path.npz", [("../../etc/passwd.npy", _npy(np.zeros(3)))])
    refused(capsys, tmp_path / "path.npz", made / "in.ply", tmp_path / "o.ply", None)
    _zip(tmp_path / "dup.npz", [("centers.npy", _npy(np.zeros((2, 3))))] * 2)
    refused(capsys, tmp_path / "dup.npz", made / "in.ply", tmp_path / "o.ply", "centers")
    _zip(tmp_path / "z.npz", [("centers.npy", _npy(np.zeros((50, 3))))], zipfile.ZIP_DEFLATED)
    raw = bytearray((tmp_path / "z.npz").read_bytes())
    raw[60:100] = bytes(b ^ 0x55 for b in raw[60:100])  # a corrupt deflate stream
    (tmp_path / "deflate.npz").write_bytes(bytes(raw))
    refused(capsys, tmp_path / "deflate.npz", made / "in.ply", tmp_path / "o.ply", "centers")
    raw = bytearray((tmp_path / "z.npz").read_bytes())
    raw[6] |= 1  # flagged encrypted, local header and directory
    raw[raw.rfind(b"PK\x01\x02") + 8] |= 1
    (tmp_path / "locked.npz").write_bytes(bytes(raw))
    refused(capsys, tmp_path / "locked.npz", made / "in.ply", tmp_path / "o.ply", "centers")
    header = _npy(np.zeros((5, 3)))[:-16]  # the header says 120 bytes of data, 104 follow
    _zip(tmp_path / "short.npz", [("centers.npy", header)])
    refused(capsys, tmp_path / "short.npz", made / "in.ply", tmp_path / "o.ply", "centers")


# VmHWM (kB), not ru_maxrss: Linux carries the forking parent's peak into a child's ru_maxrss
# across exec, so under a grown pytest process every child read ~1.2 GB
PEAK = """
import sys
from splatdeform.cli import main
code = main(["apply", sys.argv[1], sys.argv[2], "-o", sys.argv[3]])
hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")][0].split()[1]
print(code, hwm)
"""


def _peak(field: Path, model: Path, out: Path) -> tuple[int, int, str]:
    run = subprocess.run([sys.executable, "-c", PEAK, str(field), str(model), str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    code, kib = run.stdout.split()
    return int(code), int(kib) * 1024, run.stderr


def test_large_declarations_are_refused_in_bounded_memory(made, tmp_path):
    """A deflated 600 MiB member, 200k centers and 1,000 columns: refused (exit 2, one line)
    under 300 MB of peak memory, before anything large is read or evaluated."""
    arrays, meta = members(made / "f.npz")
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w") as zf:
        for name, a in dict(arrays, meta=np.array(json.dumps(meta))).items():
            zf.writestr(f"{name}.npy", _npy(a))
        info = zipfile.ZipInfo("fixed_idx.npy")  # an allowed name: its size refuses it
        info.compress_type = zipfile.ZIP_DEFLATED
        block = bytes(1 << 20)
        with zf.open(info, "w", force_zip64=True) as f:
            for _ in range(600):
                f.write(block)
    assert bomb.stat().st_size < 5 * 2**20
    many = write(tmp_path / "many.npz", dict(arrays, centers=np.zeros((200_000, 3))), meta)
    wide = write(tmp_path / "wide.npz", dict(arrays, weights=np.zeros(
        (arrays["weights"].shape[0], 1000)), delta_c=np.zeros((1000, 3))), meta)
    for field in (bomb, many, wide):
        code, peak, err = _peak(field, made / "in.ply", tmp_path / "o.ply")
        assert code == 2, err
        assert len(err.strip().splitlines()) == 1 and str(field) in err, err
        assert peak < 300 * 2**20, (field.name, peak)
        assert not (tmp_path / "o.ply").exists()


def test_a_zip_directory_of_many_entries_is_refused_from_its_end_record(made, tmp_path,
                                                                       capsys):
    path = tmp_path / "entries.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for i in range(200):
            zf.writestr(f"m{i}.npy", b"")
    refused(capsys, path, made / "in.ply", tmp_path / "o.ply", None)


# ------------------------------------------------------------------- selectors and paths

def test_selectors_are_stored_by_kind_name(made):
    _, meta = members(made / "f.npz")
    text = json.dumps(meta)
    assert "__selector__" not in text and "splatdeform.edit" not in text
    sel = meta["handles"][0]["selectors"][0]
    assert list(sel) == ["all"] and list(sel["all"][1]) == ["not"]


def test_an_indices_field_stores_the_indices_not_the_file(made, tmp_path, capsys):
    """The indices file named by the edit is stored as indices: apply never opens it (it is
    gone), and the meta names no file."""
    arrays, meta = members(made / "fi.npz")
    assert meta["fixed"] == [{"indices": "stored"}]
    assert "picked" not in json.dumps(meta["fixed"])
    np.testing.assert_array_equal(arrays["fixed_idx"], np.arange(0, 400, 7))
    d = tmp_path / "moved"
    d.mkdir()
    shutil.copy(made / "in.ply", d / "in.ply")
    shutil.copy(made / "fi.npz", d / "fi.npz")
    assert main(["apply", str(d / "fi.npz"), str(d / "in.ply"), "-o", str(d / "o.ply")]) == 0
    a = load(d / "o.ply").positions
    b = load(made / "in.ply").positions
    np.testing.assert_array_equal(a[np.arange(0, 400, 7)], b[np.arange(0, 400, 7)])


def test_an_indices_region_without_its_indices_is_refused(made, tmp_path, capsys):
    arrays, meta = members(made / "fi.npz")
    arrays.pop("fixed_idx")
    field = write(tmp_path / "bad.npz", arrays, meta)
    refused(capsys, field, made / "in.ply", tmp_path / "o.ply", "fixed_idx")
    arrays, meta = members(made / "fi.npz")
    arrays["fixed_idx"] = np.array([0, 10**9])
    field = write(tmp_path / "bad2.npz", arrays, meta)
    refused(capsys, field, made / "in.ply", tmp_path / "o.ply", "fixed_idx")


# ------------------------------------------------------------------------ version 1 fields

_V1_CLASS = {"box": "box:Box", "sphere": "sphere:Sphere", "plane": "plane:Plane",
             "indices": "indices:Indices", "property": "prop:Property", "all": "all_of:All",
             "not": "not_:Not"}


def _as_v1(sel: dict) -> dict:
    """A stored selector as version 1 wrote it (its dataclass, module:class and fields)."""
    (kind, body), = sel.items()
    out = {"__selector__": "splatdeform.edit.selectors." + _V1_CLASS[kind]}
    if kind == "all":
        out["parts"] = [_as_v1(p) for p in body]
    elif kind == "not":
        out["part"] = _as_v1(body)
    elif kind == "indices":
        out.update(indices=[], file="/etc/passwd")
    else:
        out.update(body)
    return out


def _v1_file(src: Path, dst: Path) -> Path:
    arrays, meta = members(src)
    arrays.pop("support")
    meta["version"] = 1
    meta["fixed"] = [_as_v1(s) for s in meta["fixed"]]
    for h in meta["handles"]:
        h["selectors"] = [_as_v1(s) for s in h["selectors"]]
    return write(dst, arrays, meta)


def test_a_version_1_field_still_loads_and_applies_the_same(made, tmp_path, capsys):
    old = _v1_file(made / "f.npz", tmp_path / "v1.npz")
    assert "__selector__" in json.dumps(members(old)[1])
    assert main(["apply", str(old), str(made / "in.ply"), "-o", str(tmp_path / "a.ply")]) == 0
    assert (tmp_path / "a.ply").read_bytes() == (made / "out.ply").read_bytes()
    assert "warning" not in capsys.readouterr().err
    f = Field.load(old)
    lo, hi = load(made / "in.ply").bbox()
    assert np.all(f.support[0] <= lo) and np.all(f.support[1] >= hi)
    assert "version 1" in f.support_note
    f.save(tmp_path / "v2.npz")  # re-saved in this version's form
    assert Field.load(tmp_path / "v2.npz").meta["version"] == 2
    np.testing.assert_array_equal(members(tmp_path / "v2.npz")[0]["support"], f.support)


def test_a_version_1_indices_file_is_never_opened(made, tmp_path, capsys):
    """A version 1 indices selector named a file beside its stored indices: the indices are
    used; without them the field is refused, and no line shows the file's contents."""
    old = _v1_file(made / "fi.npz", tmp_path / "v1.npz")
    assert main(["apply", str(old), str(made / "in.ply"), "-o", str(tmp_path / "a.ply")]) == 0
    arrays, meta = members(old)
    arrays.pop("fixed_idx")
    bad = write(tmp_path / "bad.npz", arrays, meta)
    err = refused(capsys, bad, made / "in.ply", tmp_path / "o.ply", "fixed_idx")
    assert "root:" not in err and "passwd" not in err


def test_a_version_1_name_outside_the_table_is_refused(made, tmp_path, capsys):
    old = _v1_file(made / "f.npz", tmp_path / "v1.npz")
    arrays, meta = members(old)
    meta["fixed"][0]["__selector__"] = "splatdeform.edit.selectors.box:__init__"
    bad = write(tmp_path / "bad.npz", arrays, meta)
    err = refused(capsys, bad, made / "in.ply", tmp_path / "o.ply", "meta")
    assert "re-save" in err


# -------------------------------------------------------------------------- the support

def test_a_model_entirely_outside_the_support_is_refused_unless_extrapolate(made, tmp_path,
                                                                            capsys):
    bunny = load(made / "in.ply")
    save(PointModel(positions=bunny.positions + [100.0, 0, 0]), tmp_path / "far.ply")
    out = tmp_path / "o.ply"
    code = main(["apply", str(made / "f.npz"), str(tmp_path / "far.ply"), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "far.ply" in err and "--extrapolate" in err and "support" in err
    assert not out.exists()
    code = main(["apply", str(made / "f.npz"), str(tmp_path / "far.ply"), "-o", str(out),
                 "--extrapolate"])
    err = capsys.readouterr().err.strip()
    assert code == 0 and out.exists()
    lines = err.splitlines()
    assert len(lines) == 1 and str(out) in lines[0] and "outside its support" in lines[0], err
    assert "up to 100" in lines[0]  # the distance in model units


def test_points_partly_outside_are_counted(made, tmp_path, capsys):
    bunny = load(made / "in.ply")
    save(PointModel(positions=bunny.positions * 1.5), tmp_path / "big.ply")
    out = tmp_path / "o.ply"
    assert main(["apply", str(made / "f.npz"), str(tmp_path / "big.ply"), "-o", str(out)]) == 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(out) in err and "outside its support" in err


def test_the_same_model_gives_no_support_warning(made, tmp_path, capsys):
    f = Field.load(made / "f.npz")
    lo, hi = load(made / "in.ply").bbox()
    assert np.all(f.support[0] <= lo) and np.all(f.support[1] >= hi)
    assert main(["apply", str(made / "f.npz"), str(made / "in.ply"), "-o",
                 str(tmp_path / "o.ply")]) == 0
    assert capsys.readouterr().err == ""
    assert (tmp_path / "o.ply").read_bytes() == (made / "out.ply").read_bytes()


def test_a_streamed_apply_outside_leaves_no_output(made, tmp_path, capsys):
    bunny = load(made / "in.ply")
    save(PointModel(positions=bunny.positions - [0, 50.0, 0]), tmp_path / "far.ply")
    out = tmp_path / "o.ply"
    code = main(["apply", str(made / "f.npz"), str(tmp_path / "far.ply"), "-o", str(out),
                 "--memory-budget", "200MB"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--extrapolate" in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["far.ply"]


# ------------------------------------------------------------ warnings name the output

def test_warnings_while_writing_name_the_output_not_the_temporary_file(tmp_path):
    out = tmp_path / "sub" / "warped.las"
    tmp = out.parent / f".warped.{os.getpid()}-ab_d12x9.tmp.las"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with naming_output(out):
            warnings.warn(f"{tmp}: moved the x offset to 5.0", stacklevel=1)
    assert [str(w.message) for w in caught] == [f"{out}: moved the x offset to 5.0"]


def test_a_streamed_las_apply_names_the_output(tmp_path, capsys):
    shutil.copy(shared_file("lidar/vegetation_1_3.las"), tmp_path / "v.las")
    (tmp_path / "l.yaml").write_text(
        "input: v.las\noutput: vout.las\nbackend: numpy\nregions:\n  units: relative\n"
        "  fixed: [{box: {min: [0,0,0], max: [0.2,1,1]}}]\n"
        "  handle: [{box: {min: [0.8,0,0], max: [1,1,1]}}]\n"
        "handle:\n  transform: {translate: [0, 0, 30000000]}\n")
    assert main(["deform", str(tmp_path / "l.yaml"), "--save-field", str(tmp_path / "f.npz"),
                 "--quiet"]) == 0
    capsys.readouterr()
    out = tmp_path / "o.las"
    assert main(["apply", str(tmp_path / "f.npz"), str(tmp_path / "v.las"), "-o", str(out),
                 "--memory-budget", "200MB"]) == 0
    err = capsys.readouterr().err
    assert err and ".tmp" not in err
    assert all(line.startswith(f"splatdeform: warning: {out}:") for line in err.splitlines())


# ------------------------------------------------------------------ the stored-form table

def test_every_registered_selector_has_a_stored_form():
    """The fixed table holds one builder per registry name, and each selector survives the
    round trip through its stored form (relative-unit frames included)."""
    import splatdeform as sd
    from splatdeform.edit.selectors import REGISTRY, All, Not, stored

    assert set(stored.KINDS) == set(REGISTRY)
    box = sd.Box((0, 0, 0), (1, 1, 0.5), origin=(1.0, 2.0, 3.0), scale=(2.0, 2.0, 2.0))
    sels = [box, sd.Sphere((1, 2, 3), 0.5), sd.Plane((0, 0, 0), (0, 0, 2), (0, 0, 0), (1, 1, 1)),
            sd.Property("classification", values=(2.0, 6.0), max=9.0),
            All((box, Not(sd.Sphere((0, 0, 0), 1.0))))]
    form = json.loads(json.dumps([stored.encode(s) for s in sels]))
    assert stored.decode(form, "fixed") == sels
    assert stored.encode(sd.Indices(file="/etc/passwd")) == {"indices": "stored"}


def test_a_reuse_cache_is_read_by_the_same_bounded_reader(tmp_path):
    """--reuse-file caches go through the one .npz reader: an object member or a member
    declaring far more than the file holds is refused with one line before numpy reads it."""
    from splatdeform.edit.cache import load_deformation
    from splatdeform.errors import InputError

    model = PointModel(positions=np.zeros((4, 3)))
    with open(tmp_path / "obj.npz", "wb") as fh:
        np.savez(fh, key=np.array("k"), n_points=np.array(4),
                 values=np.array([object()], dtype=object))
    with pytest.raises(InputError, match="precomputed deformation.*object"):
        load_deformation(tmp_path / "obj.npz", "k", model)
    with zipfile.ZipFile(tmp_path / "big.npz", "w") as zf:
        zf.writestr("key.npy", _npy(np.array("k")))
        info = zipfile.ZipInfo("values.npy")
        info.compress_type = zipfile.ZIP_DEFLATED
        with zf.open(info, "w", force_zip64=True) as f:
            for _ in range(400):
                f.write(bytes(1 << 20))
    with pytest.raises(InputError, match="precomputed deformation.*declares"):
        load_deformation(tmp_path / "big.npz", "k", model)
