"""Splat formats in and out (.compressed.ply, .splat, .spz, .sog), cross-checked against PlayCanvas
splat-transform (pinned, installed by ``make test`` into .cache/; a missing oracle fails).

Directions per format (splat-transform 3.7.0 reads .ply .compressed.ply .splat .ksplat .spz .sog
and writes .ply .compressed.ply .spz .sog .glb): where it reads, its decode of our file equals our
decode of the same file; where it writes, our decode of its file equals its own decode, to the
format's quantisation step, in PLY space. Its decodes are taken by converting to a plain .ply.
"""

from __future__ import annotations

import gzip
import warnings
from pathlib import Path

import numpy as np
import pytest
from splat_oracle import compare, fields, write_scene

from data_tools import gltf_spz, splat_transform
from splatdeform.errors import FormatError
from splatdeform.io import gltf, load, save, spz
from splatdeform.io.sog_order import morton_order, order, take
from splatdeform.io.splats import LossyWriteWarning

# which directions the oracle checks: (it reads our output, we read its output, extra args)
ORACLE = {
    ".compressed.ply": (True, True, ()),
    ".splat": (True, False, ()),
    ".spz": (True, True, ("--spz-version", "3")),
    ".sog": (True, True, ("-g", "cpu")),
}
# our decode vs the original scene: the format's quantisation step (see each module)
ROUND_TRIP = {
    ".compressed.ply": dict(pos=0.006, scale=0.004, rot=2e-5, alpha=2.5e-3, dc=0.02, rest=0.016),
    ".splat": dict(pos=1e-6, scale=1e-6, rot=1e-4, alpha=2.5e-3, dc=0.008, rest=0.0),
    ".spz": dict(pos=1.3e-4, scale=0.032, rot=5e-6, alpha=2.5e-3, dc=0.0131, rest=0.067),
    # SOG: 16-bit log-spaced positions (5 m from the origin: 2^-16 of the log range, times
    # e^|n|), 8-bit rotation, codebooks of 256 entries for the 2100 scale and dc values; random
    # SH rows (incompressible) through a 64-entry palette: only bounded here, the palette and
    # its codebook are checked in test_sog_sh_palette_is_exact_for_few_distinct_rows
    ".sog": dict(pos=4e-4, scale=0.03, rot=2e-4, alpha=2.5e-3, dc=0.02, rest=1.0),
}
SAME = dict(pos=1e-5, scale=1e-5, rot=1e-6, alpha=1e-5, dc=1e-5, rest=1e-5)
# where the two decoders differ within one quantisation step: .splat rotation bytes are centred
# at 128 by the format's original writer (q * 128 + 128), at 127.5 by splat-transform's reader
ORACLE_TOL = {".splat": {**SAME, "rot": 1.2e-4}}


def _their_decode(src: Path, out: Path):
    splat_transform.run("-w", "-q", "-g", "cpu", str(src), str(out))
    return fields(load(out))


def _spz_frame(f):
    """splat-transform 3.7.0 stores SPZ in PLY axes (no RDF -> RUB flip, unlike the SPZ
    specification this reader follows): turn its decode by 180 degrees about x to compare."""
    f.positions = f.positions * np.array([1, -1, -1])
    f.rotation = f.rotation * np.array([1, 1, -1, -1], dtype=np.float32)
    f.sh_rest = f.sh_rest * spz.SH_FLIP[:f.sh_rest.shape[2]]
    return f


def _save_quiet(model, path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        return save(model, path)


@pytest.mark.parametrize("ext", list(ORACLE))
@pytest.mark.parametrize("degree", [0, 3])
def test_round_trip_and_oracle_reads_ours(tmp_path, oracle, ext, degree):
    src = write_scene(tmp_path / "scene.ply", 700, degree, seed=degree)
    original = fields(load(src))
    out = tmp_path / f"ours{ext}"
    with pytest.warns(LossyWriteWarning, match="lossy") as record:
        save(load(src), out)
    assert len([w for w in record if issubclass(w.category, LossyWriteWarning)]) == 1
    ours = fields(load(out))
    assert ours.count == original.count
    tol = dict(ROUND_TRIP[ext])
    if ext == ".splat" and degree:
        original.sh_rest = original.sh_rest[:, :, :0]  # .splat holds no SH rest (said)
    if ext == ".sog":   # stored in Morton order, as splat-transform stores it
        original = take(original, morton_order(original.positions))
    compare(ours, original, **tol)
    theirs = _their_decode(out, tmp_path / "theirs.ply")
    if ext == ".spz":
        theirs = _spz_frame(theirs)
    compare(ours, theirs, **ORACLE_TOL.get(ext, SAME))


@pytest.mark.parametrize("ext", [e for e, (_, reads, _) in ORACLE.items() if reads])
def test_we_read_the_oracles_output(tmp_path, oracle, ext):
    src = write_scene(tmp_path / "scene.ply", 900, 3, seed=5)
    theirs_file = tmp_path / f"theirs{ext}"
    splat_transform.run("-w", "-q", *ORACLE[ext][2], str(src), str(theirs_file))
    ours = fields(load(theirs_file))
    theirs = _their_decode(theirs_file, tmp_path / "theirs.ply")
    if ext == ".spz":
        theirs = _spz_frame(theirs)
    compare(ours, theirs, **SAME)


def test_compressed_sh_decode_is_unbiased(tmp_path, oracle):
    """Bin-centre decode: the mean SH error of a compressed file against its source < 1e-3."""
    src = write_scene(tmp_path / "scene.ply", 4000, 3, seed=9)
    original = fields(load(src))
    out = tmp_path / "ours.compressed.ply"
    _save_quiet(load(src), out)
    ours = fields(load(out))
    assert abs(float((ours.sh_rest - original.sh_rest).mean())) < 1e-3
    theirs_file = tmp_path / "theirs.compressed.ply"
    splat_transform.run("-w", "-q", str(src), str(theirs_file))
    # splat-transform reorders splats (Morton order) when compressing: compare distributions
    theirs = fields(load(theirs_file))
    assert abs(float(theirs.sh_rest.mean() - original.sh_rest.mean())) < 1e-3


def test_compressed_output_is_small(tmp_path):
    src = write_scene(tmp_path / "scene.ply", 3000, 3)
    out = tmp_path / "x.compressed.ply"
    _save_quiet(load(src), out)
    assert out.stat().st_size <= 0.35 * src.stat().st_size
    assert out.read_bytes().startswith(b"ply\n")
    assert b"element chunk 12" in out.read_bytes()[:2000]


@pytest.mark.parametrize("version", [2, 3])
def test_spz_versions_round_trip(tmp_path, version):
    model = load(write_scene(tmp_path / "scene.ply", 500, 2, seed=3))
    f = fields(model)
    path = tmp_path / f"v{version}.spz"
    path.write_bytes(gzip.compress(spz.encode(f, version=version)))
    back = fields(load(path))
    assert spz.read_info(path)["version"] == version
    compare(back, f, **{**ROUND_TRIP[".spz"], "rot": 5e-3 if version == 2 else 5e-6})


def test_spz_unknown_version_and_truncation_are_one_line(tmp_path):
    model = load(write_scene(tmp_path / "scene.ply", 50, 1))
    raw = bytearray(spz.encode(fields(model)))
    raw[4] = 9
    bad = tmp_path / "v9.spz"
    bad.write_bytes(gzip.compress(bytes(raw)))
    with pytest.raises(FormatError, match=r"v9.spz: SPZ version 9 is not supported"):
        load(bad)
    short = tmp_path / "short.spz"
    short.write_bytes(gzip.compress(bytes(spz.encode(fields(model)))[:-10]))
    with pytest.raises(FormatError, match="shorter than the 50 splats"):
        load(short)
    huge = bytearray(spz.encode(fields(model)))
    huge[8:12] = (2**32 - 1).to_bytes(4, "little")
    big = tmp_path / "big.spz"
    big.write_bytes(gzip.compress(bytes(huge)))
    with pytest.raises(FormatError, match="big.spz"):
        load(big)


def test_splat_size_must_be_whole_records(tmp_path):
    bad = tmp_path / "x.splat"
    bad.write_bytes(b"\0" * 33)
    with pytest.raises(FormatError, match="not a multiple of the 32-byte"):
        load(bad)


def test_non_splat_model_is_refused_with_one_line(tmp_path):
    from splatdeform.model import PointModel

    model = PointModel(positions=np.zeros((3, 3)), kind="cloud")
    for ext in ORACLE:
        with pytest.raises(FormatError, match="holds 3D Gaussian splats"):
            save(model, tmp_path / f"x{ext}")
        assert not (tmp_path / f"x{ext}").exists()


def _glb_json(path: Path) -> dict:
    import json
    import struct

    raw = path.read_bytes()
    assert struct.unpack_from("<III", raw)[:2] == (0x46546C67, 2)
    size, kind = struct.unpack_from("<II", raw, 12)
    assert kind == 0x4E4F534A and struct.unpack_from("<I", raw, 8)[0] == len(raw)
    return json.loads(raw[20:20 + size])


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_glb_follows_the_specification_and_matches_the_oracle(tmp_path, oracle, degree):
    """Our .glb has the KHR_gaussian_splatting required fields; our decode of splat-transform's
    .glb equals its source (it writes, it does not read glTF); float conversions within 1 ulp."""
    src = write_scene(tmp_path / "scene.ply", 600, degree, seed=degree + 20)
    original = fields(load(src))
    ours_file = tmp_path / "ours.glb"
    save(load(src), ours_file)
    doc = _glb_json(ours_file)
    assert "KHR_gaussian_splatting" in doc["extensionsUsed"]
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0
    ext = prim["extensions"]["KHR_gaussian_splatting"]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] in (
        "srgb_rec709_display", "lin_rec709_display")
    attrs = prim["attributes"]
    for name in ("POSITION", "KHR_gaussian_splatting:ROTATION", "KHR_gaussian_splatting:SCALE",
                 "KHR_gaussian_splatting:OPACITY", "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"):
        assert name in attrs
    sh = [a for a in attrs if "SH_DEGREE_" in a and not a.endswith("DEGREE_0_COEF_0")]
    assert len(sh) == {0: 0, 1: 3, 3: 15}[degree]
    accessors = doc["accessors"]
    assert {"min", "max"} <= set(accessors[attrs["POSITION"]])
    types = {"KHR_gaussian_splatting:ROTATION": "VEC4", "KHR_gaussian_splatting:SCALE": "VEC3",
             "KHR_gaussian_splatting:OPACITY": "SCALAR", **{a: "VEC3" for a in sh}}
    for name, kind in types.items():
        assert accessors[attrs[name]]["type"] == kind
    ours = fields(load(ours_file))
    exact = dict(pos=0.0, scale=0.0, rot=1e-7, alpha=1e-7, dc=0.0, rest=0.0)
    compare(ours, original, **exact)
    ulp = np.abs(ours.scale_log - original.scale_log) / np.spacing(np.abs(original.scale_log))
    assert ulp.max() <= 1
    logit_ulp = np.abs(ours.opacity - original.opacity) / np.spacing(np.abs(original.opacity))
    assert np.median(logit_ulp) <= 1
    theirs_file = tmp_path / "theirs.glb"
    splat_transform.run("-w", "-q", str(src), str(theirs_file))
    compare(fields(load(theirs_file)), original, **exact)


def test_gltf_with_an_external_buffer_and_bad_glb(tmp_path):
    import json

    src = write_scene(tmp_path / "scene.ply", 40, 1)
    save(load(src), tmp_path / "embedded.gltf")
    doc = json.loads((tmp_path / "embedded.gltf").read_text())
    import base64
    blob = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    (tmp_path / "data.bin").write_bytes(blob)
    doc["buffers"][0]["uri"] = "data.bin"
    (tmp_path / "external.gltf").write_text(json.dumps(doc))
    compare(fields(load(tmp_path / "external.gltf")), fields(load(src)),
            pos=0, scale=0, rot=1e-7, alpha=1e-7, dc=0, rest=0)
    doc["buffers"][0]["uri"] = "../elsewhere.bin"
    (tmp_path / "escape.gltf").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="escape.gltf: glTF buffer 0"):
        load(tmp_path / "escape.gltf")
    glb = tmp_path / "x.glb"
    save(load(src), glb)
    glb.write_bytes(glb.read_bytes()[:-8])
    with pytest.raises(FormatError, match="x.glb: GLB header declares"):
        load(glb)
    doc["buffers"][0]["uri"] = "data.bin"
    del doc["meshes"][0]["primitives"][0]["extensions"]
    (tmp_path / "plain.gltf").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="no glTF primitive with the KHR_gaussian_splatting"):
        load(tmp_path / "plain.gltf")


def _covariances(rot_wxyz: np.ndarray, scale_log: np.ndarray) -> np.ndarray:
    q = rot_wxyz / np.linalg.norm(rot_wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                 axis=1).reshape(-1, 3, 3)
    return np.einsum("nij,nj,nkj->nik", r, np.exp(2.0 * scale_log), r)


@pytest.mark.parametrize("degree", [0, 1, 3])
@pytest.mark.parametrize("name", gltf.SPZ_EXTS)
def test_gltf_spz_extension_is_read_in_the_gltf_frame(tmp_path, degree, name):
    """An SPZ-compressed glb (written from the extension's specification by data_tools) decodes
    like the plain glb to SPZ's quantisation step; its stored SPZ values are in glTF's frame:
    they equal the plain glb's POSITION, SH and covariances (that glb's frame is checked against
    splat-transform in test_glb_follows_the_specification_and_matches_the_oracle)."""
    src = write_scene(tmp_path / "scene.ply", 500, degree, seed=degree + 40)
    model = load(src)
    packed = gltf_spz.write(model, tmp_path / "spz.glb", name)
    plain = save(model, tmp_path / "plain.glb")
    doc = _glb_json(packed)
    assert name in doc["extensionsRequired"] and "bufferView" not in doc["accessors"][0]
    compare(fields(load(packed)), fields(load(plain)), **ROUND_TRIP[".spz"])
    # the stored values, no frame change, against the plain glb's attributes
    doc, buffers = gltf.read_document(packed)
    view = doc["bufferViews"][0]
    raw = spz.gunzip_blob(packed, buffers[0][:view["byteLength"]])
    stored, _ = spz.decode(raw, packed, (np.ones(3), np.ones(15, np.float32)))
    pdoc, pbuf = gltf.read_document(plain)
    attrs = pdoc["meshes"][0]["primitives"][0]["attributes"]

    def get(a):
        return gltf._accessor(plain, pdoc, pbuf, attrs[a], a).astype(np.float64)

    assert np.abs(stored.positions - get("POSITION")).max() <= ROUND_TRIP[".spz"]["pos"]
    ext = "KHR_gaussian_splatting"
    if degree:
        sh = np.stack([get(a) for a in gltf._sh_names(degree)], axis=2)  # (N, 3, K)
        assert np.abs(stored.sh_rest - sh).max() <= ROUND_TRIP[".spz"]["rest"]
    xyzw = get(f"{ext}:ROTATION")
    theirs = _covariances(xyzw[:, [3, 0, 1, 2]], np.log(get(f"{ext}:SCALE")))
    ours = _covariances(stored.rotation.astype(np.float64), stored.scale_log)
    assert (np.abs(ours - theirs).max(axis=(1, 2)) / np.abs(theirs).max(axis=(1, 2))).max() < 0.1


def test_gltf_spz_extension_bad_input_is_one_line(tmp_path):
    import json

    model = load(write_scene(tmp_path / "scene.ply", 30, 1))
    good = gltf_spz.write(model, tmp_path / "good.glb")
    raw = good.read_bytes()
    size = int.from_bytes(raw[12:16], "little")
    doc = json.loads(raw[20:20 + size])

    def variant(name: str, change) -> Path:
        d = json.loads(json.dumps(doc))
        change(d)
        text = json.dumps(d).encode()
        text += b" " * ((-len(text)) % 4)
        rest = raw[20 + size:]
        out = tmp_path / name
        out.write_bytes(raw[:8] + (20 + len(text) + len(rest)).to_bytes(4, "little")
                        + len(text).to_bytes(4, "little") + raw[16:20] + text + rest)
        return out

    def count(d):
        d["accessors"][0]["count"] = 31

    def past(d):
        d["bufferViews"][0]["byteLength"] = 10**6

    def view(d):
        ext = d["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]
        ext["extensions"][gltf.SPZ_EXTS[0]]["bufferView"] = "0"

    for name, change, message in (
            ("count.glb", count, "POSITION accessor count 31 differs from the 30 splats"),
            ("past.glb", past, "SPZ bufferView 0 runs past its buffer"),
            ("view.glb", view, "needs an integer bufferView")):
        with pytest.raises(FormatError, match=f"{name}: .*{message}"):
            load(variant(name, change))
    short = tmp_path / "short.glb"
    blob = bytearray(raw)
    blob[-40:] = b"\0" * 40  # the gzip stream's end
    short.write_bytes(bytes(blob))
    with pytest.raises(FormatError, match="short.glb: "):
        load(short)


def test_info_reports_sh_degree_and_format_fields(tmp_path):
    import json
    import subprocess
    import sys

    src = write_scene(tmp_path / "scene.ply", 300, 2)
    _save_quiet(load(src), tmp_path / "x.spz")
    save(load(src), tmp_path / "x.glb")
    _save_quiet(load(src), tmp_path / "x.compressed.ply")
    _save_quiet(load(src), tmp_path / "x.sog")
    expect = {"x.sog": ("PlayCanvas SOG v2 bundle", "sh_bands"),
              "x.spz": ("SPZ v4", "version"), "x.glb": ("glTF 2.0", "extensions"),
              "x.compressed.ply": ("PlayCanvas compressed", "sh_bands"),
              "scene.ply": ("binary_little_endian", None)}
    for name, (fmt, key) in expect.items():
        proc = subprocess.run([sys.executable, "-m", "splatdeform.cli", "info", "--json",
                               str(tmp_path / name)], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        info = json.loads(proc.stdout)
        assert info["sh_degree"] == 2 and info["format"].startswith(fmt)
        if key:
            assert key in info["format_fields"]
    assert info.get("format_fields") is None


def test_compressed_untouched_chunks_keep_their_codes(tmp_path):
    """Re-saving an edited .compressed.ply: chunks whose splats all kept their decoded values
    keep the input's chunk bounds and codes (byte-identical rows); edited chunks re-quantise."""
    from splatdeform.io.ply_format import read_ply

    src = write_scene(tmp_path / "scene.ply", 1000, 3, seed=2)
    first = tmp_path / "first.compressed.ply"
    _save_quiet(load(src), first)
    model = load(first)
    model.positions[300:310] += 0.5  # inside chunk 1 only
    second = tmp_path / "second.compressed.ply"
    _save_quiet(model, second)
    a, b = read_ply(first), read_ply(second)
    for name in ("chunk", "vertex", "sh"):
        assert a.element(name).count == b.element(name).count
    ca, cb = a.element("chunk").data, b.element("chunk").data
    va, vb = a.element("vertex").data, b.element("vertex").data
    for chunk in (0, 2, 3):
        assert ca[chunk].tobytes() == cb[chunk].tobytes()
        rows = slice(chunk * 256, min(chunk * 256 + 256, 1000))
        assert va[rows].tobytes() == vb[rows].tobytes()
    assert ca[1].tobytes() != cb[1].tobytes()
    back = fields(load(second))
    np.testing.assert_allclose(back.positions[300:310], model.positions[300:310], atol=0.01)


@pytest.mark.parametrize("ext", [".spz", ".splat", ".glb", ".gltf", ".compressed.ply", ".pcd",
                                 ".sog"])
def test_mutated_files_give_one_line_errors(tmp_path, ext):
    """Truncations and byte flips of each format: a clean FormatError/InputError naming the
    file, or a successful load; never another exception (seeded, bounded)."""
    from splatdeform.errors import InputError

    src = write_scene(tmp_path / "scene.ply", 300, 1, seed=7)
    good = tmp_path / f"good{ext}"
    _save_quiet(load(src), good)
    raw = good.read_bytes()
    rng = np.random.default_rng(11)
    cases = [raw[:k] for k in (0, 5, 15, 40, len(raw) // 2, len(raw) - 1)]
    for _ in range(30):
        b = bytearray(raw)
        for at in rng.integers(0, len(b), 3):
            b[at] = int(rng.integers(0, 256))
        cases.append(bytes(b))
    bad = tmp_path / f"bad{ext}"
    for case in cases:
        bad.write_bytes(case)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                load(bad)
        except (FormatError, InputError) as exc:
            assert str(bad) in str(exc) and "\n" not in str(exc)


def _sog_scene(tmp_path: Path, n: int, prototypes: int, seed: int = 4) -> Path:
    """A SH3 scene whose SH rest rows are ``prototypes`` distinct rows (a palette can hold them)."""
    from splat_oracle import scene_source

    from splatdeform.io.ply_format import write_ply

    source = scene_source(n, 3, seed)
    data = source.element("vertex").data
    rng = np.random.default_rng(seed)
    table = rng.uniform(-0.5, 0.5, (prototypes, 45)).astype(np.float32)
    pick = rng.integers(0, prototypes, n)
    for i in range(45):
        data[f"f_rest_{i}"] = table[pick, i]
    path = tmp_path / "protos.ply"
    with open(path, "wb") as f:
        write_ply(source, f)
    return path


def _sog_members(path: Path) -> dict:
    import io
    import json
    import zipfile

    from PIL import Image

    with zipfile.ZipFile(path) as z:
        out = {name: z.read(name) for name in z.namelist()}
    meta = json.loads(out.pop("meta.json"))
    return {"meta": meta, **{name: np.asarray(Image.open(io.BytesIO(raw)).convert("RGBA"))
                             for name, raw in out.items()}}


def test_sog_sh_palette_is_exact_for_few_distinct_rows(tmp_path):
    """Fewer distinct SH rows than palette entries: every splat gets its own row back, to half
    the largest gap of the 256-entry SH codebook; the lossless WebP keeps every code."""
    src = _sog_scene(tmp_path, 2000, 40)
    original = fields(load(src))
    original = take(original, morton_order(original.positions))   # the order SOG stores
    out = tmp_path / "x.sog"
    _save_quiet(load(src), out)
    members = _sog_members(out)
    book = np.asarray(members["meta"]["shN"]["codebook"])
    assert members["meta"]["shN"]["count"] == 40 and members["meta"]["shN"]["bands"] == 3
    back = fields(load(out))
    err = np.abs(back.sh_rest - original.sh_rest).max()
    assert err <= np.diff(book).max() / 2 + 1e-6
    assert len(np.unique(back.sh_rest.reshape(2000, -1), axis=0)) == 40


def test_sog_is_lossless_webp_in_a_zip_and_deterministic(tmp_path):
    src = write_scene(tmp_path / "scene.ply", 500, 1, seed=8)
    a, b = tmp_path / "a.sog", tmp_path / "b.sog"
    _save_quiet(load(src), a)
    _save_quiet(load(src), b)
    assert a.read_bytes() == b.read_bytes()  # seeded k-means, fixed ZIP dates
    import zipfile
    with zipfile.ZipFile(a) as z:
        names = z.namelist()
        assert names[0] == "meta.json"
        for name in names[1:]:
            assert z.read(name)[8:16] == b"WEBPVP8L"  # the lossless WebP bitstream


def test_sog_folder_reads_and_writes_like_the_bundle(tmp_path, oracle):
    src = write_scene(tmp_path / "scene.ply", 400, 2, seed=6)
    folder = tmp_path / "scene_sog"
    folder.mkdir()
    _save_quiet(load(src), folder / "meta.json")
    _save_quiet(load(src), tmp_path / "x.sog")
    for name in ("means_l.webp", "quats.webp", "shN_labels.webp"):
        assert (folder / name).is_file()
    by_dir, by_meta = fields(load(folder)), fields(load(folder / "meta.json"))
    bundle = fields(load(tmp_path / "x.sog"))
    compare(by_dir, bundle, **{k: 0.0 for k in SAME})
    compare(by_meta, bundle, **{k: 0.0 for k in SAME})
    theirs = _their_decode(folder / "meta.json", tmp_path / "theirs.ply")
    compare(by_meta, theirs, **SAME)


@pytest.mark.parametrize("ext", [".ply", ".spz", ".compressed.ply"])
def test_loaded_gaussians_share_the_table_read_only(tmp_path, ext):
    """A load shares the decoded table (no second copy of the Gaussian columns): the fields are
    read-only views of the model's source rows, an in-place write is refused, and a copy is
    writable and leaves the source as read."""
    src = write_scene(tmp_path / "scene.ply", 600, 3, seed=4)
    path = src if ext == ".ply" else tmp_path / f"x{ext}"
    if path != src:
        _save_quiet(load(src), path)
    model = load(path)
    g, rows = model.gaussians, model.source.element("vertex").data
    before = rows.copy()
    for name in ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
        column = getattr(g, name)
        assert np.shares_memory(column, rows) and not column.flags.writeable, name
    with pytest.raises(ValueError, match="read-only"):
        g.scale_log[0] += 1
    edited = model.copy()
    edited.gaussians.scale_log[:10] += 1.0
    edited.gaussians.sh_rest[:10] *= 0.5
    assert rows.tobytes() == before.tobytes()
    assert (edited.gaussians.scale_log[:10] > g.scale_log[:10]).all()


def test_sog_untouched_splats_keep_their_codes(tmp_path):
    """Re-saving an edited SOG: splats that kept their decoded values keep every code (pixel),
    and the codebook and palette entries they use keep their index and value; the edited
    splats are re-quantised."""
    src = _sog_scene(tmp_path, 1500, 30, seed=3)
    first = tmp_path / "first.sog"
    _save_quiet(load(src), first)
    model = load(first).copy()  # a loaded model's Gaussian fields are read-only views
    moved = np.zeros(1500, dtype=bool)
    moved[100:160] = True
    model.positions[moved] *= 0.8  # inside the input's range: its mins/maxs are kept
    model.gaussians.scale_log[moved] += 0.5
    model.gaussians.sh_rest[moved] *= 0.5
    second = tmp_path / "second.sog"
    with order("keep"):   # row for row (by default the edited scene is stored in Morton order:
        _save_quiet(model, second)   # tests/test_sog_order.py)
    a, b = _sog_members(first), _sog_members(second)
    assert a["meta"]["means"] == b["meta"]["means"]  # the moved splats stay inside its range
    for image in ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                  "shN_labels.webp"):  # every per-splat code of the untouched splats
        np.testing.assert_array_equal(a[image].reshape(-1, 4)[:1500][~moved],
                                      b[image].reshape(-1, 4)[:1500][~moved])
    for key, image in (("scales", "scales.webp"), ("sh0", "sh0.webp")):
        used = np.unique(a[image].reshape(-1, 4)[:1500][~moved, :3])
        np.testing.assert_array_equal(np.asarray(b["meta"][key]["codebook"])[used],
                                      np.asarray(a["meta"][key]["codebook"])[used])
    labels = a["shN_labels.webp"].reshape(-1, 4)[:1500][~moved]
    used = np.unique(labels[:, 0].astype(int) | labels[:, 1].astype(int) << 8)
    k = 15
    pa = a["shN_centroids.webp"].reshape(-1, 64 * k, 4)[:, :, :3].reshape(-1, k, 3)
    pb = b["shN_centroids.webp"].reshape(-1, 64 * k, 4)[:, :, :3].reshape(-1, k, 3)
    np.testing.assert_array_equal(pb[used], pa[used])  # the palette entries they use
    sh_used = np.unique(pa[used])
    np.testing.assert_array_equal(np.asarray(b["meta"]["shN"]["codebook"])[sh_used],
                                  np.asarray(a["meta"]["shN"]["codebook"])[sh_used])
    before, after = fields(load(first)), fields(load(second))
    for name in ("positions", "scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(after, name)[~moved],
                                      getattr(before, name)[~moved])
    np.testing.assert_allclose(after.positions[moved], model.positions[moved], atol=1e-3)


def test_sog_bad_meta_is_one_line(tmp_path):
    import json
    import zipfile

    src = write_scene(tmp_path / "scene.ply", 60, 1)
    good = tmp_path / "good.sog"
    _save_quiet(load(src), good)
    with zipfile.ZipFile(good) as z:
        members = {name: z.read(name) for name in z.namelist()}
    meta = json.loads(members["meta.json"])
    cases = {"version": (dict(meta, version=3), "SOG version 3 is not supported"),
             "count": (dict(meta, count=500_000), "pixels for 500,000 splats"),
             "implausible": (dict(meta, count=10**6),   # 20 MB of pixels from 18 KB
                             "1,000,000 splats .* compresses at most 64x"),
             "codebook": (dict(meta, scales={**meta["scales"], "codebook": [0.0] * 5}),
                          "'scales.codebook' must be 256"),
             "missing": (dict(meta, quats={"files": ["nope.webp"]}), "has no nope.webp"),
             "escape": (dict(meta, quats={"files": ["../x.webp"]}), "not a plain file name")}
    for name, (bad_meta, message) in cases.items():
        path = tmp_path / f"{name}.sog"
        with zipfile.ZipFile(path, "w") as z:
            for member, raw in members.items():
                z.writestr(member, json.dumps(bad_meta) if member == "meta.json" else raw)
        with pytest.raises(FormatError, match=message) as info:
            load(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
