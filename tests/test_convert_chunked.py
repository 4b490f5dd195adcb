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
