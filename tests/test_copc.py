"""COPC in, plain LAZ 1.4 out (issue 47 item 5). The COPC files are made by copc-lib (a dev
dependency, its own writer and octree); laspy and copc-lib read ours."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import copclib
import laspy
import numpy as np
import pytest
import yaml

from splatdeform.cli import main
from splatdeform.io import load, save

WKT = ('PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
       '6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
       'PROJECTION["Transverse_Mercator"],UNIT["metre",1]]')


def _copc(path: Path, n: int = 3000, seed: int = 2) -> Path:
    """A COPC file (point format 7, a WKT) with its points in the root node and one child."""
    rng = np.random.default_rng(seed)
    cfg = copclib.CopcConfigWriter(7, copclib.Vector3(0.001, 0.001, 0.001),
                                   copclib.Vector3(500000, 5400000, 0), WKT)
    writer = copclib.FileWriter(str(path), cfg)
    header = writer.copc_config.las_header
    xyz = np.stack([500000 + rng.uniform(0, 50, n), 5400000 + rng.uniform(0, 50, n),
                    rng.uniform(0, 10, n)], axis=1)
    nodes = {copclib.VoxelKey(0, 0, 0, 0): xyz[: n // 2],
             copclib.VoxelKey(1, 0, 0, 0): xyz[n // 2:]}
    for key, part in nodes.items():
        points = copclib.Points(header)
        for i, (x, y, z) in enumerate(part):
            p = points.CreatePoint()
            p.x, p.y, p.z = float(x), float(y), float(z)
            p.intensity = int(i * 7 % 65535)
            p.return_number, p.number_of_returns = 1, 1
            p.classification = 2 if z < 5 else 5
            p.red, p.green, p.blue = 1000, 2000, 3000
            points.AddPoint(p)
        writer.AddNode(key, points)
    writer.Close()
    return path


def _users(records) -> list[str]:
    return [v.user_id for v in records]


def test_copc_loads_as_the_laz_it_is(tmp_path, capsys) -> None:
    src = _copc(tmp_path / "site.copc.laz")
    model = load(src)
    theirs = laspy.read(src)
    assert model.n_points == len(theirs.points)
    np.testing.assert_array_equal(model.positions,
                                  np.stack([theirs.x, theirs.y, theirs.z], axis=1))
    assert main(["info", str(src)]) == 0
    assert "LAS 1.4 point format 7 (COPC)" in capsys.readouterr().out


@pytest.mark.parametrize("ext", [".laz", ".las"])
def test_copc_written_as_plain_laz(tmp_path, ext) -> None:
    src = _copc(tmp_path / "site.copc.laz")
    out = tmp_path / f"plain{ext}"
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        save(load(src), out)
    notes = [str(w.message) for w in said if "COPC octree" in str(w.message)]
    assert len(notes) == 1 and str(out) in notes[0]
    a, b = laspy.read(src), laspy.read(out)
    assert str(b.header.version) == "1.4" and b.header.point_format.id == 7
    assert np.array_equal(a.points.array, b.points.array)
    assert "copc" not in _users(b.header.vlrs) + _users(b.evlrs or [])
    wkt = [v for v in list(a.header.vlrs) + list(a.evlrs or []) if v.user_id == "LASF_Projection"]
    kept = [v for v in list(b.header.vlrs) + list(b.evlrs or []) if v.user_id == "LASF_Projection"]
    assert wkt and [bytes(v.record_data_bytes()) for v in kept] == \
        [bytes(v.record_data_bytes()) for v in wkt]    # the CRS kept byte for byte
    # the kept header bytes: the point counts and GUID are the input's
    ra, rb = src.read_bytes(), out.read_bytes()
    assert ra[8:24] == rb[8:24] and ra[247:375] == rb[247:375]
    # copc-lib does not take our file for a COPC
    with pytest.raises(Exception):  # noqa: B017  (copc-lib raises its own runtime errors)
        copclib.FileReader(str(out))
    assert struct.unpack_from("<I", rb, 100)[0] == len(b.header.vlrs) + (ext == ".laz")


def test_copc_deformed_into_plain_laz(tmp_path) -> None:
    src = _copc(tmp_path / "site.copc.laz")
    out = tmp_path / "bent.laz"
    cfg = {"input": str(src), "output": str(out),
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                       "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"translate": [0, 0, 0.2]}},
           "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["deform", str(tmp_path / "e.yaml"), "--quiet"]) == 0
    a, b = laspy.read(src), laspy.read(out)
    assert len(a.points) == len(b.points)
    assert (b.z - a.z).max() > 1.0
    for name in ("intensity", "classification", "red", "gps_time"):
        assert np.array_equal(np.asarray(a[name]), np.asarray(b[name])), name
    assert "copc" not in _users(b.header.vlrs) + _users(b.evlrs or [])
