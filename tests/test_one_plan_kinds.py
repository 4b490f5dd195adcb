"""Issue 44, the rest of items 1 and 2: every verb that writes plans its paths through the one
check (:func:`splatdeform.io.plan.plan_io`), so two outputs that are one file or an output that
is an input are refused before any work, naming both; and ``points`` is one metaphor kind among
the others (one module plus one line in ``KINDS``), with no branch on the config's metaphor
keys outside the metaphor modules."""

from __future__ import annotations

import ast
from pathlib import Path

import helpers
import pytest
from helpers import base_config, one_error_line, snapshot, write_config

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("one_plan")
    sd.save(bumpy_bar(1200, seed=44), root / "bar.ply")
    return root


def _refused(work: Path, *args: str, needles=()) -> str:
    before = snapshot(work)
    res = helpers.run_cli(*args, cwd=work, timeout=300)
    line = one_error_line(res, 2, needles)
    assert snapshot(work) == before, "a refused run wrote or removed something"
    return line


# ------------------------------------------------------------- one plan for every verb's paths

def test_convert_onto_its_input_by_another_spelling_is_refused(scans, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    (work / "bar.ply").write_bytes((scans / "bar.ply").read_bytes())
    _refused(work, "convert", "bar.ply", "./sub/../bar.ply", needles=["output", "input"])


def test_apply_onto_its_field_is_refused(scans, tmp_path):
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans))
    res = helpers.run_cli("deform", cfg.name, "--quiet", "--save-field", "f.npz", cwd=work,
                          timeout=300)
    assert res.returncode == 0, res.stderr
    _refused(work, "apply", "f.npz", str(scans / "bar.ply"), "-o", "f.npz",
             needles=["-o/--output", "field"])


def test_select_image_whose_camera_file_is_the_config_is_refused(scans, tmp_path):
    """``select -o x.png`` also writes x.camera.json: an edit config of that name is an input
    the preview would replace."""
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans), name="x.camera.json")
    _refused(work, "select", cfg.name, "-o", "x.png", needles=["-o/--output", "edit config"])


def test_render_image_whose_camera_file_is_the_model_is_refused(scans, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    model = work / "x.camera.json"
    model.write_bytes(b"not read: refused before")
    res = helpers.run_cli("render", str(scans / "bar.ply"), "--camera", model.name, "-o",
                          "x.png", cwd=work, timeout=300)
    one_error_line(res, 2, ["-o/--output", "--camera"])


def test_editor_save_with_two_outputs_at_one_path_is_refused(scans, tmp_path):
    from splatdeform.editor.controller import EditorController

    ed = EditorController.open(scans / "bar.ply")
    ed.add_selector("fixed", sd.Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)))
    ed.add_selector("handle", sd.Box((3.0, -1.0, -1.0), (5.0, 1.0, 1.0)))
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    with pytest.raises(InputError, match="image .*is also the model output"):
        ed.save(model_path=tmp_path / "same.ply", config_path=tmp_path / "e.yaml",
                image_path=tmp_path / "same.ply")
    assert not list(tmp_path.iterdir())


def test_the_edit_plan_holds_the_io_plan(scans, tmp_path):
    from splatdeform.edit.plan import plan_edit

    plan = plan_edit(base_config(scans), tmp_path, field=tmp_path / "f.npz")
    assert plan.io.output("--save-field") == tmp_path / "f.npz"
    assert plan.io.output("output") == plan.output
    assert ("input model", scans / "bar.ply") in plan.io.inputs


# ------------------------------------------------------------------ points is one kind of many

def test_points_is_a_kind_with_the_protocol_of_every_kind():
    from splatdeform.edit.metaphors import KINDS, points

    assert KINDS[-1] is points
    for kind in KINDS:
        for name in ("entries", "metaphor", "delta", "basis_key", "label", "columns",
                     "CAPABILITIES"):
            assert hasattr(kind, name), (kind.__name__, name)


def test_a_points_edit_and_a_handle_edit_share_the_run(scans, tmp_path):
    """Pairs with a handle: one deformation whose last group holds the pairs' fit; the
    residual report comes from the kind's hook."""
    from splatdeform.deform.points import PointsFit

    cfg = base_config(scans, points={"pairs": [[2.0, 0, 0.4, 2.0, 0.05, 0.4]]})
    result = sd.run_edit(cfg, base_dir=tmp_path, save_output=False, log=lambda line: None)
    groups = result.deformation.groups
    assert [g.name for g in groups][-1] == "points"
    assert isinstance(groups[-1].constraints, PointsFit)
    assert groups[-1].columns == (result.deformation.k - 3, result.deformation.k)
    assert result.points is not None and result.points.residuals.shape == (1, 3)
    plain = sd.run_edit(base_config(scans), base_dir=tmp_path, save_output=False,
                        log=lambda line: None)
    assert plain.points is None


#: where the edit config's metaphor keys may be read: the kinds themselves, the schema, the
#: YAML writer (it writes each key back) and the editor's state loader
ALLOWED = {"splatdeform/edit/config.py", "splatdeform/edit/writer.py",
           "splatdeform/editor/controller.py"}
KEYS = {"points", "curve", "handle", "handles"}


def test_no_branch_on_the_metaphor_keys_outside_the_kinds():
    found = []
    for path in sorted((ROOT / "splatdeform").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel in ALLOWED or rel.startswith("splatdeform/edit/metaphors/"):
            continue
        for node in ast.walk(ast.parse(path.read_text(), rel)):
            if (isinstance(node, ast.Attribute) and node.attr in KEYS
                    and isinstance(node.value, ast.Name) and node.value.id in ("cfg", "config")):
                found.append(f"{rel}:{node.lineno} {node.value.id}.{node.attr}")
    assert found == []
