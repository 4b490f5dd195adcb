"""A LAS/LAZ file's header, VLR and EVLR bytes survive a save (issue 47 item 1).

Every shared LAS/LAZ file, and LAS 1.4 point format 7 files made here the way scanner software
writes them (legacy counts filled, return numbers left 0, a GeoKeyDirectory whose key count
laspy would rewrite, an OGC WKT EVLR), is loaded and saved, plainly and after a deform; the raw
header bytes are compared except the fields that must change (the bounding box, and with a
deform scale/offset when moved: see splatdeform/io/las_keep.py), and every VLR/EVLR record
byte for byte (the ``laszip encoded`` VLR is the writer's own). laspy reads each output.
"""

from __future__ import annotations

import struct
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml
from conftest import shared_file
from laspy.vlrs.vlrlist import VLRList

from splatdeform.cli import main
from splatdeform.edit import load_edit
from splatdeform.edit.stream import run_stream
from splatdeform.io import las as las_io
from splatdeform.io import load, save

SHARED = ("lidar/extrabytes.las", "lidar/simple.laz", "lidar/vegetation_1_3.las")
BBOX = slice(179, 227)
SCALE_OFFSET = slice(131, 179)
LAYOUT = slice(94, 107)   # header size, offset to points, VLR count, point format, length
EVLR_START = slice(235, 243)  # moves with the size of the (compressed) points


def _geokeys(n_declared: int, n_entries: int) -> bytes:
    """A GeoKeyDirectory payload whose header declares ``n_declared`` keys but holds
    ``n_entries`` key entries (as some writers leave it; laspy rewrites the count)."""
    keys = [(1024, 0, 1, 1), (1025, 0, 1, 1), (3072, 0, 1, 32632)]
    keys += [(4096 + i, 0, 1, i) for i in range(n_entries - len(keys))]
    return struct.pack("<4H", 1, 1, 0, n_declared) + b"".join(struct.pack("<4H", *k)
                                                               for k in keys)


WKT = (b'PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
       b'6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
       b'PROJECTION["Transverse_Mercator"],UNIT["metre",1]]\0')


def _scanner_las(path: Path, n: int = 3000, seed: int = 7) -> Path:
    """LAS 1.4 point format 7 as scanner software writes it: legacy point count and
    points-by-return filled (every point a first return) though return_number is 0, a
    GeoKeyDirectory of 21 declared / 22 held keys, a WKT EVLR, a dated header and a VLR
    description with bytes after its terminating NUL."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version="1.4", point_format=7)
    header.scales = np.full(3, 0.001)
    header.offsets = np.array([500000.0, 5400000.0, 100.0])
    header.vlrs.append(laspy.VLR("LASF_Projection", 34735, "GeoKeyDirectoryTag",
                                 _geokeys(21, 22)))
    data = laspy.LasData(header)
    data.x = 500000.0 + rng.uniform(0, 50, n)
    data.y = 5400000.0 + rng.uniform(0, 50, n)
    data.z = 100.0 + rng.uniform(0, 5, n)
    data.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    data.red = rng.integers(0, 65535, n).astype(np.uint16)
    data.green = data.red
    data.blue = data.red
    data.gps_time = np.sort(rng.uniform(0, 1000, n))
    data.evlrs = VLRList([laspy.VLR("LASF_Projection", 2112, "OGC WKT", WKT)])
    data.write(path)
    raw = bytearray(path.read_bytes())
    struct.pack_into("<HH", raw, 90, 200, 2019)               # creation day 200 of 2019
    struct.pack_into("<I5I", raw, 107, n, n, 0, 0, 0, 0)      # legacy counts filled
    struct.pack_into("<15Q", raw, 255, n, *([0] * 14))        # every point a first return
    raw[58:90] = b"TerraScan\0".ljust(32, b"\0")
    first_vlr = struct.unpack_from("<H", raw, 94)[0]
    raw[first_vlr + 22:first_vlr + 54] = b"GeoKeyDirectoryTag\0junk".ljust(32, b"\0")
    path.write_bytes(bytes(raw))
    return path


def _laz(src: Path, out: Path) -> Path:
    """The same file compressed by laspy, its header and VLR bytes put back."""
    save(load(src), out)
    return out


def _records(data: bytes, start: int, count: int, head: int, long: bool) -> list[bytes]:
    out, at = [], start
    for _ in range(count):
        length = struct.unpack_from("<Q" if long else "<H", data, at + 20)[0]
        out.append(data[at:at + head + length])
        at += head + length
    return out


def _vlrs(data: bytes) -> list[bytes]:
    size, _, n = struct.unpack_from("<HII", data, 94)
    return [r for r in _records(data, size, n, 54, False)
            if r[2:16] != b"laszip encoded"]


def _evlrs(data: bytes) -> list[bytes]:
    if data[25] < 4:
        return []
    start, n = struct.unpack_from("<QI", data, 235)
    return _records(data, start, n, 60, True) if n else []


def _header_diff(a: bytes, b: bytes, allowed: tuple[slice, ...]) -> list[int]:
    size = struct.unpack_from("<H", a, 94)[0]
    skip = {i for s in allowed for i in range(s.start, s.stop)}
    return [i for i in range(size) if a[i] != b[i] and i not in skip]


def _inputs(tmp_path: Path) -> list[Path]:
    made = _scanner_las(tmp_path / "scanner14.las")
    return [shared_file(r) for r in SHARED] + [made, _laz(made, tmp_path / "scanner14.laz")]


def test_made_file_is_what_laspy_would_rewrite(tmp_path: Path) -> None:
    """The made file holds what laspy alone loses: a plain laspy read/write changes it."""
    src = _scanner_las(tmp_path / "s.las")
    laspy.read(src).write(tmp_path / "laspy.las")
    a, b = src.read_bytes(), (tmp_path / "laspy.las").read_bytes()
    assert _header_diff(a, b, (BBOX,))            # legacy counts, creation date
    assert _vlrs(a) != _vlrs(b)                   # GeoKey count (21 -> 22), description


@pytest.mark.parametrize("suffix", [".same", ".las", ".laz"])
def test_plain_save_keeps_header_and_records(tmp_path: Path, suffix: str) -> None:
    for src in _inputs(tmp_path):
        ext = src.suffix if suffix == ".same" else suffix
        out = tmp_path / f"out_{src.stem}{ext}"
        save(load(src), out)
        a, b = src.read_bytes(), out.read_bytes()
        allowed = (BBOX,) if ext == src.suffix else (BBOX, LAYOUT, EVLR_START)
        assert _header_diff(a, b, allowed) == [], (src.name, ext)
        assert _vlrs(a) == _vlrs(b), src.name
        assert _evlrs(a) == _evlrs(b), src.name
        if ext == src.suffix:
            assert a[94:107] == b[94:107], src.name
        la, lb = laspy.read(src), laspy.read(out)
        assert np.array_equal(la.points.array, lb.points.array), src.name
        assert lb.header.point_count == la.header.point_count
        assert np.array_equal(lb.header.number_of_points_by_return,
                              la.header.number_of_points_by_return)
        assert lb.header.creation_date == la.header.creation_date


def _deform(src: Path, out: Path, tmp_path: Path, *, chunk: int | None = None) -> None:
    """Deform ``src`` into ``out`` (in memory, or streamed ``chunk`` points at a time)."""
    cfg = {"input": str(src), "output": str(out),
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                       "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"translate": [0, 0, 0.3]}},
           "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    path = tmp_path / f"{out.stem}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    if chunk is None:
        assert main(["deform", str(path), "--quiet"]) == 0
    else:
        run_stream(load_edit(path), tmp_path, chunk=chunk, quiet=True)


def test_deform_keeps_header_and_records(tmp_path: Path) -> None:
    for src in _inputs(tmp_path):
        out = tmp_path / f"bent_{src.name}"
        _deform(src, out, tmp_path)
        a, b = src.read_bytes(), out.read_bytes()
        assert _header_diff(a, b, (BBOX, SCALE_OFFSET, EVLR_START)) == [], src.name
        assert _vlrs(a) == _vlrs(b) and _evlrs(a) == _evlrs(b), src.name
        la, lb = laspy.read(src), laspy.read(out)
        assert not np.array_equal(la.z, lb.z), src.name
        assert np.allclose(lb.header.maxs, [lb.x.max(), lb.y.max(), lb.z.max()])
        assert np.array_equal(np.asarray(la.return_number), np.asarray(lb.return_number))


def test_streamed_deform_keeps_header_and_records(tmp_path: Path) -> None:
    src = _scanner_las(tmp_path / "big.las", n=20000)
    out = tmp_path / "bent_stream.las"
    _deform(src, out, tmp_path, chunk=5000)
    a, b = src.read_bytes(), out.read_bytes()
    assert _header_diff(a, b, (BBOX, SCALE_OFFSET)) == []
    assert _vlrs(a) == _vlrs(b) and _evlrs(a) == _evlrs(b)


def test_counts_recomputed_when_the_number_changes(tmp_path: Path) -> None:
    """Fewer points written than read: the counts are counted again, by return number where
    it is set, and as the input counted them (first returns, legacy fields) where not."""
    for src, n in ((_scanner_las(tmp_path / "s.las"), 1000),
                   (shared_file("lidar/simple.laz"), 500)):
        model = load(src)
        source = model.source
        out = tmp_path / f"half_{src.name}"
        writer = las_io.LasWriter(source.header, out, source.evlrs, source.raw)
        writer.write(source.points[:n])
        writer.close()
        b = laspy.read(out)
        a = laspy.read(src)
        assert b.header.point_count == n
        returns = np.asarray(a.return_number)[:n]
        if returns.any():
            want = np.bincount(returns, minlength=16)[1:16]
        else:
            want = np.zeros(15, dtype=np.int64)
            want[0] = n
        assert np.array_equal(b.header.number_of_points_by_return, want)
        raw = out.read_bytes()
        assert struct.unpack_from("<I", raw, 107)[0] == n       # legacy count as the input
        assert _vlrs(src.read_bytes()) == _vlrs(raw)
