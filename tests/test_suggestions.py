"""Issue 48 items 1-2: ``splatdeform --version``, ``splatdeform example`` (the quick start's
scan and config from the package), and "did you mean" for mistyped config keys, enum values,
selector kinds, CLI flags, choices and verbs."""

from __future__ import annotations

import hashlib

import pytest
import yaml
from helpers import base_config, one_error_line, run_cli, write_config

import splatdeform
from data_tools.synth import bumpy_bar
from splatdeform.io import save


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans")
    save(bumpy_bar(800), folder / "bar.ply")
    return folder


def test_version():
    res = run_cli("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"splatdeform {splatdeform.__version__}"


def _edit(tmp_path, scans, change) -> str:
    cfg = base_config(scans)
    change(cfg)
    return one_error_line(run_cli("deform", write_config(tmp_path, cfg), cwd=tmp_path))


@pytest.mark.parametrize("change, key, hint", [
    (lambda c: c["handle"]["transform"].update(rotation=c["handle"]["transform"].pop("rotate")),
     "handle.transform.rotation: unknown key", "did you mean 'rotate'?"),
    (lambda c: c.update(fitt=c.pop("fit")), "fitt: unknown key", "did you mean 'fit'?"),
    (lambda c: c.update(boundary={"neighbours": 8}), "boundary.neighbours: unknown key",
     "did you mean 'neighbors'?"),
    (lambda c: c["regions"]["fixed"][0]["box"].update(mins=[-1, -1, -1]),
     "regions.fixed[0].box.mins: unknown key", "did you mean 'min'?"),
    (lambda c: c["regions"]["fixed"].__setitem__(0, {"boxx": {"min": [0, 0, 0],
                                                               "max": [1, 1, 1]}}),
     "regions.fixed[0]: expected exactly one of", "(got 'boxx') (did you mean 'box'?)"),
    (lambda c: c["regions"].update(units="relativ"), "regions.units:",
     "did you mean 'relative'?"),
    (lambda c: c.update(backend="opencll"), "backend:", "did you mean 'opencl'?"),
])
def test_config_typos_suggest_the_allowed_name(tmp_path, scans, change, key, hint):
    line = _edit(tmp_path, scans, change)
    assert key in line and line.rstrip(")").endswith(hint.rstrip(")")), line


def test_nothing_close_suggests_nothing(tmp_path, scans):
    line = _edit(tmp_path, scans, lambda c: c.update(zzzzzz=1))
    assert line.endswith("zzzzzz: unknown key"), line


def test_batch_typo_suggests(tmp_path, scans):
    (tmp_path / "b.yaml").write_text(yaml.safe_dump({
        "scans": str(scans / "*.ply"), "output_dir": "out", "worker": 2,
        "edit": {"regions": {"fixed": [{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}]}}}))
    line = one_error_line(run_cli("batch", tmp_path / "b.yaml", cwd=tmp_path))
    assert line.endswith("worker: unknown key (did you mean 'workers'?)"), line


@pytest.mark.parametrize("argv, hint", [
    (["deform", "EDIT", "--reder", "x.png"], "unrecognized arguments: --reder x.png "
                                             "(did you mean --render?)"),
    (["render", "a.ply", "-o", "x.png", "--azimth=3"], "(did you mean --azimuth?)"),
    (["defrom", "x.yaml"], "invalid choice: 'defrom'"),
    (["render", "a.ply", "-o", "x.png", "--color", "elev"], "(did you mean 'elevation'?)"),
])
def test_cli_typos_suggest(tmp_path, scans, argv, hint):
    argv = [str(write_config(tmp_path, base_config(scans))) if a == "EDIT" else a for a in argv]
    line = one_error_line(run_cli(*argv, cwd=tmp_path))
    assert hint in line, line
    if argv[0] == "defrom":
        assert line.endswith("(did you mean 'deform'?)"), line


def test_example_list_and_write(tmp_path):
    listed = run_cli("example", "--list", cwd=tmp_path)
    assert listed.returncode == 0
    assert [ln.split()[0] for ln in listed.stdout.splitlines()] == [
        "bar", "curve", "sphere", "rubber_sheet"]
    assert run_cli("example", "bar", cwd=tmp_path).returncode == 0
    ply = (tmp_path / "scans" / "bar.ply").read_bytes()
    assert hashlib.sha256(ply).digest() == hashlib.sha256(
        save(bumpy_bar(), tmp_path / "same.ply").read_bytes()).digest()  # one generator
    assert yaml.safe_load((tmp_path / "bend.yaml").read_text())["input"] == "scans/bar.ply"
    again = run_cli("example", "curve", "sub", cwd=tmp_path)   # into a new folder
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "sub" / "curve.yaml").is_file()
    assert run_cli("example", "bar", cwd=tmp_path).returncode == 0  # same contents: kept


def test_example_refuses_to_replace_other_contents(tmp_path):
    (tmp_path / "bend.yaml").write_text("mine\n")
    one_error_line(run_cli("example", "bar", cwd=tmp_path),
                   needles=("bend.yaml: exists with other contents", "--force"))
    assert (tmp_path / "bend.yaml").read_text() == "mine\n"
    assert not (tmp_path / "scans").exists()   # nothing written
    assert run_cli("example", "bar", "--force", cwd=tmp_path).returncode == 0
    assert (tmp_path / "bend.yaml").read_text() != "mine\n"


def test_example_unknown_name(tmp_path):
    one_error_line(run_cli("example", "sphre", cwd=tmp_path),
                   needles=("unknown example 'sphre' (did you mean 'sphere'?)",))
    one_error_line(run_cli("example", cwd=tmp_path), needles=("--list",))


@pytest.mark.parametrize("name", ["bar", "curve", "sphere"])
def test_every_example_config_validates(tmp_path, name):
    from splatdeform.edit.config import load_edit
    from splatdeform.examples import EXAMPLES, write_example

    paths = write_example(name, tmp_path)
    assert [str(p.relative_to(tmp_path)) for p in paths] == [f for f, _ in EXAMPLES[name][1]]
    cfg = load_edit(paths[-1])
    assert cfg.input == paths[0].relative_to(tmp_path).as_posix()
