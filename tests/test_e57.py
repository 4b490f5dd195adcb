"""E57 in and out (issue 47 item 4), checked with pye57 (libE57Format) as the independent
reader; the test files are made with pye57 itself: several scans with poses, with and without
a row/column grid, colour, intensity and invalid points, and one written through its libE57
binding with scaled-integer coordinates, return indices and time stamps."""

from __future__ import annotations

import numpy as np
import pye57
import pytest
import yaml
from pye57 import libe57

from splatdeform import memory
from splatdeform.cli import main
from splatdeform.io import load, save

QUARTER_Z = np.array([np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)])   # 45 degrees about z


def _returns_scan(path, rng, n: int = 600) -> None:
    """Append one scan through libE57 directly: scaled-integer coordinates (0.1 mm), returns,
    time stamps and a pose (pye57's writer holds none of these)."""
    e = pye57.E57(str(path), mode="w")
    imf = e.image_file
    scan = libe57.StructureNode(imf)
    scan.set("guid", libe57.StringNode(imf, "{returns-scan}"))
    scan.set("name", libe57.StringNode(imf, "returns"))
    scan.set("description", libe57.StringNode(imf, "made by the test through libE57"))
    pose = libe57.StructureNode(imf)
    rot = libe57.StructureNode(imf)
    for k, v in zip("wxyz", [0.0, 0.0, 0.0, 1.0], strict=True):    # 180 degrees about z
        rot.set(k, libe57.FloatNode(imf, v))
    tr = libe57.StructureNode(imf)
    for k, v in zip("xyz", [-5.0, 2.0, 0.5], strict=True):
        tr.set(k, libe57.FloatNode(imf, v))
    pose.set("rotation", rot)
    pose.set("translation", tr)
    scan.set("pose", pose)
    proto = libe57.StructureNode(imf)
    for c in ("cartesianX", "cartesianY", "cartesianZ"):
        proto.set(c, libe57.ScaledIntegerNode(imf, 0, -200000, 200000, 1e-4, 0.0))
    proto.set("returnIndex", libe57.IntegerNode(imf, 0, 0, 3))
    proto.set("returnCount", libe57.IntegerNode(imf, 1, 1, 4))
    proto.set("timeStamp", libe57.FloatNode(imf, 0.0, libe57.FloatPrecision.E57_DOUBLE, 0.0, 1e6))
    points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    scan.set("points", points)
    e.data3d.append(scan)
    data = {"cartesianX": np.rint(rng.uniform(-5, 5, n) * 1e4).astype(np.longlong),
            "cartesianY": np.rint(rng.uniform(-5, 5, n) * 1e4).astype(np.longlong),
            "cartesianZ": np.rint(rng.uniform(0, 3, n) * 1e4).astype(np.longlong),
            "returnCount": rng.integers(1, 5, n).astype(np.longlong)}
    data["returnIndex"] = (rng.integers(0, 4, n) % data["returnCount"]).astype(np.longlong)
    data["timeStamp"] = np.sort(rng.uniform(0, 100, n))
    buffers = libe57.VectorSourceDestBuffer()
    for name, values in data.items():
        buffers.append(libe57.SourceDestBuffer(imf, name, values, n, True, False))
    writer = points.writer(buffers)
    writer.write(n)
    writer.close()
    e.close()


def _scans(tmp_path, seed: int = 3):
    """Three scans written by pye57 (a grid with colour, intensity and invalid points under a
    45-degree pose; a bare one and one with intensity, each with an offset pose), and one
    scan through libE57 in a second file."""
    rng = np.random.default_rng(seed)
    path = tmp_path / "site.e57"
    e = pye57.E57(str(path), mode="w")
    rows, cols = 30, 40
    n = rows * cols
    invalid = (rng.uniform(size=n) < 0.15).astype(np.int8) * 2
    grid = {"cartesianX": rng.uniform(-3, 3, n), "cartesianY": rng.uniform(-3, 3, n),
            "cartesianZ": rng.uniform(0, 2, n),
            "intensity": rng.uniform(0, 1, n).astype(np.float32),
            "colorRed": rng.integers(0, 256, n).astype(np.uint8),
            "colorGreen": rng.integers(0, 256, n).astype(np.uint8),
            "colorBlue": rng.integers(0, 256, n).astype(np.uint8),
            "rowIndex": (np.arange(n) // cols).astype(np.uint16),
            "columnIndex": (np.arange(n) % cols).astype(np.uint16),
            "cartesianInvalidState": invalid}
    e.write_scan_raw(grid, name="station 1", rotation=QUARTER_Z,
                     translation=np.array([100.0, 50.0, 2.0]))
    bare = {c: rng.uniform(-2, 2, 500) for c in ("cartesianX", "cartesianY", "cartesianZ")}
    e.write_scan_raw(bare, name="station 2", rotation=np.array([1.0, 0, 0, 0]),
                     translation=np.array([104.0, 50.0, 2.0]))
    third = {**{c: rng.uniform(-1, 1, 300) for c in ("cartesianX", "cartesianY", "cartesianZ")},
             "intensity": rng.uniform(0, 1, 300).astype(np.float32)}
    e.write_scan_raw(third, name="station 3", rotation=np.array([1.0, 0, 0, 0]),
                     translation=np.array([99.0, 47.0, 2.0]))
    e.close()
    other = tmp_path / "returns.e57"
    _returns_scan(other, rng)
    return path, other


def _theirs(path) -> np.ndarray:
    """pye57's own world positions (poses applied, invalid points dropped), scan by scan."""
    e = pye57.E57(str(path))
    return np.concatenate([_world(e, i) for i in range(e.scan_count)])


def _world(e, i: int) -> np.ndarray:
    header = e.get_header(i)
    raw = _raw(e, i)
    xyz = np.stack([raw[c] for c in ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
    if "cartesianInvalidState" in raw:
        xyz = xyz[raw["cartesianInvalidState"] == 0]
    return e.to_global(xyz, header.rotation, header.translation)


def _raw(e, i: int, scaled: bool = True) -> dict:
    """Every field of scan ``i`` as libE57 reads it (scaled integers scaled, or raw; 64-bit
    integers as C long long, the only 64-bit integer pye57's buffers take)."""
    header = e.get_header(i)
    n = header.point_count
    proto = libe57.StructureNode(header.points.prototype())
    data, buffers = {}, libe57.VectorSourceDestBuffer()
    for k in range(proto.childCount()):
        name = proto.get(k).elementName()
        kind = proto.get(k).type()
        scaled_int = kind == libe57.NodeType.E57_SCALED_INTEGER
        dtype = np.float64 if kind == libe57.NodeType.E57_FLOAT or (scaled_int and scaled) \
            else np.longlong
        data[name] = np.empty(n, dtype)
        buffers.append(libe57.SourceDestBuffer(e.image_file, name, data[name], n, True,
                                               scaled))
    header.points.reader(buffers).read()
    return data


def test_every_scan_loads_in_one_world_frame(tmp_path) -> None:
    for path in _scans(tmp_path):
        model = load(path)
        theirs = _theirs(path)
        assert model.n_points == len(theirs)
        np.testing.assert_allclose(model.positions, theirs, rtol=0, atol=1e-9)
    model = load(tmp_path / "site.e57")
    assert model.n_points == int(1200 - (model.source.scans[0].valid == 0).sum()) + 800
    assert model.colors is None        # stations 2 and 3 hold no colour: none for the model
    vertex = model.source.element("vertex")
    for name in ("scan", "intensity", "rowIndex", "columnIndex"):
        assert name in vertex.data.dtype.names


def test_info_lists_the_scans(tmp_path, capsys) -> None:
    site, _ = _scans(tmp_path)
    assert main(["info", str(site)]) == 0
    out = capsys.readouterr().out
    assert "E57 1.0, 3 scan(s)" in out
    for name in ("station 1", "station 2", "station 3"):
        assert f"scan '{name}'" in out
    assert "grid 30x40" in out and "up:       +z" in out


def _same_fields(a_path, b_path, moved_ok: bool) -> None:
    a, b = pye57.E57(str(a_path)), pye57.E57(str(b_path))
    assert a.scan_count == b.scan_count
    for i in range(a.scan_count):
        ha, hb = a.get_header(i), b.get_header(i)
        assert ha["name"].value() == hb["name"].value()
        assert ha["guid"].value() == hb["guid"].value()
        assert np.array_equal(ha.rotation, hb.rotation) and \
            np.array_equal(ha.translation, hb.translation)
        assert ha.point_fields == hb.point_fields
        ra, rb = _raw(a, i, scaled=False), _raw(b, i, scaled=False)
        for name in ra:
            if moved_ok and name.startswith("cartesian") and name != "cartesianInvalidState":
                continue
            assert np.array_equal(ra[name], rb[name]), (i, name)


def test_plain_save_keeps_every_scan_whole(tmp_path) -> None:
    for path in _scans(tmp_path):
        out = tmp_path / f"back_{path.name}"
        save(load(path), out)
        _same_fields(path, out, moved_ok=False)


def test_deform_moves_every_scan_in_the_world_frame(tmp_path) -> None:
    site, _ = _scans(tmp_path)
    out = tmp_path / "bent.e57"
    cfg = {"input": str(site), "output": str(out),
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                       "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"translate": [0, 0, 0.2]}},
           "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["deform", str(tmp_path / "e.yaml"), "--quiet"]) == 0
    before, after = load(site), load(out)
    theirs = _theirs(out)
    np.testing.assert_allclose(theirs, after.positions, rtol=0, atol=1e-9)
    lift = theirs[:, 2] - before.positions[:, 2]
    u = (before.positions[:, 0] - before.positions[:, 0].min()) / np.ptp(before.positions[:, 0])
    assert np.abs(lift[u <= 0.3]).max() < 1e-9          # the fixed part of every scan
    assert lift[u >= 0.7].min() > 0.1                    # the handle, across scans
    handle_scans = {int(s) for s in after.source.element("vertex").data["scan"][u >= 0.7]}
    assert len(handle_scans) >= 2
    _same_fields(site, out, moved_ok=True)               # poses, invalid points, every field
    a, b = pye57.E57(str(site)), pye57.E57(str(out))
    ra, rb = _raw(a, 0), _raw(b, 0)
    holes = ra["cartesianInvalidState"] != 0
    for c in ("cartesianX", "cartesianY", "cartesianZ"):
        assert np.array_equal(ra[c][holes], rb[c][holes])


def test_other_formats_write_one_scan(tmp_path) -> None:
    from splatdeform.model import PointModel, classify

    rng = np.random.default_rng(5)
    model = PointModel(positions=rng.normal(size=(400, 3)),
                       colors=rng.integers(0, 256, (400, 3)).astype(np.uint8),
                       kind=classify(has_faces=False, has_normals=False, has_radius=False,
                                     has_axes=False, has_gaussians=False))
    save(model, tmp_path / "cloud.ply")
    out = tmp_path / "cloud.e57"
    assert main(["convert", str(tmp_path / "cloud.ply"), str(out)]) == 0
    e = pye57.E57(str(out))
    assert e.scan_count == 1
    data = e.read_scan(0, colors=True, ignore_missing_fields=True)
    np.testing.assert_allclose(np.stack([data["cartesianX"], data["cartesianY"],
                                         data["cartesianZ"]], axis=1), model.positions)
    assert np.array_equal(data["colorRed"], model.colors[:, 0])
    back = load(out)
    assert np.array_equal(back.colors, model.colors)
    np.testing.assert_allclose(back.positions, model.positions)


def test_probe_counts_and_refusals(tmp_path, capsys) -> None:
    site, other = _scans(tmp_path)
    assert memory.file_cost(site).points == 1200 + 500 + 300
    assert memory.file_cost(other).points == 600
    bad = tmp_path / "bad.e57"
    raw = bytearray(site.read_bytes())
    raw[16:24] = (len(raw) * 3).to_bytes(8, "little")    # physical length != the file size
    bad.write_bytes(bytes(raw))
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.e57" in err and "physical length" in err and err.count("\n") == 1
    short = tmp_path / "short.e57"
    short.write_bytes(site.read_bytes()[:3000])
    assert main(["info", str(short)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_over_the_budget_is_refused(tmp_path, capsys) -> None:
    site, _ = _scans(tmp_path)
    choice = memory.choose(memory.file_cost(site).load_bytes, 1024, streamable=False,
                           name=site)
    assert choice.mode == "refuse"


@pytest.mark.parametrize("kind", ["site", "returns"])
def test_convert_to_ply_keeps_fields(tmp_path, kind) -> None:
    site, other = _scans(tmp_path)
    src = site if kind == "site" else other
    out = tmp_path / f"{kind}.ply"
    assert main(["convert", str(src), str(out)]) == 0
    back = load(out)
    names = back.source.element("vertex").data.dtype.names
    want = ("intensity", "rowIndex") if kind == "site" else ("returnIndex", "returnCount",
                                                             "timeStamp")
    assert all(n in names for n in (*want, "scan"))
    np.testing.assert_allclose(back.positions, _theirs(src), atol=1e-4)
