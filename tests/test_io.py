"""Loading and saving: lossless PLY round trips of every real file, kinds, byte orders, tristrips,
extra elements, atomic saves, generated scans through every supported format, normal estimation.

Real files come from ../shared/data (skipped when absent); everything written goes to tmp_path.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import plyfile
import pytest
from conftest import shared_file

import splatdeform.io as sio
from data_tools.synth import bumpy_bar, sphere
from splatdeform.deform.normals import estimate_normals
from splatdeform.errors import InputError
from splatdeform.io import load, open3d_io, pcd, ply, save
from splatdeform.model import PlySource, PointModel

# file -> kind the loader must recognise (see ../shared/data/README.md)
REAL_FILES = {
    "scans/bunny.ply": "mesh",
    "scans/bunny_res2.ply": "mesh",
    "scans/armadillo_oriented.ply": "oriented_cloud",
    "scans/head_surfels.ply": "surfel_radius",
    "scans/lidar_terrain_522k.ply": "cloud",
    "splats/guitar_3dgs_sh0.ply": "gaussians",
    "splats/tile_3dgs_sh3.ply": "gaussians",
    "edge_cases/horse_big_endian.ply": "mesh",
    "edge_cases/igea_tristrips.ply": "mesh",
    "edge_cases/pepper_extra_elements.ply": "mesh",
}
# format as written in the file header: (text, byte order)
REAL_FORMATS = {
    "scans/bunny.ply": (True, None),
    "scans/bunny_res2.ply": (True, None),
    "scans/armadillo_oriented.ply": (True, None),
    "scans/head_surfels.ply": (True, None),
    "scans/lidar_terrain_522k.ply": (False, "<"),
    "splats/guitar_3dgs_sh0.ply": (False, "<"),
    "splats/tile_3dgs_sh3.ply": (False, "<"),
    "edge_cases/horse_big_endian.ply": (False, ">"),
    "edge_cases/igea_tristrips.ply": (False, "<"),
    "edge_cases/pepper_extra_elements.ply": (False, "<"),
}
# vertex (and face) counts from the README
REAL_COUNTS = {
    "scans/bunny.ply": (35947, 69451),
    "scans/bunny_res2.ply": (8171, 16301),
    "scans/armadillo_oriented.ply": (38294, 0),
    "scans/head_surfels.ply": (45428, 0),
    "scans/lidar_terrain_522k.ply": (522674, 0),
    "splats/guitar_3dgs_sh0.ply": (90854, 0),
    "splats/tile_3dgs_sh3.ply": (6831, 0),
    "edge_cases/horse_big_endian.ply": (48485, 96966),
    "edge_cases/pepper_extra_elements.ply": (14980, 29956),
    "edge_cases/igea_tristrips.ply": (134345, None),
}


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _dtype(x: np.ndarray, native: bool) -> str:
    return (x.dtype.newbyteorder("=") if native else x.dtype).str


def assert_columns_equal(a: np.ndarray, b: np.ndarray, what: str, native: bool = False) -> None:
    """Equal values and dtypes (native: byte order ignored); object (list) columns compared
    row by row."""
    assert len(a) == len(b), what
    if a.dtype == object or b.dtype == object:
        assert a.dtype == b.dtype == object, what
        if len(a) == 0:
            return
        la = np.fromiter((len(r) for r in a), dtype=np.int64, count=len(a))
        lb = np.fromiter((len(r) for r in b), dtype=np.int64, count=len(b))
        np.testing.assert_array_equal(la, lb, err_msg=f"{what}: list lengths")
        assert ({_dtype(np.asarray(r), native) for r in a}
                == {_dtype(np.asarray(r), native) for r in b}), what
        # concatenating rows with identical lengths is equivalent to comparing row by row
        np.testing.assert_array_equal(np.concatenate(list(a)), np.concatenate(list(b)),
                                      err_msg=f"{what}: list values")
    else:
        assert _dtype(a, native) == _dtype(b, native), f"{what}: {a.dtype} != {b.dtype}"
        np.testing.assert_array_equal(a, b, err_msg=what)


def assert_sources_equal(a: PlySource, b: PlySource, *, same_format: bool = True) -> None:
    assert [e.name for e in a.elements] == [e.name for e in b.elements]
    assert a.comments == b.comments
    assert a.obj_info == b.obj_info
    if same_format:
        assert a.text == b.text
        if not a.text:
            assert a.byte_order == b.byte_order
    for ea, eb in zip(a.elements, b.elements, strict=True):
        assert ea.count == eb.count, ea.name
        assert ea.properties == eb.properties, ea.name  # names, dtypes, type spellings, lists
        assert ea.data.dtype.names == eb.data.dtype.names, ea.name
        for name in ea.data.dtype.names:
            # the byte order may change with the format: then compare native types and values
            assert_columns_equal(ea.data[name], eb.data[name], f"{ea.name}.{name}",
                                 native=not same_format)


def assert_geometry_equal(a: PointModel, b: PointModel) -> None:
    assert a.kind == b.kind
    for name in ("positions", "normals", "colors", "radius", "axes", "faces"):
        va, vb = getattr(a, name), getattr(b, name)
        assert (va is None) == (vb is None), name
        if va is not None:
            np.testing.assert_array_equal(va, vb, err_msg=name)
    assert (a.gaussians is None) == (b.gaussians is None)
    if a.gaussians is not None:
        for name in ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
            va, vb = getattr(a.gaussians, name), getattr(b.gaussians, name)
            assert (va is None) == (vb is None), name
            if va is not None:
                np.testing.assert_array_equal(va, vb, err_msg=name)


# --------------------------------------------------------------------------------------------
# real files


@pytest.mark.parametrize("rel", list(REAL_FILES))
def test_real_file_round_trip(rel: str, tmp_path: Path) -> None:
    src = shared_file(rel)
    before = sha256(src)
    model = load(src)
    text, byte_order = REAL_FORMATS[rel]
    assert model.kind == REAL_FILES[rel]
    assert model.source.text == text
    if not text:
        assert model.source.byte_order == byte_order
    n_vertices, n_faces = REAL_COUNTS[rel]
    assert model.n_points == n_vertices
    if n_faces is not None:
        assert model.n_faces == n_faces
    assert np.isfinite(model.positions).all()
    assert model.path == str(src)

    out = save(model, tmp_path / src.name)
    again = load(out)
    assert_sources_equal(model.source, again.source)
    assert_geometry_equal(model, again)
    if not text:  # binary: every array identical, so the file is too
        assert out.read_bytes() == src.read_bytes()
    else:  # ascii: the saved header is the original one (same lines, same order)
        hdr = src.read_bytes().split(b"end_header")[0].split(b"\n")
        hdr_out = out.read_bytes().split(b"end_header")[0].split(b"\n")
        assert [ln.strip() for ln in hdr] == [ln.strip() for ln in hdr_out]
    assert sorted(p.name for p in tmp_path.iterdir()) == [src.name]  # no temp files left
    assert sha256(src) == before  # the input is never modified


# lidar: 522k rows of plain floats, little to learn and slow as ascii; igea's single
# 373,830-entry tristrips row exercises the ascii writer's long list rows.
@pytest.mark.parametrize("rel", [r for r in REAL_FILES if r != "scans/lidar_terrain_522k.ply"])
def test_real_file_round_trip_other_encoding(rel: str, tmp_path: Path) -> None:
    """ascii -> binary and binary -> ascii keep every value and type."""
    src = shared_file(rel)
    model = load(src)
    text = not model.source.text
    out = save(model, tmp_path / src.name, text=text)
    again = load(out)
    assert again.source.text == text
    assert_sources_equal(model.source, again.source, same_format=False)
    assert_geometry_equal(model, again)


@pytest.mark.parametrize("rel", [
    "edge_cases/horse_big_endian.ply",
    "edge_cases/pepper_extra_elements.ply",
    "edge_cases/igea_tristrips.ply",
    "splats/tile_3dgs_sh3.ply",
    "scans/bunny_res2.ply",
])
def test_matches_plyfile(rel: str, tmp_path: Path) -> None:
    """Independent reading with plyfile: same elements and values, before and after a save."""
    src = shared_file(rel)
    model = load(src)
    out = save(model, tmp_path / src.name)
    for path in (src, out):
        ref = plyfile.PlyData.read(str(path))
        assert [e.name for e in ref.elements] == [e.name for e in model.source.elements]
        for el in ref.elements:
            ours = model.source.element(el.name)
            assert ours.count == len(el.data)
            for prop in el.properties:
                a, b = ours.data[prop.name], el.data[prop.name]
                if a.dtype == object:
                    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
                else:
                    np.testing.assert_array_equal(a, b)


def test_big_endian_horse_values() -> None:
    src = shared_file("edge_cases/horse_big_endian.ply")
    model = load(src)
    ref = plyfile.PlyData.read(str(src))
    v = ref["vertex"].data
    for i in (0, 1, 2, 1000, 24242, 48484):
        expected = np.array([v["x"][i], v["y"][i], v["z"][i]], dtype=np.float64)
        np.testing.assert_array_equal(model.positions[i], expected)
        np.testing.assert_array_equal(model.colors[i], [v["red"][i], v["green"][i], v["blue"][i]])
    # values are sane (a byte-swapped float would be astronomically large or tiny)
    assert model.diagonal() < 10 and model.diagonal() > 1e-3
    assert np.abs(model.positions).max() < 10
    faces = np.stack(ref["face"].data["vertex_indices"]).astype(np.int64)
    np.testing.assert_array_equal(model.faces, faces)
    assert model.source.byte_order == ">"


def test_igea_tristrips_faces() -> None:
    model = load(shared_file("edge_cases/igea_tristrips.ply"))
    assert model.source.element("face") is None
    assert model.kind == "mesh"
    n, f = model.n_points, model.n_faces
    assert 1.5 * n < f < 2.1 * n  # closed-ish triangle mesh: F ~ 2V
    assert model.faces.dtype.kind == "i"
    assert model.faces.min() >= 0 and model.faces.max() < n
    t = model.faces
    assert ((t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])).all()
    # almost every vertex is used
    assert len(np.unique(t)) > 0.95 * n
    # consistent winding from the strip alternation: a directed edge is (almost) never shared
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    key = edges[:, 0] * n + edges[:, 1]
    _, counts = np.unique(key, return_counts=True)
    assert (counts > 1).sum() < 0.001 * len(counts)


def _canonical(tris) -> np.ndarray:
    """Rotate each triangle to start at its smallest index (same winding), then sort rows."""
    t = np.asarray(tris, dtype=np.int64)
    shift = np.argmin(t, axis=1)
    t = np.stack([t[np.arange(len(t)), (shift + i) % 3] for i in range(3)], axis=1)
    return t[np.lexsort(t.T[::-1])]


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_tristrips_generated(fmt: str, tmp_path: Path) -> None:
    """Strip decoding: alternating winding, -1 restarts, degenerate triangles skipped."""
    strip = [0, 1, 2, 3, 4, -1, 5, 6, 7, -1, 2, 2, 3]
    header = (f"ply\nformat {fmt} 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
              "property float z\nelement tristrips 1\nproperty list int int vertex_indices\n"
              "end_header\n").encode()
    positions = np.arange(24, dtype=np.float32).reshape(8, 3)
    if fmt == "ascii":
        body = "".join(" ".join(map(str, p)) + "\n" for p in positions.tolist())
        body += " ".join(map(str, [len(strip), *strip])) + "\n"
        raw = header + body.encode()
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        raw = (header + positions.astype(bo + "f4").tobytes()
               + np.array([len(strip), *strip], dtype=bo + "i4").tobytes())
    path = tmp_path / "strips.ply"
    path.write_bytes(raw)
    model = load(path)
    assert model.kind == "mesh"
    expected = _canonical([[0, 1, 2], [2, 1, 3], [2, 3, 4], [5, 6, 7]])
    np.testing.assert_array_equal(_canonical(model.faces), expected)
    np.testing.assert_array_equal(model.positions, positions)
    for text in (False, True):
        again = load(save(model, tmp_path / f"out_{text}.ply", text=text))
        np.testing.assert_array_equal(_canonical(again.faces), expected)
        assert_sources_equal(model.source, again.source, same_format=False)


def test_pepper_extra_elements_kept(tmp_path: Path) -> None:
    src = shared_file("edge_cases/pepper_extra_elements.ply")
    model = load(src)
    names = [e.name for e in model.source.elements]
    assert names == ["vertex", "face", "multi_texture_vertex", "multi_texture_face"]
    mtf = model.source.element("multi_texture_face")
    assert mtf.count == 29956
    assert [p.name for p in mtf.properties] == ["tx", "tn", "texture_vertex_indices"]
    assert mtf.property("tn").type_name == "uint"
    out = save(model, tmp_path / "pepper.ply")
    ref = plyfile.PlyData.read(str(out))
    assert [e.name for e in ref.elements] == names
    np.testing.assert_array_equal(ref["multi_texture_vertex"].data["u"],
                                  model.source.element("multi_texture_vertex").data["u"])
    assert model.source.comments == ["File exported by Artec Group 3D Scanning Solutions",
                                     "www.artec-group.com"]


def test_lidar_522k_loads() -> None:
    src = shared_file("scans/lidar_terrain_522k.ply")
    model = load(src)
    assert model.n_points == 522674
    assert model.kind == "cloud" and model.normals is None and model.faces is None
    ref = plyfile.PlyData.read(str(src))["vertex"].data
    lo, hi = model.bbox()
    for i, axis in enumerate("xyz"):
        assert lo[i] == float(ref[axis].min()) and hi[i] == float(ref[axis].max())
    assert 5.0e6 < lo[1] < hi[1] < 6.0e6  # UTM northing kept (not normalised on load)


def test_save_refuses_input_path(tmp_path: Path) -> None:
    src = shared_file("scans/bunny_res2.ply")
    model = load(src)
    before = sha256(src)
    with pytest.raises(InputError, match="bunny_res2"):
        save(model, src)
    # another spelling of the same file: relative path and symlink
    rel = os.path.relpath(src, Path.cwd())
    with pytest.raises(InputError):
        save(model, rel)
    link = tmp_path / "link.ply"
    link.symlink_to(src)
    with pytest.raises(InputError):
        save(model, link)
    assert sha256(src) == before
    # writable input (generated): still refused, and untouched
    gen = save(sphere(200, seed=3), tmp_path / "gen.ply")
    h = sha256(gen)
    m = load(gen)
    with pytest.raises(InputError, match="gen.ply"):
        save(m, gen)
    with pytest.raises(InputError):
        save(m, tmp_path / "." / "gen.ply")
    assert sha256(gen) == h
    # the model is still usable for a save elsewhere
    assert save(m, tmp_path / "other.ply").is_file()


# --------------------------------------------------------------------------------------------
# atomic saves


def _partial_ply_writer(model, stream, *, text=None):
    stream.write(b"ply\nformat ascii 1.0\nelement vertex 100\n")
    stream.flush()
    raise RuntimeError("disk on fire")


def _partial_o3d_writer(model, path):
    Path(path).write_bytes(b"0 0 0\n1 1 1\n")
    raise RuntimeError("disk on fire")


def _partial_stream_writer(model, path, stream):
    stream.write(b"# .PCD v0.7\nVERSION 0.7\n")
    raise RuntimeError("disk on fire")


@pytest.mark.parametrize("ext", [".ply", ".xyz", ".pcd"])
def test_failed_save_leaves_nothing(ext: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(ply, "write_model", _partial_ply_writer)
    monkeypatch.setattr(open3d_io, "write_model", _partial_o3d_writer)
    monkeypatch.setattr(pcd, "write_model", _partial_stream_writer)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(RuntimeError, match="disk on fire"):
        save(sphere(100, seed=0), out_dir / f"s{ext}")
    assert list(out_dir.iterdir()) == []
    # an existing output is kept intact when the replacing save fails
    old = out_dir / f"old{ext}"
    old.write_bytes(b"previous contents")
    with pytest.raises(RuntimeError):
        save(sphere(100, seed=0), old)
    assert old.read_bytes() == b"previous contents"
    assert [p.name for p in out_dir.iterdir()] == [old.name]


def test_save_into_new_folder_and_permissions(tmp_path: Path) -> None:
    out = save(sphere(100, seed=0), tmp_path / "a" / "b" / "s.ply")
    assert out.is_file()
    mask = os.umask(0o022)
    os.umask(mask)
    assert oct(out.stat().st_mode & 0o777) == oct(0o666 & ~mask)  # as open(out, 'w')
    assert sorted(p.name for p in out.parent.iterdir()) == ["s.ply"]


def test_save_to_directory_refused(tmp_path: Path) -> None:
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(InputError, match="d.ply"):
        save(sphere(100, seed=0), tmp_path / "d.ply")


def test_save_unknown_extension_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="obj"):
        save(sphere(100, seed=0), tmp_path / "s.obj")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# generated models


def _generated() -> list[tuple[str, PointModel]]:
    return [("bar", bumpy_bar(3000, seed=1)), ("sphere", sphere(1500, seed=2))]


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("name", ["bar", "sphere"])
def test_generated_ply_round_trip(name: str, text: bool, tmp_path: Path) -> None:
    model = dict(_generated())[name]
    out = save(model, tmp_path / f"{name}.ply", text=text)
    again = load(out)
    assert again.source.text == text
    assert again.kind == "surfel_radius"
    assert again.n_points == model.n_points
    np.testing.assert_array_equal(again.positions, model.positions)  # written as double
    np.testing.assert_allclose(again.normals, model.normals, atol=1e-7)  # float32
    np.testing.assert_array_equal(again.colors, model.colors)
    np.testing.assert_allclose(again.radius, model.radius, rtol=1e-7)
    # and a second round trip through the loaded source is exact
    out2 = save(again, tmp_path / f"{name}_2.ply")
    if not text:
        assert out2.read_bytes() == out.read_bytes()
    assert_sources_equal(again.source, load(out2).source)


@pytest.mark.parametrize("text", [False, True])
def test_generated_mesh_round_trip(text: bool, tmp_path: Path) -> None:
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    model = PointModel(positions=positions, faces=faces, kind="mesh")
    again = load(save(model, tmp_path / "tet.ply", text=text))
    assert again.kind == "mesh"
    np.testing.assert_array_equal(again.faces, faces)
    np.testing.assert_array_equal(again.positions, positions)


# ext -> (position tolerance relative to the coordinates' magnitude, holds normals, colors)
O3D_FORMATS = {
    ".pcd": (1e-6, True, True),  # float32 binary
    ".xyzn": (1e-9, True, False),  # %.10f ascii
    ".xyz": (1e-9, False, False),
    ".pts": (1e-9, False, True),
}


@pytest.mark.parametrize("ext", list(O3D_FORMATS))
@pytest.mark.parametrize("name", ["bar", "sphere"])
def test_generated_open3d_round_trip(name: str, ext: str, tmp_path: Path) -> None:
    model = dict(_generated())[name]
    tol, has_normals, has_colors = O3D_FORMATS[ext]
    out = save(model, tmp_path / f"{name}{ext}")
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    again = load(out)
    assert again.path == str(out)
    assert again.n_points == model.n_points
    scale = np.abs(model.positions).max()
    np.testing.assert_allclose(again.positions, model.positions, rtol=0, atol=tol * scale)
    if has_normals:
        assert again.normals is not None and again.kind == "oriented_cloud"
        np.testing.assert_allclose(again.normals, model.normals, rtol=0, atol=tol)
    else:
        assert again.normals is None and again.kind == "cloud"
    if has_colors:
        np.testing.assert_array_equal(again.colors, model.colors)


def test_open3d_to_ply(tmp_path: Path) -> None:
    """A model read from .xyzn (no PLY source) saves as PLY with its normals."""
    model = sphere(500, seed=4)
    cloud = load(save(model, tmp_path / "s.xyzn"))
    again = load(save(cloud, tmp_path / "s.ply"))
    assert again.kind == "oriented_cloud"
    np.testing.assert_array_equal(again.positions, cloud.positions)
    np.testing.assert_allclose(again.normals, cloud.normals, atol=1e-7)


def test_registry_lists_all_formats() -> None:
    assert set(sio.SUPPORTED) == {".ply", ".compressed.ply", ".splat", ".ksplat", ".spz", ".glb",
                                  ".gltf",
                                  ".pcd", ".xyz", ".xyzn", ".pts", ".las", ".laz", ".sog",
                                  "meta.json", ".e57"}


# --------------------------------------------------------------------------------------------
# normal estimation


def _bare_sphere(n: int, seed: int) -> tuple[PointModel, np.ndarray]:
    s = sphere(n, radius=2.0, seed=seed)
    truth = s.normals.copy()
    # shift far from the origin: estimation must not lose precision or orientation to offsets
    return PointModel(positions=s.positions + [1000.0, -50.0, 3.0], kind="cloud"), truth


def _angles_deg(normals: np.ndarray, truth: np.ndarray) -> np.ndarray:
    cos = np.clip(np.abs(np.einsum("ij,ij->i", normals, truth)), 0, 1)
    return np.degrees(np.arccos(cos))


def test_estimate_normals_outward() -> None:
    model, truth = _bare_sphere(4000, seed=5)
    est = estimate_normals(model, k=16, orient="outward")
    assert model.normals is None  # the input is not modified
    assert est.kind == "oriented_cloud"
    np.testing.assert_array_equal(est.positions, model.positions)
    np.testing.assert_allclose(np.linalg.norm(est.normals, axis=1), 1.0, atol=1e-9)
    ang = _angles_deg(est.normals, truth)
    assert np.percentile(ang, 99) < 5 and ang.max() < 10
    assert (np.einsum("ij,ij->i", est.normals, truth) > 0).all()


def test_estimate_normals_consistent() -> None:
    model, truth = _bare_sphere(4000, seed=6)
    est = estimate_normals(model, k=16, orient="consistent")
    np.testing.assert_allclose(np.linalg.norm(est.normals, axis=1), 1.0, atol=1e-9)
    ang = _angles_deg(est.normals, truth)
    assert np.percentile(ang, 99) < 5 and ang.max() < 10
    sign = np.sign(np.einsum("ij,ij->i", est.normals, truth))
    assert (sign == 1).all() or (sign == -1).all()


def test_estimate_normals_plus_z() -> None:
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 100, size=(3000, 2))
    z = 0.05 * xy[:, 0] + 2.0 * np.sin(xy[:, 1] / 20)
    model = PointModel(positions=np.column_stack([xy + [5.0e5, 5.4e6], z]), kind="cloud")
    est = estimate_normals(model, k=12, orient="+z")
    assert (est.normals[:, 2] > 0).all()
    truth = np.column_stack([-0.05 * np.ones(len(z)), -0.1 * np.cos(xy[:, 1] / 20),
                             np.ones(len(z))])
    truth /= np.linalg.norm(truth, axis=1, keepdims=True)
    assert np.percentile(_angles_deg(est.normals, truth), 99) < 5


def test_estimate_normals_bad_arguments() -> None:
    model, _ = _bare_sphere(100, seed=8)
    with pytest.raises(InputError, match="k"):
        estimate_normals(model, k=2)
    with pytest.raises(InputError, match="orient"):
        estimate_normals(model, orient="inward")
