"""LAS/LAZ: lossless round trips of the real files, a handle edit through the CLI that keeps
every non-coordinate dimension, int32 overflow handling, conversion to/from PLY."""

from __future__ import annotations

import warnings
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml
from conftest import shared_file

from splatdeform.cli import main
from splatdeform.io import las, load, save
from splatdeform.model import PointModel

LIDAR = ("lidar/simple.laz", "lidar/vegetation_1_3.las", "lidar/extrabytes.las")


@pytest.mark.parametrize("rel", LIDAR)
def test_round_trip_lossless(rel: str, tmp_path: Path) -> None:
    src = shared_file(rel)
    model = load(src)
    assert model.n_points > 0 and model.kind == "cloud"
    out = tmp_path / ("out" + src.suffix)
    save(model, out)
    a, b = laspy.read(src), laspy.read(out)
    assert a.points.array.dtype == b.points.array.dtype
    assert np.array_equal(a.points.array, b.points.array)  # every dimension, same order
    for name in a.point_format.dimension_names:
        assert np.array_equal(np.asarray(a[name]), np.asarray(b[name])), name
    assert list(a.point_format.extra_dimension_names) == list(b.point_format.extra_dimension_names)
    assert np.array_equal(a.header.scales, b.header.scales)
    assert np.array_equal(a.header.offsets, b.header.offsets)
    assert str(a.header.version) == str(b.header.version)
    assert a.header.point_format.id == b.header.point_format.id
    assert [(v.user_id, v.record_id, v.record_data_bytes()) for v in a.header.vlrs] == \
        [(v.user_id, v.record_id, v.record_data_bytes()) for v in b.header.vlrs]
    assert b.header.are_points_compressed == (src.suffix == ".laz")
    assert a.header.system_identifier == b.header.system_identifier
    assert a.header.generating_software == b.header.generating_software
    assert np.array_equal(load(out).positions, model.positions)


def test_extra_bytes_and_info(capsys) -> None:
    src = shared_file("lidar/extrabytes.las")
    assert main(["info", str(src), "--json"]) == 0
    text = capsys.readouterr().out
    assert "LAS 1.4 point format 3" in text
    for name in ("classification", "gps_time", "Colors_0", "Intensity", "Time"):
        assert f'"{name}"' in text
    model = load(src)
    assert model.colors is not None and model.colors.dtype == np.uint8


def test_property_selector_on_las_dimension() -> None:
    from splatdeform.edit.selectors import Property, select

    model = load(shared_file("lidar/simple.laz"))
    mask = select(model, [Property("classification", 2)])
    truth = np.asarray(laspy.read(shared_file("lidar/simple.laz")).classification) == 2
    assert mask.any() and np.array_equal(mask, truth)


def test_handle_edit_keeps_every_other_dimension(tmp_path: Path) -> None:
    src = shared_file("lidar/simple.laz")
    out = tmp_path / "bent.laz"
    cfg = {
        "input": str(src), "output": str(out),
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                    "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"translate": [0, 0, 0.3],
                                 "rotate": {"axis": [0, 1, 0], "degrees": 5}}},
        "fit": {"tolerance": 1e-3},
        "backend": "numpy",
    }
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["deform", str(path)]) == 0
    a, b = laspy.read(src), laspy.read(out)
    assert b.header.are_points_compressed
    assert len(a.points) == len(b.points)
    for name in ("classification", "intensity", "gps_time", "red", "green", "blue",
                 "return_number", "number_of_returns", "point_source_id", "scan_angle_rank"):
        assert np.array_equal(np.asarray(a[name]), np.asarray(b[name])), name
    assert np.array_equal(a.header.scales, b.header.scales)
    # the fixed region is bit-exact (same integers); the handle moved up
    u = (a.x - a.x.min()) / (a.x.max() - a.x.min())
    fixed = u <= 0.3
    assert np.array_equal(a.X[fixed], b.X[fixed]) and np.array_equal(a.Z[fixed], b.Z[fixed])
    handle = u >= 0.7
    assert (b.z[handle] - a.z[handle]).mean() > 0.1 * (a.z.max() - a.z.min())


def _big_las(path: Path, offset: float, scale: float, n: int = 200) -> Path:
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales = np.full(3, scale)
    header.offsets = np.full(3, offset)
    rng = np.random.default_rng(7)
    data = laspy.LasData(header)
    ints = rng.integers(2**31 - 2000, 2**31 - 1, size=(n, 3), dtype=np.int64)
    data.X, data.Y, data.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    data.classification = rng.integers(0, 10, n)
    data.intensity = rng.integers(0, 60000, n)
    data.write(path)
    return path


def test_overflow_moves_offset_with_warning(tmp_path: Path) -> None:
    src = _big_las(tmp_path / "big.las", offset=0.0, scale=0.001)
    model = load(src)
    moved = model.copy()
    moved.positions[:10, 0] += 5000.0  # 5e6 steps beyond int32
    with pytest.warns(UserWarning, match="overflow the LAS int32 range"):
        save(moved, tmp_path / "moved.las")
    back = load(tmp_path / "moved.las")
    assert np.allclose(back.positions, moved.positions, atol=0.0006, rtol=0)
    # untouched points keep their exact coordinates; the other dimensions are kept
    assert np.abs(back.positions[10:] - model.positions[10:]).max() < 1e-6
    a, b = laspy.read(src), laspy.read(tmp_path / "moved.las")
    assert np.array_equal(np.asarray(a.classification), np.asarray(b.classification))
    assert np.array_equal(a.header.scales, b.header.scales)


def test_overflow_widens_scale_only_when_extent_too_big(tmp_path: Path) -> None:
    src = _big_las(tmp_path / "big.las", offset=0.0, scale=0.001)
    model = load(src)
    moved = model.copy()
    moved.positions[0, 1] = -3.0e6  # extent 5.1e6 m = 5.1e9 steps > int32
    with pytest.warns(UserWarning, match="widened the y scale"):
        save(moved, tmp_path / "wide.las")
    b = laspy.read(tmp_path / "wide.las")
    assert b.header.scales[1] > 0.001 and b.header.scales[0] == 0.001
    assert np.allclose(np.asarray(b.y), moved.positions[:, 1], atol=b.header.scales[1])


def test_no_warning_without_overflow(tmp_path: Path) -> None:
    model = load(shared_file("lidar/vegetation_1_3.las"))
    moved = model.copy()
    moved.positions += 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save(moved, tmp_path / "v.las")
    assert np.allclose(load(tmp_path / "v.las").positions, moved.positions, atol=6e-4)


def test_ply_to_las_and_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(500, 3)) * 10 + 1000
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    model = PointModel(positions=pts, normals=normals, colors=colors, kind="oriented_cloud")
    save(model, tmp_path / "a.laz")
    back = load(tmp_path / "a.laz")
    assert back.kind == "oriented_cloud"
    assert np.allclose(back.positions, pts, atol=1e-6)
    assert np.allclose(back.normals, normals, atol=1e-6)
    assert np.array_equal(back.colors, colors)
    # LAS -> PLY keeps every decoded dimension as a vertex property
    save(load(shared_file("lidar/simple.laz")), tmp_path / "s.ply")
    ply = load(tmp_path / "s.ply")
    names = ply.source.element("vertex").data.dtype.names
    assert {"classification", "intensity", "gps_time", "red"} <= set(names)


def test_not_a_las_file(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"PLY nonsense" * 10)
    assert main(["info", str(bad)]) == 2
    assert "not a LAS/LAZ file" in capsys.readouterr().err
    truncated = tmp_path / "trunc.las"
    truncated.write_bytes(shared_file("lidar/vegetation_1_3.las").read_bytes()[:5000])
    assert main(["info", str(truncated)]) == 2
    err = capsys.readouterr().err
    assert "trunc.las" in err and err.count("\n") == 1


def test_chunked_read_matches_whole(tmp_path: Path) -> None:
    src = shared_file("lidar/simple.laz")
    header, compressed, _ = las.read_header(src)
    assert compressed
    whole = laspy.read(src).points.array
    parts = list(las.iter_chunks(src, 300))
    assert [len(p) for p in parts] == [300, 300, 300, 165]
    assert np.array_equal(np.concatenate(parts), whole)
    assert np.array_equal(np.concatenate(list(las.iter_chunks(src, 100, 250, 700))),
                          whole[250:700])
    writer = las.LasWriter(header, tmp_path / "w.laz")
    for p in parts:
        writer.write(p)
    writer.close()
    assert np.array_equal(laspy.read(tmp_path / "w.laz").points.array, whole)


def test_batch_over_las_members(tmp_path: Path) -> None:
    """Batch folders and archives may hold .las/.laz scans; outputs keep the format and every
    other dimension."""
    import shutil
    import zipfile

    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(shared_file("lidar/simple.laz"), scans / "a.laz")
    with zipfile.ZipFile(tmp_path / "scans.zip", "w") as z:
        z.write(scans / "a.laz", "a.laz")
    edit = {"regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                        "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": {"translate": [0, 0, 0.2]}},
            "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    for scan_key, out in (("scans.zip", "out_zip"),):  # archive members (folders: same path)
        cfg = tmp_path / f"{out}.yaml"
        cfg.write_text(yaml.safe_dump({"scans": scan_key, "edit": edit, "output_dir": out,
                                       "workers": 1}))
        assert main(["batch", str(cfg), "--quiet"]) == 0
    a = laspy.read(scans / "a.laz")
    for out in ("out_zip",):
        b = laspy.read(tmp_path / out / "a_deformed.laz")
        assert b.header.are_points_compressed
        for name in ("classification", "intensity", "gps_time", "red"):
            assert np.array_equal(np.asarray(a[name]), np.asarray(b[name])), name


def test_truncated_las_streams_to_format_error(tmp_path: Path) -> None:
    from splatdeform.edit.config import load_edit
    from splatdeform.edit.stream import run_stream
    from splatdeform.errors import FormatError

    raw = shared_file("lidar/vegetation_1_3.las").read_bytes()
    (tmp_path / "t.las").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "e.yaml").write_text(yaml.safe_dump({
        "input": "t.las", "output": "o.las",
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                    "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"translate": [0, 0, 0.2]}}}))
    with pytest.raises(FormatError, match="t.las"):
        run_stream(load_edit(tmp_path / "e.yaml"), tmp_path, chunk=1000, quiet=True)
    assert not (tmp_path / "o.las").exists()
