"""The edit YAML writer is the inverse of the parser: write -> parse gives the same config, for
the shipped configs and for every form of edit (one handle by transform or matrix, handles:,
a curve with handles, every selector kind), written beside or away from the data."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import ROOT, bar_edit

from splatdeform.edit.config import load_edit, parse_edit, read_yaml
from splatdeform.edit.writer import config_yaml, yaml_text

SHIPPED = sorted(p for p in (ROOT / "configs").glob("*.yaml") if "input" in read_yaml(p))

SELECTORS = [
    {"sphere": {"center": [0.9, 0.5, 0.5], "radius": 0.2}},
    {"plane": {"point": [0.8, 0, 0], "normal": [1, 0, 0]}},
    {"all": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}},
             {"not": {"property": {"name": "red", "max": 10}}}]},
    {"indices": [3, 5, 8]},
]
EDITS = {
    "transform": bar_edit({"pivot": [0.75, 0.5, 0.5], "scale": [1, 2, 1],
                           "rotate": {"axis": [0, 0, 1], "degrees": 30},
                           "translate": [0, 0.1, 0]}, input="bar.ply", output="out/o.ply"),
    "matrix": {**bar_edit(input="bar.ply", output="o.ply", backend="opencl", device="0:0",
                          normals="estimate", memory_budget="2GB"),
               "handle": {"matrix": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
               "gaussians": {"covariance": "rotation"},
               "render": {"output": "pics/o.png", "size": [400, 200], "up": "+z", "roll": 5}},
    "handles": {**{k: v for k, v in bar_edit(input="bar.ply", output="o.ply").items()
                   if k != "handle"},
                "regions": {"units": "relative",
                            "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}]},
                "handles": [{"region": [s], "transform": {"translate": [0, 0.1 * i, 0]}}
                            for i, s in enumerate(SELECTORS)]},
    "curve": {"input": "/data/bar.ply", "output": "o.ply",
              "regions": {"units": "model", "fixed": [{"box": {"min": [-1, -1, -1],
                                                               "max": [0.6, 1, 1]}}]},
              "curve": {"control_points": [[1.2, 0.5, 0], [2.8, 0.5, 0]],
                        "moved_to": [[1.2, 0.5, 0], [2.8, 0.9, 0]], "degree": 1,
                        "capture_radius": 0.1},
              "handles": [{"region": [SELECTORS[0]], "matrix": [[1, 0, 0, 0], [0, 1, 0, 0],
                                                                [0, 0, 1, 0.2], [0, 0, 0, 1]]}],
              "fit": {"tolerance": 1e-3, "threads": 2, "method": "exact"}},
}


def _round_trip(cfg, base: Path, config_dir: Path):
    text = yaml_text(config_yaml(cfg, base, config_dir), "written by a test\n  second line")
    assert text.startswith("# written by a test\n#   second line\n")
    return parse_edit(yaml.safe_load(text), "round trip")


def _assert_same(back, cfg, base: Path, config_dir: Path) -> None:
    """``back`` (paths relative to ``config_dir``) is ``cfg`` (relative to ``base``): the same
    files (a path outside the folder is written absolute), every other value equal."""
    for field in ("input", "output"):
        assert (config_dir / getattr(back, field)).resolve() == \
            (base / getattr(cfg, field)).resolve()
    render = cfg.render
    if render is not None and render.output is not None:
        assert (config_dir / back.render.output).resolve() == (base / render.output).resolve()
        render = render.model_copy(update={"output": back.render.output})
    points = cfg.points
    for key in ("pairs", "check_pairs"):   # a pairs file: the same file
        entry = None if points is None else getattr(points, key)
        if entry is not None and getattr(entry, "file", None) is not None:
            theirs = getattr(back.points, key)
            assert (config_dir / theirs.file).resolve() == (base / entry.file).resolve()
            points = points.model_copy(update={key: theirs})
    assert back == cfg.model_copy(update={"input": back.input, "output": back.output,
                                          "render": render, "points": points})


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_configs_round_trip(path: Path) -> None:
    cfg = load_edit(path)
    _assert_same(_round_trip(cfg, path.parent, path.parent), cfg, path.parent, path.parent)


@pytest.mark.parametrize("name", sorted(EDITS))
def test_every_form_round_trips(name: str, tmp_path: Path) -> None:
    cfg = parse_edit(EDITS[name], name)
    back = _round_trip(cfg, tmp_path, tmp_path)
    assert back == cfg   # paths inside the folder stay as written
    if name == "matrix":
        assert back.render.output == "pics/o.png" and back.memory_budget == "2GB"


def test_written_elsewhere_the_paths_follow(tmp_path: Path) -> None:
    """Written into another folder, relative paths are rebased: the same files are meant."""
    cfg = parse_edit(EDITS["matrix"], "matrix")
    away = tmp_path / "away"
    back = _round_trip(cfg, tmp_path / "data", away)
    assert back.input != cfg.input
    _assert_same(back, cfg, tmp_path / "data", away)
