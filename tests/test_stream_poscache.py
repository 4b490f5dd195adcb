"""Passes 1-4 of a streamed LAZ edit decode the file once (issue 45 item 3): the position cache
serves the later passes the very arrays pass 1 decoded, and a streamed LAZ edit still equals the
in-memory one (tests/test_stream.py compares the files)."""

from __future__ import annotations

import os

import numpy as np
from conftest import shared_file

from splatdeform.edit.stream.poscache import PositionCache, cached_positions
from splatdeform.io import open_chunks


def test_the_cache_serves_what_pass_one_decoded(tmp_path):
    src = open_chunks(shared_file("lidar/simple.laz"))
    n = src.n_points
    chunk = 257
    with PositionCache(src, tmp_path) as cache:
        first = [cache.positions(a, min(a + chunk, n)) for a in range(0, n, chunk)]
        assert cache._filled == n
        # later passes, other chunk sizes and out of order: the same float64 bits
        for step in (100, 1000, n):
            again = np.concatenate([cache.positions(a, min(a + step, n))
                                    for a in range(0, n, step)])
            assert np.array_equal(again.view(np.uint64), np.concatenate(first).view(np.uint64))
        assert np.array_equal(cache.positions(500, 700), src.positions(500, 700))
    assert os.listdir(tmp_path) == []      # an unnamed temporary file: nothing left behind


def test_only_compressed_sources_are_cached(tmp_path):
    assert cached_positions(open_chunks(shared_file("lidar/simple.laz")), tmp_path / "o.laz")
    assert cached_positions(open_chunks(shared_file("lidar/extrabytes.las")),
                            tmp_path / "o.las") is None
