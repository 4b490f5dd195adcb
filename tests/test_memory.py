"""memory.py's file cost against measurement: generated binary, list-heavy and ASCII PLY and a
LAS file are loaded in a fresh subprocess, whose peak RSS above its post-import baseline must
not exceed the estimate, and the estimate must stay within a sane factor of it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import bar_edit

# VmHWM, not ru_maxrss: the latter keeps the forking parent's peak across exec
MEASURE = """
import sys
from splatdeform.io import load
from splatdeform.memory import file_cost
import splatdeform.io.ply_format, splatdeform.io.las, laspy, numpy
def status(key):
    return int(open('/proc/self/status').read().split(key + ':')[1].split()[0]) * 1024
base = status('VmRSS')
est = file_cost(sys.argv[1]).load_bytes
load(sys.argv[1])
print(status('VmHWM') - base, est)
"""
XYZ = b"property float x\nproperty float y\nproperty float z\n"


def _binary(path: Path, n: int) -> None:
    xyz = np.random.default_rng(0).random((n, 3)).astype("<f4")
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n + XYZ +
                     b"end_header\n" + xyz.tobytes())


def _lists(path: Path, rows: int) -> None:
    body = np.tile(np.frombuffer(b"\x01\x00\x02\x00\x00", np.uint8), rows // 2).tobytes()
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n" + XYZ +
                     b"element face %d\nproperty list uchar uchar vertex_indices\n" % rows +
                     b"end_header\n" + bytes(36) + body)


def _ascii(path: Path, n: int) -> None:
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex %d\n" % n + XYZ + b"end_header\n"
                     + b"0 0 0\n" * n)


def _las(path: Path, n: int) -> None:
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0, 0, 0]
    las = laspy.LasData(header)
    xyz = np.random.default_rng(0).random((n, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(path)


@pytest.mark.parametrize("kind, make, n", [("binary.ply", _binary, 2_000_000),
                                           ("lists.ply", _lists, 1_000_000),
                                           ("ascii.ply", _ascii, 1_000_000),
                                           ("points.las", _las, 1_000_000)])
def test_file_cost_bounds_the_measured_load_peak(tmp_path: Path, kind, make, n) -> None:
    path = tmp_path / kind
    make(path, n)
    r = subprocess.run([sys.executable, "-c", MEASURE, str(path)], capture_output=True,
                       text=True, timeout=300, check=True)
    measured, estimate = map(int, r.stdout.split())
    assert measured > 0
    assert estimate >= measured, (kind, measured / 2**20, estimate / 2**20)
    assert estimate <= 4 * measured + 64 * 2**20, (kind, measured / 2**20, estimate / 2**20)


DEFORM = """
import sys
from splatdeform.cli import main
import splatdeform.edit.run, splatdeform.io, scipy.spatial, splatdeform.basis
from splatdeform.memory import deform_bytes, file_cost
def status(key):
    return int(open('/proc/self/status').read().split(key + ':')[1].split()[0]) * 1024
base = status('VmRSS')
est = deform_bytes(file_cost(sys.argv[2]))
assert main(['deform', sys.argv[1]]) == 0
print(status('VmHWM') - base, est)
"""


def test_deform_bytes_bounds_the_measured_deform_peak(tmp_path: Path) -> None:
    import yaml

    from data_tools.make_archive import make_scans

    # large enough for the per-point part to outweigh the fit's worst case (max_centers)
    (scan,), _ = make_scans(tmp_path, 1, 600_000, spheres=False, zip_name=None)
    cfg = tmp_path / "e.yaml"
    edit = bar_edit({"pivot": [0.75, 0.5, 0.5], "rotate": {"axis": [0, 0, 1], "degrees": 35}},
                    input=str(scan), output=str(tmp_path / "out.ply"))
    del edit["fit"]   # the default fit, the one the estimate is for
    cfg.write_text(yaml.safe_dump(edit))
    r = subprocess.run([sys.executable, "-c", DEFORM, str(cfg), str(scan)], capture_output=True,
                       text=True, timeout=600, check=True)
    measured, estimate = map(int, r.stdout.split()[-2:])
    assert estimate >= measured, (measured / 2**20, estimate / 2**20)
    assert estimate <= 4 * measured + 64 * 2**20, (measured / 2**20, estimate / 2**20)


def test_stream_sizes_fit_their_budget() -> None:
    """A streamed chunk's working set takes at most a quarter of what the fixed part leaves (the
    5,000-point floor aside); the border and whole-handle caps grow with the budget."""
    from splatdeform.memory import STREAM_BYTES_PER_POINT, stream_caps, stream_chunk

    fixed = 150 * 2**20
    for budget in (256 * 2**20, 2**30, 8 * 2**30):
        for record in (15, 62, 248):
            chunk = stream_chunk(budget, record, fixed)
            assert 5_000 <= chunk <= 4_000_000
            if chunk > 5_000:
                assert chunk * (4 * record + STREAM_BYTES_PER_POINT) <= (budget - fixed) / 4
    small, big = stream_caps(256 * 2**20, fixed), stream_caps(2**30, fixed)
    assert 0 < small[0] < big[0] and 0 < small[1] < big[1]


def test_split_growth_and_a_stored_basis_are_counted() -> None:
    """The estimate counts what a run may add: split children (gaussians.split: auto, up to
    GROWTH_CAP of the points) and a stored basis (--reuse)."""
    from splatdeform.deform.split import GROWTH_CAP
    from splatdeform.io.format import FileCost
    from splatdeform.memory import STORED_BASIS_BYTES_PER_POINT, deform_bytes

    cost = FileCost(points=1_000_000, size=248_000_000, record_bytes=248, load_bytes=500 * 2**20)
    plain = deform_bytes(cost)
    assert deform_bytes(cost, growth=GROWTH_CAP) - plain == int(GROWTH_CAP * 1_000_000 * 248)
    assert deform_bytes(cost, stored=True) - plain == STORED_BASIS_BYTES_PER_POINT * 1_000_000
