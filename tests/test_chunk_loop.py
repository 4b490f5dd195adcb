"""The one chunk loop (io.chunks.map_chunks) with its reader and writer threads (issue 45 item
3): the same bytes with and without the read-ahead, and an error mid-way leaves no output, no
thread and no read-ahead behind."""

from __future__ import annotations

import threading

import pytest

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.io import open_chunks
from splatdeform.io.chunks import map_chunks


@pytest.fixture(scope="module")
def ply(tmp_path_factory):
    path = tmp_path_factory.mktemp("loop") / "bar.ply"
    sd.save(bumpy_bar(30_000, seed=6), path)
    return path


def _copy(src, a, b):
    return src.encode(src.read(a, b))


@pytest.mark.parametrize("chunk", [7_000, 30_000, 100_000])
def test_read_ahead_writes_the_same_bytes(ply, tmp_path, chunk):
    outs = []
    for ahead in (False, True):
        src = open_chunks(ply)
        done = []
        out = map_chunks(src, tmp_path / f"out_{ahead}.ply", lambda a, b, s=src: _copy(s, a, b),
                         chunk, progress=done.append, read_ahead=ahead)
        assert sum(done) == src.n_points
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
    whole = tmp_path / "whole.ply"
    sd.save(sd.load(ply), whole)
    assert outs[1] == whole.read_bytes()


def test_an_error_mid_way_leaves_nothing_behind(ply, tmp_path):
    src = open_chunks(ply)

    def fn(a, b):
        if a >= 14_000:
            raise RuntimeError("chunk failed")
        return _copy(src, a, b)

    with pytest.raises(RuntimeError, match="chunk failed"):
        map_chunks(src, tmp_path / "out.ply", fn, 7_000, read_ahead=True)
    assert not list(tmp_path.iterdir())
    assert src._ahead is None
    names = [t.name for t in threading.enumerate()]
    assert not [n for n in names if n.startswith(("splatdeform-read", "splatdeform-write"))]
