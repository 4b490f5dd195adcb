""".ksplat read (issue 34 item 7): files made by GaussianSplats3D's own converter (the pinned npm
library, data_tools/ksplat_oracle.py, alpha threshold 0) at compression levels 0, 1, 2 and SH
degrees 0-2 load equal to splat-transform 3.7.0's decode of the same file and, matched to the
source PLY by position (the converter reorders splats), within each level's quantisation;
degree 3 (which the library 0.4.7 never writes) in the layout splat-transform reads; hostile
headers refused with one line."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file
from helpers import one_error_line, run_cli
from scipy.spatial import cKDTree
from splat_oracle import fields

from data_tools import ksplat_oracle, splat_transform
from splatdeform.errors import FormatError
from splatdeform.io import format_fields, ksplat, load
from splatdeform.io.splats import SH_C0, sigmoid

SCENE = "splats/tile_3dgs_sh3.ply"
LEVELS = (0, 1, 2)
DEGREES = (0, 1, 2)
NAMES = ("positions", "scale_log", "rotation", "sh_dc", "sh_rest")


@pytest.fixture(scope="module")
def oracles():
    try:
        splat_transform.install()
        splat_transform.command()
        ksplat_oracle.install()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"the .ksplat oracles are required: {exc}")


@pytest.fixture(scope="module")
def made(oracles, tmp_path_factory):
    """{(level, degree): .ksplat path} from the shared SH3 scene."""
    folder = tmp_path_factory.mktemp("ksplat")
    src = shared_file(SCENE)
    return {(lv, d): ksplat_oracle.convert(src, folder / f"tile_{lv}_{d}.ksplat", lv, d)
            for lv in LEVELS for d in DEGREES}


def _order_free(a, b):
    """``b`` reordered to ``a``'s splats, matched by nearest position (one to one)."""
    dist, idx = cKDTree(b.positions).query(a.positions)
    assert len(np.unique(idx)) == a.count == b.count
    return dist, idx


def _theirs(path: Path, tmp_path: Path):
    out = tmp_path / (path.stem + "_st.ply")
    splat_transform.run("-w", "-q", str(path), str(out))
    return fields(load(out))


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("degree", DEGREES)
def test_library_files_equal_splat_transform_decode(made, tmp_path, level, degree):
    path = made[level, degree]
    ours, theirs = fields(load(path)), _theirs(path, tmp_path)
    assert ours.sh_degree == degree
    _, idx = _order_free(ours, theirs)
    for name in NAMES:
        a, b = getattr(ours, name), getattr(theirs, name)[idx]
        atol = 1e-5 * max(1.0, float(np.abs(b).max(initial=0)))
        np.testing.assert_allclose(a, b, rtol=0, atol=atol, err_msg=name)
    # splat-transform clamps alpha to [1e-6, 1 - 1e-6]; byte 0 is alpha 0 here (-inf)
    np.testing.assert_allclose(sigmoid(ours.opacity), sigmoid(theirs.opacity[idx]), atol=2e-6)


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("degree", DEGREES)
def test_library_files_match_the_source_within_quantisation(made, level, degree):
    path = made[level, degree]
    ours, src = fields(load(path)), fields(load(shared_file(SCENE)))
    dist, idx = _order_free(ours, src)
    block = 5.0   # the converter's bucket block size; positions step block / 2 / 32767
    assert dist.max() <= (0 if level == 0 else 0.51 * block / 2 / 32767 * np.sqrt(3) + 1e-6)
    # scale: float32 (level 0) or float16 (three.js truncates: one unit in the last place,
    # relative 2**-10 or 2**-24 below float16's normal range; an underflow to 0 reads as -10)
    lin_src, lin = np.exp(src.scale_log[idx].astype(np.float64)), np.exp(ours.scale_log)
    zero = ours.scale_log == ksplat.ZERO_SCALE_LOG
    assert (lin_src[zero] < 2.0**-24).all()
    tol, floor = (1e-6, 0.0) if level == 0 else (2.0**-10, 2.0**-24)
    assert (np.abs(lin - lin_src)[~zero] <= tol * lin_src[~zero] + floor).all()
    qa = ours.rotation / np.linalg.norm(ours.rotation, axis=1, keepdims=True)
    qb = src.rotation[idx] / np.linalg.norm(src.rotation[idx], axis=1, keepdims=True)
    assert (1 - np.abs((qa * qb).sum(axis=1))).max() < (1e-6 if level == 0 else 1e-5)
    # colour and alpha: the converter floors 255 * value (clamped): one step below at most
    color = np.clip(0.5 + SH_C0 * src.sh_dc[idx].astype(np.float64), 0, 1)
    step = (color - (0.5 + SH_C0 * ours.sh_dc.astype(np.float64)))
    assert step.min() >= -1e-6 and step.max() <= 1 / 255 + 1e-6
    alpha = sigmoid(src.opacity[idx]) - sigmoid(ours.opacity)
    assert alpha.min() >= -1e-6 and alpha.max() <= 1 / 255 + 1e-6
    k = ours.sh_rest.shape[2]
    rest = src.sh_rest[idx][:, :, :k].astype(np.float64)
    if level == 2 and k:
        lo, hi = ksplat.parse_main(path, path.read_bytes(), path.stat().st_size)["sh_range"]
        rest = np.clip(rest, lo, hi)
        assert np.abs(ours.sh_rest - rest).max() <= (hi - lo) / 255 + 1e-6
    elif k:
        tol, floor = (0.0, 0.0) if level == 0 else (2.0**-10, 2.0**-24)
        assert (np.abs(ours.sh_rest - rest) <= tol * np.abs(rest) + floor).all()


def _degree_3_file(base: Path, out: Path, level: int) -> np.ndarray:
    """A copy of a degree-2 library file of ``level`` with a band 3 added (known values):
    the same header, its SH degree 3, each record widened by 21 SH values."""
    data = bytearray(base.read_bytes())
    main = ksplat.parse_main(base, bytes(data), len(data))
    (section,) = ksplat._sections(base, bytes(data), main, len(data))
    n = section["count"]
    old = np.frombuffer(bytes(data), section["record"], n, section["data_at"])
    new = np.zeros(n, ksplat._record(level, 3))
    for name in old.dtype.names:
        if name == "sh":
            new["sh"][:, :24] = old["sh"]
        else:
            new[name] = old[name]
    rng = np.random.default_rng(34)
    codes = rng.integers(0, 256, (n, 21)) if level == 2 else rng.uniform(-1, 1, (n, 21))
    new["sh"][:, 24:] = codes
    head = bytearray(data[:section["data_at"]])
    struct.pack_into("<H", head, ksplat.HEADER_BYTES + 40, 3)
    out.write_bytes(bytes(head) + new.tobytes())
    return codes


@pytest.mark.parametrize("level", LEVELS)
def test_degree_3_layout_is_splat_transforms(made, tmp_path, level):
    path = tmp_path / f"deg3_{level}.ksplat"
    _degree_3_file(made[level, 2], path, level)
    ours, theirs = fields(load(path)), _theirs(path, tmp_path)
    assert ours.sh_degree == 3 and theirs.sh_degree == 3
    _, idx = _order_free(ours, theirs)
    np.testing.assert_allclose(ours.sh_rest, theirs.sh_rest[idx], atol=1e-5)
    # bands 1-2 stay what the degree-2 file held
    two = fields(load(made[level, 2]))
    np.testing.assert_array_equal(ours.sh_rest[:, :, :8], two.sh_rest)


def test_info_names_the_level(made):
    info = format_fields(made[1, 2])
    assert info["format"].startswith(".ksplat v0.1")
    assert info["format_fields"] == {"compression_level": 1, "sections": 1, "sh_degree": 2}


def _hostile(made, tmp_path, edit) -> Path:
    data = bytearray(made[1, 1].read_bytes())
    data = edit(data) or data
    path = tmp_path / "bad.ksplat"
    path.write_bytes(bytes(data))
    return path


HOSTILE = {
    "version": (lambda d: d.__setitem__(0, 1), "version 1.1"),
    "level": (lambda d: struct.pack_into("<H", d, 20, 7), "compression level 7"),
    "sections": (lambda d: struct.pack_into("<I", d, 4, 2**31), "sections"),
    "count": (lambda d: struct.pack_into("<II", d, 12, 2**31, 2**31), "splats"),
    "truncated": (lambda d: d[:len(d) // 2], "more than the file"),
    "short_section": (lambda d: d[:-10], "past the end"),
    "tiny": (lambda d: d[:100], "too small"),
    "degree": (lambda d: struct.pack_into("<H", d, 4096 + 40, 9), "SH degree 9"),
    "buckets": (lambda d: struct.pack_into("<I", d, 4096 + 32, 10**6), "bucket layout"),
    "section_count": (lambda d: struct.pack_into("<I", d, 4096, 5), "sections hold"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_headers_are_one_line(made, tmp_path, case):
    edit, needle = HOSTILE[case]
    path = _hostile(made, tmp_path, edit)
    with pytest.raises(FormatError, match=needle) as err:
        load(path)
    assert str(err.value).startswith(str(path))


def test_cli_info_and_write_refusal(made, tmp_path):
    res = run_cli("info", made[2, 1])
    assert res.returncode == 0, res.stderr
    assert "ksplat" in res.stdout
    bad = _hostile(made, tmp_path, HOSTILE["truncated"][0])
    one_error_line(run_cli("info", bad), needles=("bad.ksplat",))
    one_error_line(run_cli("convert", made[0, 0], tmp_path / "x.ksplat"),
                   needles=("read only",))
