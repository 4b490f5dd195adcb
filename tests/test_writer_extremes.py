"""Every writer at its extremes (issue 43 item 6): what we write, our own reader reads back, or
the write is refused with one line naming the output and the value that does not fit, and no
output is left. LAS scale and offset are held to the reader's own bound
(:func:`splatdeform.io.las_header.scale_offset_fault`, ``MAX_COORDINATE``); a PCD written from
another format widens to F 8 for values beyond float32, one read from PCD keeps its field types
and refuses a value they cannot hold; float32 writers refuse what would become inf; SPZ's 24-bit
and SOG's logarithmic positions refuse what they cannot quantise. Also ``convert --scale`` held
to the handle scales' bound, and writer warnings naming the output, never its temporary file."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file
from helpers import one_error_line, run_cli

from data_tools.synth import gaussian_bar, sphere
from splatdeform.errors import SplatdeformError
from splatdeform.io import extension_of, load, save
from splatdeform.io.splats import LossyWriteWarning
from splatdeform.model import MAX_COORDINATE

TILE = "splats/tile_3dgs_sh3.ply"
MAGNITUDES = (1e5, 1e9, 1e15, 3e38, 1e39)
CLOUD_FORMATS = (".ply", ".pcd", ".las", ".laz", ".xyz", ".pts")
SPLAT_FORMATS = (".ply", ".compressed.ply", ".splat", ".spz", ".sog", ".glb", ".gltf")
#: formats that keep a coordinate to float32 precision or better (the others quantise)
EXACTISH = {".ply", ".pcd", ".las", ".laz", ".xyz", ".pts", ".splat", ".glb", ".gltf"}


def _written_or_refused(model, out: Path, changed: np.ndarray | None = None) -> str:
    """Save ``model`` to ``out``: 'refused' (one line naming ``out``, nothing left) or 'read'
    (our reader reads it back, every coordinate finite; row 0 within float32 precision of
    ``changed`` for the formats in :data:`EXACTISH`)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LossyWriteWarning)
            warnings.simplefilter("ignore", UserWarning)
            save(model, out)
    except SplatdeformError as exc:
        text = str(exc)
        assert text.startswith(str(out)), text
        assert "\n" not in text and ".tmp" not in text, text
        assert not out.exists()
        return "refused"
    back = load(out)
    assert back.n_points == model.n_points
    assert np.isfinite(back.positions).all(), out
    if changed is not None and extension_of(out) in EXACTISH:
        assert np.allclose(back.positions[0], changed, rtol=1e-6, atol=0), \
            (out, back.positions[0], changed)
    return "read"


@pytest.mark.parametrize("ext", CLOUD_FORMATS)
def test_cloud_writers_at_their_extremes(tmp_path, ext):
    outcomes = {}
    for mag in MAGNITUDES:
        model = sphere(300)
        far = np.array([mag, -mag, mag / 3])
        model.positions[0] = far
        outcomes[mag] = _written_or_refused(model, tmp_path / f"far_{mag:g}{ext}", far)
    if ext in (".las", ".laz"):   # the reader's own bound: 1e15 cannot be held with int32 steps
        assert outcomes == {1e5: "read", 1e9: "read", 1e15: "refused", 3e38: "refused",
                            1e39: "refused"}
    else:   # float64 text, a double PLY property, PCD F 8
        assert set(outcomes.values()) == {"read"}, outcomes


@pytest.mark.parametrize("ext", SPLAT_FORMATS)
@pytest.mark.parametrize("from_file", [False, True], ids=["new", "float32-source"])
def test_splat_writers_at_their_extremes(tmp_path, ext, from_file):
    # a real 3DGS PLY's float32 columns, or a new model (a PLY of it: double positions)
    base = load(shared_file(TILE)) if from_file else gaussian_bar(400, sh_degree=1, seed=43)
    outcomes = {}
    for mag in MAGNITUDES:
        model = base.copy()
        far = np.array([mag, -mag, mag / 3])
        model.positions[0] = far
        outcomes[mag] = _written_or_refused(model, tmp_path / f"far_{mag:g}{ext}", far)
    # 1e39 is beyond float32 everywhere but a new PLY (double): refused, never inf
    assert outcomes[1e39] == ("read" if ext == ".ply" and not from_file else "refused")
    assert outcomes[1e5] == "read"
    if ext == ".spz":   # 24-bit fixed point
        assert outcomes[1e9] == "refused"
    if ext == ".sog":   # ln(1 + |p|) up to 88
        assert outcomes[3e38] == "refused" and outcomes[1e15] == "read"


@pytest.mark.parametrize("ext", SPLAT_FORMATS)
def test_splat_attributes_at_their_extremes(tmp_path, ext):
    """Log scales whose exponent overflows float32 (stored linear by .splat and glTF), float32
    overflow in any attribute, huge SH and opacity values (clamped by the quantising formats,
    said by their lossy warning): refused or read back finite."""
    cases = {"scale_100": ("scale_log", 100.0), "scale_1e39": ("scale_log", 1e39),
             "scale_-100": ("scale_log", -100.0), "dc_1e5": ("sh_dc", 1e5),
             "rest_1e5": ("sh_rest", 1e5), "opacity_1e30": ("opacity", 1e30),
             "rotation_1e30": ("rotation", 1e30), "opacity_inf": ("opacity", np.inf)}
    for name, (field, value) in cases.items():
        model = gaussian_bar(300, sh_degree=1, seed=7)
        column = getattr(model.gaussians, field).astype(np.float64)
        column.reshape(len(column), -1)[0] = value
        setattr(model.gaussians, field, column)
        out = tmp_path / f"{name}{ext}"
        outcome = _written_or_refused(model, out)
        if outcome == "read":
            g = load(out).gaussians
            assert np.isfinite(g.scale_log).all() and np.isfinite(g.sh_dc).all(), (name, ext)
        if value == 1e39:
            assert outcome == "refused", (name, ext)


def test_convert_far_ply_to_las_is_refused_naming_the_output(tmp_path):
    far = sphere(200)
    far.positions[:] *= 1e39
    src = tmp_path / "far.ply"
    save(far, src)
    res = run_cli("convert", src, tmp_path / "out.las")
    line = one_error_line(res, needles=("out.las", "coordinates reach",
                                        f"beyond {MAX_COORDINATE:g}"))
    assert ".tmp" not in line
    assert not (tmp_path / "out.las").exists()
    # the same file to PCD keeps every value (F 8 columns)
    assert run_cli("convert", src, tmp_path / "out.pcd").returncode == 0
    assert b"SIZE 8 8 8" in (tmp_path / "out.pcd").read_bytes()[:300]
    assert np.array_equal(load(tmp_path / "out.pcd").positions, load(src).positions)


def test_pcd_source_types_hold_or_refuse(tmp_path):
    src = tmp_path / "in.pcd"
    save(sphere(100), src)                  # F 4 columns
    model = load(src)
    model.positions[5] = [1e39, 0, 0]
    out = tmp_path / "far.pcd"
    with pytest.raises(SplatdeformError, match=r"far.pcd: PCD field x value 1e\+39 does not fit"):
        save(model, out)
    assert not out.exists()
    model.positions[5] = [3e38, 0, 0]       # within float32: kept
    save(model, out)
    assert load(out).positions[5, 0] == np.float32(3e38)


def test_ply_float32_source_refuses_what_float32_cannot_hold(tmp_path):
    model = load(shared_file(TILE))
    assert model.source.element("vertex").data.dtype["x"] == np.float32
    model.positions[0, 1] = -1e39
    with pytest.raises(SplatdeformError, match=r"out.ply: PLY property y value -1e\+39"):
        save(model, tmp_path / "out.ply")


def test_convert_scale_bound_is_the_handles(tmp_path):
    src = tmp_path / "in.ply"
    save(sphere(100), src)
    for bad in ("1e-50", "1e7", "0", "-1", "nan"):
        one_error_line(run_cli("convert", src, tmp_path / "out.ply", "--scale", bad),
                       needles=("--scale", "1e-06", "1e+06"))
    assert not (tmp_path / "out.ply").exists()
    assert run_cli("convert", src, tmp_path / "out.ply", "--scale", "1e-6").returncode == 0
    assert np.allclose(load(tmp_path / "out.ply").positions, load(src).positions * 1e-6)


def test_las_offset_warning_names_the_output_not_its_temporary_file(tmp_path):
    src = tmp_path / "in.las"
    save(sphere(200), src)
    model = load(src)
    model.positions[:, 0] += 5e6   # beyond int32 steps of the input's offset: it moves
    out = tmp_path / "moved.las"
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        save(model, out)
    texts = [str(w.message) for w in said if "offset" in str(w.message)]
    assert texts and all(t.startswith(str(out)) and ".tmp" not in t for t in texts), texts
    assert np.allclose(load(out).positions, model.positions, atol=1e-6)
