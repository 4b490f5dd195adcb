"""``save:`` in an edit config and ``deform --spz-version``: the writers' options for one run
(issue 34: SPZ v4 by default, v3 for older readers; the SOG encoder; the PCD encoding)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import yaml
from conftest import bar_edit
from helpers import run_cli

from data_tools.synth import bumpy_bar, gaussian_bar
from splatdeform.edit.run import run_edit
from splatdeform.io import load, save, spz
from splatdeform.io import pcd as pcd_io


@pytest.fixture(scope="module")
def splats(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("save_options") / "g.ply"
    save(gaussian_bar(3000, sh_degree=1, seed=7), path)
    return path


def _edit(src: Path, out: str, **save_keys) -> dict:
    cfg = bar_edit(input=str(src), output=out)
    if save_keys:
        cfg["save"] = save_keys
    return cfg


def _run(cfg: dict, folder: Path) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the lossy writers' notes
        return run_edit(cfg, folder).output


@pytest.mark.parametrize("version", [None, 3, 4])
def test_spz_version_key(splats: Path, tmp_path: Path, version) -> None:
    keys = {} if version is None else {"spz_version": version}
    out = _run(_edit(splats, "out.spz", **keys), tmp_path)
    assert spz.read_info(out)["version"] == (version or 4)
    assert load(out).n_points == 3000


def test_spz_version_flag_wins_over_the_config(splats: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "e.yaml"
    cfg.write_text(yaml.safe_dump(_edit(splats, "out.spz", spz_version=4)))
    res = run_cli("deform", cfg, "--spz-version", "3", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert spz.read_info(tmp_path / "out.spz")["version"] == 3


def test_bad_save_keys_name_the_key(splats: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "e.yaml"
    cfg.write_text(yaml.safe_dump(_edit(splats, "out.spz", spz_version=2)))
    res = run_cli("deform", cfg, cwd=tmp_path)
    assert res.returncode == 2 and "save.spz_version" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "out.spz").exists()


def test_sog_quality_and_pcd_data(splats: Path, tmp_path: Path) -> None:
    fast = _run(_edit(splats, "fast.sog", sog_quality="fast"), tmp_path)
    ref = _run(_edit(splats, "ref.sog", sog_quality="reference"), tmp_path)
    assert fast.read_bytes() != ref.read_bytes()
    src = tmp_path / "bar.pcd"
    save(bumpy_bar(3000, seed=8), src)
    out = _run(_edit(src, "out.pcd", pcd_data="binary_compressed"), tmp_path)
    assert pcd_io.read_header(out)[0].encoding == "binary_compressed"


def test_editor_save_writes_the_save_keys_as_deform(splats: Path, tmp_path: Path) -> None:
    """The editor's Save honours ``save:`` (here SPZ v3) as ``deform`` does: the same bytes."""
    from splatdeform.editor.controller import EditorController

    cfg = tmp_path / "e.yaml"
    cfg.write_text(yaml.safe_dump(_edit(splats, str(tmp_path / "out.spz"), spz_version=3)))
    ed = EditorController.open(cfg)
    ed.fit()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the lossy writer's note
        result = ed.save(model_path=tmp_path / "saved.spz", config_path=tmp_path / "s.yaml",
                         image=False)
    assert spz.read_info(result.model)["version"] == 3
    assert yaml.safe_load(result.config.read_text())["save"]["spz_version"] == 3
    run = run_cli("deform", str(result.config), "-o", str(tmp_path / "again.spz"))
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "again.spz").read_bytes() == result.model.read_bytes()
