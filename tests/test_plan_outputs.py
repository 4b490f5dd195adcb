"""One plan owns every output (issue 44 item 1): ``deform``'s model, reuse cache, image and its
camera file, ``--save-field`` and ``--residuals`` are checked together, before any work, so two
of them that are the same file (also through another spelling or a link) are refused with one
line naming both, and nothing is written."""

from __future__ import annotations

import os
from pathlib import Path

import helpers
import pytest
from helpers import base_config, one_error_line, snapshot, write_config

import splatdeform as sd
from data_tools.synth import bumpy_bar


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("plan_outputs")
    sd.save(bumpy_bar(1200, seed=21), root / "bar.ply")
    return root


def _refused(work: Path, *args: str, needles=()) -> str:
    before = snapshot(work)
    res = helpers.run_cli(*args, cwd=work, timeout=300)
    line = one_error_line(res, 2, needles)
    assert snapshot(work) == before, "a refused run wrote or removed something"
    return line


@pytest.mark.parametrize("args,needles", [
    (["--render", "out/x.png", "--save-field", "out/x.png"], ["--save-field", "--render"]),
    (["--reuse-file", "z.npz", "--save-field", "z.npz"], ["--save-field", "--reuse-file"]),
    (["--save-field", "out/bent.ply"], ["--save-field", "output"]),
    (["--render", "out/x.png", "--save-field", "out/x.camera.json"], ["--save-field", "--render"]),
    (["--render", "out/x.png", "--save-field", "out/../out/./x.png"], ["--save-field"]),
])
def test_two_outputs_that_are_one_file_are_refused(scans, tmp_path, args, needles):
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans))
    (work / "out").mkdir()
    _refused(work, "deform", cfg.name, *args, needles=needles)


def test_an_output_linked_to_another_is_refused(scans, tmp_path):
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans))
    (work / "out").mkdir()
    (work / "out" / "x.png").write_bytes(b"an earlier image")
    os.symlink("x.png", work / "out" / "field.npz")   # the field would replace the image
    _refused(work, "deform", cfg.name, "--render", "out/x.png", "--save-field", "out/field.npz",
             needles=["--save-field", "--render"])


def test_residuals_only_for_points_before_any_work(scans, tmp_path):
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans))
    _refused(work, "deform", cfg.name, "--residuals", "r.csv", needles=["--residuals", "points"])


def test_distinct_outputs_all_written(scans, tmp_path):
    work = tmp_path / "w"
    cfg = write_config(work, base_config(scans))
    res = helpers.run_cli("deform", cfg.name, "--quiet", "--save-field", "out/field.npz",
                          "--reuse-file", "out/cache.npz", cwd=work, timeout=300)
    assert res.returncode == 0, res.stderr
    assert {p.name for p in (work / "out").iterdir()} == {"bent.ply", "field.npz", "cache.npz"}


def test_the_plan_lists_every_output(scans, tmp_path):
    from splatdeform.edit.plan import plan_edit

    cfg = base_config(scans)
    plan = plan_edit(cfg, tmp_path, field=tmp_path / "f.npz", reuse=tmp_path / "c.npz")
    assert (plan.output, plan.field, plan.reuse) == (tmp_path / "out/bent.ply",
                                                      tmp_path / "f.npz", tmp_path / "c.npz")


# ------------------------------------------------ metaphors declare what they can take part in

def test_each_kind_declares_its_capabilities():
    from splatdeform.edit.capable import refusal
    from splatdeform.edit.config import parse_edit
    from splatdeform.edit.metaphors import KINDS, points

    for kind in (*KINDS, points):
        assert kind.CAPABILITIES.why, kind.__name__
    one = parse_edit(base_config(Path("/nowhere")), "edit")
    assert refusal(one, "streams") == "" and refusal(one, "reusable") == ""
    many = base_config(Path("/nowhere"))
    many["handles"] = [{"region": many["regions"].pop("handle"), **many.pop("handle")}]
    assert "several handles" in refusal(parse_edit(many, "edit"), "streams")
    pairs = base_config(Path("/nowhere"), points={"pairs": [[2, 0, 0, 2, 0.1, 0]]})
    pairs["regions"].pop("handle")
    pairs.pop("handle")
    cfg = parse_edit(pairs, "edit")
    assert refusal(cfg, "streams").startswith("points:")
    assert refusal(cfg, "reusable").startswith("points:")


def test_an_edit_that_cannot_stream_runs_in_memory_under_the_default_budget():
    """Decided once: over the default budget (none given) an edit that cannot stream runs in
    memory with a warning; over an explicit budget it is refused, naming why."""
    from splatdeform.memory import choose

    default = choose(10**12, None, streamable=False, name="x.ply",
                     why_not="curve: curve edits do not stream yet")
    assert default.mode == "memory" and "curve edits do not stream" in default.message
    capped = choose(10**12, 10**6, streamable=False, name="x.ply",
                    why_not="curve: curve edits do not stream yet")
    assert capped.mode == "refuse" and "curve edits do not stream" in capped.message


def test_points_edit_refused_before_work(scans, tmp_path):
    work = tmp_path / "w"
    cfg = base_config(scans, points={"pairs": [[2, 0, 0, 2, 0.1, 0]]})
    cfg["regions"].pop("handle")
    cfg.pop("handle")
    path = write_config(work, cfg)
    _refused(work, "deform", path.name, "--reuse", needles=["points", "--reuse"])
