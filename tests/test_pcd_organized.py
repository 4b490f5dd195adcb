"""Organized PCD clouds keep their grid, and ascii packed colours read the same in Open3D and
pypcd4 (issue 47 item 2).

PCL's own organized RGB-D frame (640x480, NaN where the camera saw no depth) loads as its
finite points; the holes are carried in place (never deformed, selected or rendered) and a save
or a deform writes WIDTH, HEIGHT and every hole back where it was.
"""

from __future__ import annotations

import io

import numpy as np
import open3d as o3d
import pypcd4  # (a dev dependency: a missing one fails, never skips)
import yaml
from conftest import shared_file

from splatdeform.cli import main
from splatdeform.io import load, pcd, save
from splatdeform.io.options import writing
from splatdeform.model import PointModel, classify

OSD = "pcd/osd_learn0_organized.pcd"


def _bits(column: np.ndarray) -> np.ndarray:
    return column.view(np.uint32) if column.dtype.kind == "f" else column


def _holes(source: pcd.PcdSource) -> np.ndarray:
    return ~np.isfinite(pcd.xyz_of(source.data)).all(axis=1)


def test_organized_frame_loads_with_its_grid(capsys) -> None:
    src = shared_file(OSD)
    whole, _ = pcd.read_source(src)
    holes = _holes(whole)
    model = load(src)
    assert model.n_points == int((~holes).sum()) == 182_292
    assert np.isfinite(model.positions).all()
    assert np.array_equal(model.source.finite, ~holes)
    assert (model.source.width, model.source.height) == (640, 480)
    # the fields of the points, in grid order (selectors and info see these rows)
    vertex = model.source.element("vertex")
    assert vertex.count == model.n_points
    assert np.array_equal(vertex.data["label"], whole.data["label"][~holes])
    assert main(["info", str(src)]) == 0
    out = capsys.readouterr().out
    assert "organized 640x480 with 182,292 finite" in out
    assert "points:   182,292" in out


def test_plain_save_writes_every_cell_back(tmp_path) -> None:
    src = shared_file(OSD)
    whole, _ = pcd.read_source(src)
    for encoding in ("binary_compressed", "binary", "ascii"):
        out = tmp_path / f"back_{encoding}.pcd"
        with writing(pcd_data=encoding):
            save(load(src), out)
        back, _ = pcd.read_source(out)
        assert (back.width, back.height) == (640, 480), encoding
        for name in whole.fields:
            assert np.array_equal(_bits(back.data[name]), _bits(whole.data[name])), \
                (encoding, name)


def test_deform_keeps_the_grid_and_the_holes(tmp_path) -> None:
    src = shared_file(OSD)
    out = tmp_path / "bent.pcd"
    cfg = {"input": str(src), "output": str(out),
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                       "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"translate": [0, 0.2, 0]}},
           "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["deform", str(tmp_path / "e.yaml"), "--quiet"]) == 0
    before, _ = pcd.read_source(src)
    after, _ = pcd.read_source(out)
    assert (after.width, after.height) == (640, 480)
    holes = _holes(before)
    assert np.array_equal(_holes(after), holes)           # holes at the same cells
    for name in before.fields:                             # holes untouched, every field
        assert np.array_equal(_bits(after.data[name][holes]), _bits(before.data[name][holes]))
        if name not in "xyz":
            assert np.array_equal(_bits(after.data[name]), _bits(before.data[name])), name
    moved = np.abs(pcd.xyz_of(after.data) - pcd.xyz_of(before.data))[~holes]
    assert moved.max() > 0.05 and np.isfinite(moved).all()
    # Open3D reads the same grid (its NaN cells included)
    cloud = o3d.io.read_point_cloud(str(out))
    assert len(cloud.points) == 640 * 480


def test_convert_turns_the_points_not_the_holes(tmp_path) -> None:
    src = shared_file(OSD)
    out = tmp_path / "turned.pcd"
    assert main(["convert", str(src), str(out), "--rotate-euler=0,0,90"]) == 0
    before, _ = pcd.read_source(src)
    after, _ = pcd.read_source(out)
    holes = _holes(before)
    assert np.array_equal(_holes(after), holes)
    a, b = pcd.xyz_of(before.data)[~holes], pcd.xyz_of(after.data)[~holes]
    assert np.abs(b[:, 0] + a[:, 1]).max() < 1e-5   # splat-transform's frame (x = -y)


def _coloured(n: int = 500, seed: int = 3) -> PointModel:
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    colors[:4] = [[255, 255, 255], [0, 0, 0], [255, 0, 0], [127, 128, 1]]
    return PointModel(positions=rng.normal(size=(n, 3)), colors=colors,
                      kind=classify(has_faces=False, has_normals=False, has_radius=False,
                                    has_axes=False, has_gaussians=False))


def test_ascii_rgb_reads_the_same_in_open3d_and_pypcd4(tmp_path) -> None:
    model = _coloured()
    for start in ("ply", "pcd"):   # a new PCD source, and a binary PCD's source
        if start == "pcd":
            save(model, tmp_path / "bin.pcd")
            model = load(tmp_path / "bin.pcd")
        out = tmp_path / f"ascii_{start}.pcd"
        with writing(pcd_data="ascii"):
            save(model, out)
        head = out.read_bytes()[:400]
        assert b"DATA ascii" in head and b"TYPE F F F F" in head
        cloud = o3d.io.read_point_cloud(str(out))
        theirs = np.rint(np.asarray(cloud.colors) * 255).astype(np.uint8)
        assert np.array_equal(theirs, model.colors), start
        array = pypcd4.PointCloud.from_path(str(out)).numpy(("rgb",))[:, 0]
        bits = array.astype(np.float32).view(np.uint32)
        rgb = np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1)
        assert np.array_equal(rgb.astype(np.uint8), model.colors), start
        assert np.array_equal(load(out).colors, model.colors)


def test_ascii_rgba_with_nan_bits_is_declared_unsigned(tmp_path) -> None:
    """An rgba whose alpha byte makes its float a NaN cannot be written as float text: the
    field is declared TYPE U and its bits written as an integer, read back the same."""
    rng = np.random.default_rng(11)
    n = 200
    bits = (np.uint32(0xFF) << 24) | rng.integers(0, 1 << 24, n).astype(np.uint32)
    data = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "<f4")])
    for a in "xyz":
        data[a] = rng.normal(size=n)
    data["rgba"] = bits.view(np.float32)
    source = pcd.PcdSource(header=[("VERSION", "0.7")], fields=["x", "y", "z", "rgba"],
                           sizes=[4] * 4, types=["F"] * 4, counts=[1] * 4, width=n, height=1,
                           encoding="ascii", data=data)
    buf = io.BytesIO()
    pcd.write_source(source, buf)
    out = tmp_path / "rgba.pcd"
    out.write_bytes(buf.getvalue())
    assert b"TYPE F F F U" in buf.getvalue()
    back, _ = pcd.read_source(out)
    assert np.array_equal(back.data["rgba"].view(np.uint32), bits)
    theirs = pypcd4.PointCloud.from_path(str(out)).numpy(("rgba",))[:, 0]
    assert np.array_equal(theirs.astype(np.uint32), bits)
