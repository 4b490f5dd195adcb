"""Issue 32, items 6-8 (hostile inputs, round three): edits that would silently collapse a
region, ASCII PLY identity edits, selector numbers.

- A singular or nearly singular handle transform (matrix, scale; one handle or ``handles:``) is
  refused by ``deform`` (``--frames`` too), ``select`` and ``batch`` with one line naming the key;
  so is a curve whose control points (or moved points) coincide or are not finite.
- An identity edit of an ASCII PLY (deform with a zero translation, or load + save) reproduces
  the file byte for byte: CRLF, trailing spaces, a ``\\r`` on a comment line, blank lines after
  ``end_header``; changed rows keep the file's line end. A number beyond a property's range is
  refused with one line naming the file, line and property at any magnitude (1e39, 1e400).
- Selector numbers are finite, bounded and not booleans (a 5,000-digit ``min:`` was an internal
  ValueError, ``min: true`` was 1).

Every CLI case runs ``python -m splatdeform.cli`` in a subprocess with a timeout on a small
generated bar (``data_tools.synth``): exit 2, one error line naming the key, no traceback,
nothing written.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bar_edit
from helpers import one_error_line, snapshot, write_config
from helpers import run_cli as run

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.edit.config import check_handle_matrix, parse_edit
from splatdeform.errors import ConfigError, FormatError
from splatdeform.io import load, save
from splatdeform.io.ply import write_model
from splatdeform.io.ply_format import read_ply

N_BAR = 1200
SINGULAR = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]
NUM = "__NUM__"  # replaced by the number's YAML text after yaml.safe_dump


@pytest.fixture(scope="module")
def bar(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("round3") / "bar.ply"
    sd.save(bumpy_bar(N_BAR, seed=11), path)
    return path


def edit_of(bar: Path, **changes) -> dict:
    """The bar edit (relative units, a small translation) on ``bar``, keys replaced."""
    return {**bar_edit(input=str(bar), output="out/bent.ply"), **changes}


def write_text(folder: Path, cfg: dict, number: str | None = None) -> Path:
    """``cfg`` as YAML with the placeholder NUM replaced by ``number`` (YAML text that
    yaml.safe_dump cannot write, e.g. a 5,000-digit integer)."""
    text = yaml.safe_dump(cfg)
    if number is not None:
        assert NUM in text
        text = text.replace(f"'{NUM}'", number).replace(NUM, number)
    return write_config(folder, text)


def refused(folder: Path, config: Path, needles, *args, command: str = "deform") -> str:
    before = snapshot(folder)
    line = one_error_line(run(command, config, *args, cwd=folder), 2, needles)
    assert snapshot(folder) == before, "a refused edit wrote files"
    return line


# ---------------------------------------------------------------- 6. singular transforms

HANDLE_CASES = {
    # name: (handle entry, key needle)
    "zero_matrix": ({"matrix": SINGULAR}, "handle.matrix"),
    "rank_two_matrix": ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0], [0, 0, 0, 1]]},
                        "handle.matrix"),
    "tiny_singular_value": ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1e-7, 0],
                                        [0, 0, 0, 1]]}, "handle.matrix"),
    "ill_conditioned": ({"matrix": [[1e5, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1e-5, 0],
                                    [0, 0, 0, 1]]}, "handle.matrix"),
    "scale_ratio": ({"transform": {"scale": [1e6, 1, 1e-6]}}, "handle.transform.scale"),
    "tiny_scale": ({"transform": {"scale": 1e-7}}, "handle.transform.scale"),
    "scale_zero_with_rotation": ({"transform": {"scale": [1, 0, 1],
                                                "rotate": {"axis": [1, 1, 0], "degrees": 30}}},
                                 "handle.transform.scale"),
}


@pytest.mark.parametrize("name", sorted(HANDLE_CASES))
def test_deform_refuses_a_collapsing_handle(tmp_path, bar, name):
    handle, key = HANDLE_CASES[name]
    cfg = write_config(tmp_path, edit_of(bar, handle=handle))
    refused(tmp_path, cfg, [key, "edit.yaml"])


def test_matrix_with_a_non_finite_entry_is_refused(tmp_path, bar):
    cfg = edit_of(bar, handle={"matrix": [[NUM, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                          [0, 0, 0, 1]]})
    refused(tmp_path, write_text(tmp_path, cfg, ".nan"), ["handle.matrix[0][0]", "finite"])


def test_frames_and_select_refuse_it_too(tmp_path, bar):
    cfg = write_config(tmp_path, edit_of(bar, handle={"matrix": SINGULAR}))
    refused(tmp_path, cfg, ["handle.matrix", "singular"], "--render",
            tmp_path / "anim.gif", "--frames", "4")
    refused(tmp_path, cfg, ["handle.matrix", "singular"], "-o", tmp_path / "preview.png",
            command="select")


def test_multi_handle_names_the_entry(tmp_path, bar):
    edit = edit_of(bar)
    regions = edit.pop("regions")
    edit.pop("handle")
    edit["regions"] = {"units": "relative", "fixed": regions["fixed"]}
    edit["handles"] = [
        {"region": [{"box": {"min": [0.75, 0, 0], "max": [0.85, 1, 1]}}],
         "transform": {"translate": [0, 0.1, 0]}},
        {"region": [{"box": {"min": [0.9, 0, 0], "max": [1, 1, 1]}}], "matrix": SINGULAR}]
    refused(tmp_path, write_config(tmp_path, edit), ["handles[1].matrix", "singular"])


def test_check_handle_matrix_is_public():
    check_handle_matrix(np.eye(4), "handle.matrix")
    rotation = np.eye(4)
    rotation[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    check_handle_matrix(rotation * [[2], [2], [2], [1]], "handle.matrix")  # scaled rotation
    check_handle_matrix(np.diag([-1.0, 1, 1, 1]), "handle.matrix")  # a mirror is invertible
    for bad in (np.diag([0.0, 1, 1, 1]), np.diag([1.0, 1, np.nan, 1]),
                np.diag([1e-7, 1, 1, 1]), np.diag([1e4, 1, 1e-6, 1])):
        with pytest.raises(ConfigError) as err:
            check_handle_matrix(bad, "handles[2].matrix")
        assert str(err.value).startswith("handles[2].matrix: ")
    with pytest.raises(ConfigError):
        check_handle_matrix(np.full((4, 4), 1.0), "handle.matrix")  # last row not affine


def test_the_config_layer_refuses_it_for_every_entry_point(bar):
    """The editor loads configs through parse_edit: it gets the same refusal."""
    with pytest.raises(ConfigError) as err:
        parse_edit(edit_of(bar, handle={"matrix": SINGULAR}), "x.yaml")
    assert str(err.value).startswith("x.yaml: handle.matrix: singular")


def curve_edit(bar: Path, control: list, moved: list) -> dict:
    return {"input": str(bar), "output": "out/curved.ply",
            "regions": {"units": "model",
                        "fixed": [{"box": {"min": [-1, -1, -1], "max": [0.6, 1, 1]}},
                                  {"box": {"min": [3.4, -1, -1], "max": [5, 1, 1]}}]},
            "curve": {"control_points": control, "moved_to": moved, "degree": 2,
                      "capture_radius": 0.12},
            "fit": {"tolerance": 1e-3}, "backend": "numpy"}


CONTROL = [[1.2, 0.5, 0], [1.7, 0.5, 0], [2.3, 0.5, 0], [2.8, 0.5, 0]]
MOVED = [[1.2, 0.5, 0], [1.7, 0.85, 0], [2.3, 0.85, 0], [2.8, 0.5, 0]]


def test_curve_with_coincident_moved_points_is_refused(tmp_path, bar):
    moved = [p[:] for p in MOVED]
    moved[2] = moved[1][:]  # two moved points at one place: the band between them collapses
    cfg = write_config(tmp_path, curve_edit(bar, CONTROL, moved))
    refused(tmp_path, cfg, ["curve.moved_to", "points 1 and 2", "diagonal"])


def test_curve_with_coincident_control_points_is_refused(tmp_path, bar):
    control = [p[:] for p in CONTROL]
    control[3] = [control[0][0] + 1e-12, *control[0][1:]]
    cfg = write_config(tmp_path, curve_edit(bar, control, MOVED))
    refused(tmp_path, cfg, ["curve.control_points", "points 0 and 3"])
    refused(tmp_path, cfg, ["curve.control_points"], command="select")


def test_curve_with_a_non_finite_moved_point_is_refused(tmp_path, bar):
    moved = [p[:] for p in MOVED]
    moved[1][1] = NUM
    cfg = write_text(tmp_path, curve_edit(bar, CONTROL, moved), "-.inf")
    refused(tmp_path, cfg, ["curve.moved_to[1][1]", "finite"])


# batch: the singular matrix in the edit, and in an override

def _batch(tmp_path: Path, bar: Path, **keys) -> Path:
    scans = tmp_path / "scans"
    scans.mkdir(exist_ok=True)
    (scans / "bar.ply").write_bytes(bar.read_bytes())
    edit = bar_edit({"translate": [0, 0.1, 0]}, fit={"tolerance": 1e-3, "max_centers": 200})
    data = {"scans": "scans", "output_dir": "out", "edit": edit, **keys}
    if "edit" in keys:
        data["edit"] = {**edit, **keys["edit"]}
    return write_config(tmp_path, data, "batch.yaml")


def test_batch_refuses_a_singular_matrix(tmp_path, bar):
    cfg = _batch(tmp_path, bar, edit={"handle": {"matrix": SINGULAR}})
    refused(tmp_path, cfg, ["edit.handle.matrix", "singular"], "--workers", "1",
            command="batch")
    assert not (tmp_path / "out").exists()


def test_batch_refuses_a_singular_override(tmp_path, bar):
    cfg = _batch(tmp_path, bar, overrides=[{"match": "*.ply",
                                            "edit": {"handle": {"matrix": SINGULAR}}}])
    refused(tmp_path, cfg, ["overrides[0].edit.handle.matrix", "singular"], "--workers", "1",
            command="batch")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- 7. ascii PLY

def ascii_bar(path: Path, *, crlf: bool = True, extras: bool = True) -> bytes:
    """The bar as an ascii PLY (CRLF line ends); with ``extras`` also trailing spaces on some
    rows, a comment ending in \\r, blank lines after end_header and between rows."""
    buf = io.BytesIO()
    write_model(bumpy_bar(N_BAR, seed=11), buf, text=True)
    lines = buf.getvalue().split(b"\n")[:-1]
    if extras:
        lines.insert(2, b"comment made by hand  \r")
        at = lines.index(b"end_header") + 1
        lines[at:at] = [b"", b"  "]
        for i in range(at + 5, len(lines), 97):
            lines[i] += b"  "
        lines.insert(at + 40, b"")
    data = b"\n".join(lines) + b"\n"
    if crlf:
        data = b"\n".join(lines).replace(b"\n", b"\r\n") + b"\r\n"
    path.write_bytes(data)
    return data


@pytest.mark.parametrize("extras", [False, True])
def test_identity_deform_of_a_crlf_ascii_ply_is_byte_identical(tmp_path, extras):
    data = ascii_bar(tmp_path / "crlf.ply", extras=extras)
    cfg = write_config(tmp_path, bar_edit({"translate": [0, 0, 0]}, input="crlf.ply",
                                          output="out/same.ply"))
    res = run("deform", cfg, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    out = (tmp_path / "out" / "same.ply").read_bytes()
    assert len(out) == len(data)
    assert out == data


@pytest.mark.parametrize("crlf", [False, True])
def test_load_save_keeps_every_byte(tmp_path, crlf):
    data = ascii_bar(tmp_path / "in.ply", crlf=crlf)
    save(load(tmp_path / "in.ply"), tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == data


def test_odd_spacing_and_no_final_newline_are_kept(tmp_path):
    data = (b"ply\r\nformat ascii 1.0\r\ncomment a\r\r\nelement vertex 3\r\nproperty float x\r\n"
            b"property float y\r\nproperty float z \r\nelement face 1\r\n"
            b"property list uchar int vertex_indices\r\nend_header\r\n\r\n \t\r\n"
            b"  1 2 3  \r\n4\t5 6 \r\n\r\n7 8 9\r\n3 0 1 2")
    (tmp_path / "odd.ply").write_bytes(data)
    save(load(tmp_path / "odd.ply"), tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == data


def test_changed_rows_keep_the_files_line_end(tmp_path):
    data = ascii_bar(tmp_path / "in.ply")
    model = load(tmp_path / "in.ply")
    model.positions[::50, 1] += 0.25
    save(model, tmp_path / "out.ply")
    out = (tmp_path / "out.ply").read_bytes()
    assert out.count(b"\r\n") == data.count(b"\r\n")
    assert out.count(b"\n") == out.count(b"\r\n")
    before, after = data.split(b"\r\n"), out.split(b"\r\n")
    changed = [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b]
    assert len(changed) == len(range(0, N_BAR, 50))
    back = load(tmp_path / "out.ply")
    np.testing.assert_array_equal(back.positions.astype(np.float32),
                                  model.positions.astype(np.float32))


def test_a_new_property_is_written_in_the_files_line_end(tmp_path):
    data = (b"ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty float x\r\n"
            b"property float y\r\nproperty float z\r\nend_header\r\n1 2 3\r\n4 5 6\r\n7 8 9\r\n")
    (tmp_path / "in.ply").write_bytes(data)
    model = load(tmp_path / "in.ply")
    model.normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    save(model, tmp_path / "out.ply")
    out = (tmp_path / "out.ply").read_bytes()
    assert out.count(b"\n") == out.count(b"\r\n") == data.count(b"\r\n") + 3
    np.testing.assert_array_equal(load(tmp_path / "out.ply").normals, model.normals)


HEAD = (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        b"property float z\nproperty double quality\nproperty uchar label\nend_header\n"
        b"0 0 0 1 1\n")

RANGE_CASES = {
    # name: (second row, property needle)
    "float_1e39": (b"1e39 1 1 1 1", "'x' (float)"),
    "float_1e400": (b"1e400 1 1 1 1", "'x' (float)"),
    "float_minus_1e400": (b"1 -1e400 1 1 1", "'y' (float)"),
    "double_1e400": (b"1 1 1 1e400 1", "'quality' (double)"),
    "double_1e309": (b"1 1 1 -1e309 1", "'quality' (double)"),
    "uchar_1e400": (b"1 1 1 1 1e400", "'label' (uchar)"),
}


@pytest.mark.parametrize("name", sorted(RANGE_CASES))
def test_out_of_range_tokens_are_refused_at_any_magnitude(tmp_path, name):
    row, prop = RANGE_CASES[name]
    path = tmp_path / "range.ply"
    path.write_bytes(HEAD + row + b"\n")
    with pytest.raises(FormatError) as err:
        load(path)
    line = str(err.value)
    assert str(path) in line and "line 11" in line and prop in line, line
    res = run("info", path, cwd=tmp_path)
    one_error_line(res, 2, [str(path), "line 11", prop])


def test_literal_infinities_keep_todays_rule(tmp_path):
    """The literal tokens inf / nan still read as today: a double property holds them."""
    path = tmp_path / "lit.ply"
    path.write_bytes(HEAD + b"1 1 1 -Infinity 1\n")
    source = read_ply(path)
    assert np.isneginf(source.element("vertex").data["quality"][1])
    path.write_bytes(HEAD + b"1 1 1 nan 1\n")
    assert np.isnan(read_ply(path).element("vertex").data["quality"][1])
    path.write_bytes(HEAD + b"1 1 1 1e308 1\n")  # large but in range
    assert read_ply(path).element("vertex").data["quality"][1] == 1e308


# ---------------------------------------------------------------- 8. selector numbers

def _box(edit: dict, field: str, value) -> dict:
    edit["regions"]["fixed"][0]["box"][field][0] = value
    return edit


SELECTOR_CASES = {
    # name: (edit mutation, YAML text for NUM or None, key needles)
    "min_5000_digits": (lambda e: _box(e, "min", NUM), "9" * 5000,
                        ["regions.fixed[0].box.min[0]", "5,000 digits"]),
    "max_negative_5000_digits": (lambda e: _box(e, "max", NUM), "-" + "9" * 5000,
                                 ["regions.fixed[0].box.max[0]"]),
    "min_hex_3000_digits": (lambda e: _box(e, "min", NUM), "0x" + "f" * 3000,
                            ["regions.fixed[0].box.min[0]"]),
    "min_400_digits": (lambda e: _box(e, "min", NUM), "9" * 400,
                       ["regions.fixed[0].box.min[0]", "within"]),
    "min_1e300": (lambda e: _box(e, "min", NUM), "1.0e+300",
                  ["regions.fixed[0].box.min[0]", "within"]),
    "min_true": (lambda e: _box(e, "min", True), None,
                 ["regions.fixed[0].box.min[0]", "boolean"]),
    "max_false": (lambda e: _box(e, "max", False), None,
                  ["regions.fixed[0].box.max[0]", "boolean"]),
    "min_inf": (lambda e: _box(e, "min", NUM), "-.inf", ["regions.fixed[0].box.min[0]"]),
    "min_nan": (lambda e: _box(e, "min", NUM), ".nan", ["regions.fixed[0].box.min[0]"]),
    "min_above_max": (lambda e: _box(e, "min", 0.5), None,
                      ["regions.fixed[0].box", "exceeds max"]),
    "sphere_radius_true": (
        lambda e: e["regions"].update(handle=[{"sphere": {"center": [1, 0.5, 0.5],
                                                          "radius": True}}]), None,
        ["regions.handle[0].sphere.radius", "boolean"]),
    "sphere_center_huge": (
        lambda e: e["regions"].update(handle=[{"sphere": {"center": [NUM, 0.5, 0.5],
                                                          "radius": 0.1}}]), "1" * 4400,
        ["regions.handle[0].sphere.center[0]"]),
    "plane_zero_normal": (
        lambda e: e["regions"].update(handle=[{"plane": {"point": [0.8, 0, 0],
                                                         "normal": [0, 0, 0]}}]), None,
        ["regions.handle[0].plane.normal", "non-zero"]),
    "property_min_true": (
        lambda e: e["regions"].update(handle=[{"property": {"name": "red", "min": True}}]),
        None, ["regions.handle[0].property.min", "boolean"]),
    "property_in_huge": (
        lambda e: e["regions"].update(handle=[{"property": {"name": "red", "in": [1, NUM]}}]),
        "7" * 6000, ["regions.handle[0].property.in[1]"]),
    "nested_not_box_true": (
        lambda e: e["regions"].update(handle=[{"not": {"box": {"min": [True, 0, 0],
                                                               "max": [0.7, 1, 1]}}}]), None,
        ["regions.handle[0].not.box.min[0]", "boolean"]),
    "indices_true": (
        lambda e: e["regions"].update(handle=[{"indices": [1, True]}]), None,
        ["regions.handle[0].indices"]),
    "indices_5000_digits": (
        lambda e: e["regions"].update(handle=[{"indices": [1, NUM]}]), "3" * 5000,
        ["regions.handle[0].indices"]),
}


@pytest.mark.parametrize("name", sorted(SELECTOR_CASES))
def test_selector_numbers_are_bounded_finite_and_not_booleans(tmp_path, bar, name):
    mutate, number, needles = SELECTOR_CASES[name]
    edit = edit_of(bar)
    mutate(edit)  # in place
    cfg = write_text(tmp_path, edit, number)
    line = refused(tmp_path, cfg, ["edit.yaml", *needles])
    assert len(line) < 400, line  # the number is never printed in full


def test_huge_numbers_elsewhere_are_one_line_too(tmp_path, bar):
    """A 5,000-digit integer under any key (an int field, a translation, a YAML key) is a
    one-line config error, never Python's int -> str limit."""
    for edit, needle in (
        (edit_of(bar, fit={"tolerance": 1e-3, "max_centers": NUM}), "fit.max_centers"),
        (edit_of(bar, handle={"transform": {"translate": [0, NUM, 0]}}),
         "handle.transform.translate[1]"),
        (edit_of(bar, handle={"transform": {"rotate": {"degrees": NUM}}}),
         "handle.transform.rotate.degrees"),
    ):
        cfg = write_text(tmp_path, edit, "4" * 5000)
        refused(tmp_path, cfg, [needle])
    text = yaml.safe_dump(edit_of(bar)) + "9" * 5000 + ": 1\n"
    refused(tmp_path, write_config(tmp_path, text), ["edit.yaml"])


def test_valid_selector_numbers_still_load(bar):
    edit = edit_of(bar)
    edit["regions"]["handle"] = [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}},
                                 {"sphere": {"center": [1, 0.5, 0.5], "radius": 0.1}},
                                 {"property": {"name": "red", "min": 0, "max": 255}},
                                 {"indices": [0, 5]}]
    edit["handle"] = {"transform": {"scale": [2, 1, 0.5], "pivot": "centroid"}}
    cfg = parse_edit(edit, "ok.yaml")
    assert cfg.regions.handle[0].box.min == [0.75, 0.0, 0.0]
    text = yaml.safe_dump(edit).replace("- 0.75", "- '7.5e-1'")  # a string number still reads
    assert parse_edit(yaml.safe_load(text), "ok.yaml").regions.handle[0].box.min[0] == 0.75


def test_no_traceback_from_python_api_with_huge_ints(bar):
    """Callers of parse_edit with Python ints beyond the str limit get a ConfigError."""
    edit = edit_of(bar)
    edit["regions"]["fixed"][0]["box"]["min"][0] = 10**5000
    with pytest.raises(ConfigError) as err:
        parse_edit(edit, "api")
    assert "regions.fixed[0].box.min[0]" in str(err.value) and len(str(err.value)) < 300
