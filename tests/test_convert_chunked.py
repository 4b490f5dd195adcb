"""``convert`` of a binary PLY to PLY with no transform runs chunk by chunk (issue 45 item 4):
the bytes of the whole load + save, and the whole load's errors (a NaN's index counted over the
file, not over its chunk)."""

from __future__ import annotations

import numpy as np
import pytest

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.cli import main
from splatdeform.conversion import convert
from splatdeform.io import open_chunks


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    path = tmp_path_factory.mktemp("chunked") / "bar.ply"
    sd.save(bumpy_bar(200_000, seed=4), path)   # float xyz + normals: 3 chunks
    return path


def test_identity_is_the_load_and_save_bytes(big, tmp_path):
    whole = tmp_path / "whole.ply"
    sd.save(sd.load(big), whole)
    assert convert(big, tmp_path / "copy.ply") == "memory"   # not the budget's streaming
    assert (tmp_path / "copy.ply").read_bytes() == whole.read_bytes()
    assert open_chunks(big).n_points > 2 * 87_381


def test_a_nan_past_the_first_chunk_names_its_file_index(big, tmp_path, capsys):
    bad = tmp_path / "nan.ply"
    raw = big.read_bytes()
    head = raw.index(b"end_header\n") + len(b"end_header\n")
    rows = np.frombuffer(raw, dtype=open_chunks(big).dtype, offset=head).copy()
    at = 150_001
    rows["y"][at] = np.nan
    bad.write_bytes(raw[:head] + rows.tobytes())
    assert main(["convert", str(bad), str(tmp_path / "out.ply")]) == 2
    err = capsys.readouterr().err
    assert f"first at index {at}" in err and "1 vertex(es)" in err, err
    assert not (tmp_path / "out.ply").exists()


def test_ascii_and_mesh_go_through_the_whole_load(tmp_path):
    model = bumpy_bar(2000, seed=5)
    text = tmp_path / "text.ply"
    sd.save(model, text, text=True)
    convert(text, tmp_path / "text_copy.ply")
    whole = tmp_path / "whole.ply"
    sd.save(sd.load(text), whole)
    assert (tmp_path / "text_copy.ply").read_bytes() == whole.read_bytes()


def _ply(path, fields, n=5000, order="<", seed=0):
    """A binary PLY of ``fields`` ((name, numpy code), ...) with seeded values."""
    rng = np.random.default_rng(seed)
    names = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
             "u4": "uint", "f4": "float", "f8": "double"}
    rows = np.empty(n, dtype=[(f, order + c) for f, c in fields])
    for f, c in fields:
        kind = np.dtype(c)
        rows[f] = (rng.normal(size=n) if kind.kind == "f" else
                   rng.integers(np.iinfo(kind).min, np.iinfo(kind).max, n, endpoint=True))
    endian = "little" if order == "<" else "big"
    head = (f"ply\nformat binary_{endian}_endian 1.0\ncomment seeded\nelement vertex {n}\n"
            + "".join(f"property {names[c]} {f}\n" for f, c in fields) + "end_header\n")
    path.write_bytes(head.encode() + rows.tobytes())
    return rows


XYZ = [("x", "f4"), ("y", "f4"), ("z", "f4")]
NORMALS = [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
GAUSS = [(f"f_dc_{i}", "f4") for i in range(3)] + [("opacity", "f4")] + \
    [(f"scale_{i}", "f4") for i in range(3)] + [(f"rot_{i}", "f4") for i in range(4)]


@pytest.mark.parametrize("fields, order", [
    (XYZ + NORMALS + [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")], "<"),
    ([("x", "f8"), ("y", "f8"), ("z", "f8"), ("nx", "i2"), ("ny", "i2"), ("nz", "i2"),
      ("radius", "f4"), ("intensity", "u4"), ("label", "i4")], ">"),
    (XYZ + [("ux", "f4"), ("uy", "f4"), ("uz", "f8"), ("vx", "f4"), ("vy", "f4"),
            ("vz", "f4"), ("surfel_radius", "f8")], "<"),
    (XYZ + [("red", "f4"), ("green", "f4"), ("blue", "f4")], "<"),       # colours not uchar
    (XYZ + [("red", "u2"), ("green", "u2"), ("blue", "u2")], "<"),       # clipped to 255
    (XYZ + NORMALS + GAUSS, "<"),                                        # a 3DGS PLY
    (XYZ + [(n, "f8" if n.startswith(("scale", "rot")) else c) for n, c in GAUSS], "<"),
])
def test_identity_is_the_load_and_save_bytes_for_every_property_type(tmp_path, fields, order):
    """The records written as read where the types make the load + save give them back, the
    chunk model's way where they do not: the load + save's bytes either way."""
    src = tmp_path / "in.ply"
    _ply(src, fields, order=order)
    whole = tmp_path / "whole.ply"
    sd.save(sd.load(src), whole)
    assert convert(src, tmp_path / "copy.ply") == "memory"
    assert (tmp_path / "copy.ply").read_bytes() == whole.read_bytes()


def test_a_signalling_nan_normal_comes_back_as_the_load_and_save_writes_it(tmp_path):
    """A NaN normal goes the chunk model's way (through float64 a signalling NaN comes back
    quiet): the load + save's bytes, the other chunks as read."""
    src = tmp_path / "nan.ply"
    rows = _ply(src, XYZ + NORMALS, n=200_000, seed=3)   # 3 chunks
    rows["ny"][150_001] = np.uint32(0x7F800001).view(np.float32)   # a signalling NaN
    rows["nz"][7] = np.nan
    raw = src.read_bytes()
    src.write_bytes(raw[:raw.index(b"end_header\n") + 11] + rows.tobytes())
    whole = tmp_path / "whole.ply"
    sd.save(sd.load(src), whole)
    convert(src, tmp_path / "copy.ply")
    assert (tmp_path / "copy.ply").read_bytes() == whole.read_bytes()
