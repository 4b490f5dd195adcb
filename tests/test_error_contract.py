"""The typed error contract: errors carry the file and the config key path as fields."""

from __future__ import annotations

import pickle

import pytest

from splatdeform.edit.config import parse_edit
from splatdeform.errors import ConfigError, RegionError

BASE = {"input": "a.ply", "output": "b.ply",
        "regions": {"fixed": [{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}],
                    "handle": [{"sphere": {"center": [0, 0, 0], "radius": 1}}]},
        "handle": {"transform": {"rotate": {"axis": [0, 0, 1], "degrees": 3}}}}


def test_fields_compose_the_line_and_survive_pickling():
    err = RegionError.at("handles[1].region", "selects no point; widen it")
    assert (err.key, err.file, err.message) == ("handles[1].region", None,
                                                "selects no point; widen it")
    assert str(err.in_file("edit.yaml")) == "edit.yaml: handles[1].region: selects no point; " \
                                            "widen it"
    assert err.in_file("other.yaml").file == "edit.yaml"  # the first file said stays
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is RegionError and (back.key, back.file) == (err.key, err.file)


@pytest.mark.parametrize(("change", "key"), [
    (lambda c: c["regions"]["fixed"][0]["box"].update(min=[0, "x", 0]),
     "regions.fixed[0].box.min[1]"),
    (lambda c: c["handle"]["transform"]["rotate"].update(degrees="a"),
     "handle.transform.rotate.degrees"),
    (lambda c: c["handle"].update(matrix=[[1, 0, 0, 0]] * 3), "handle.matrix"),
    (lambda c: c["regions"]["fixed"][0].update(bogus=1), "regions.fixed[0].bogus"),
    (lambda c: c.update(fit={"tolerance": 2}), "fit.tolerance"),
])
def test_pydantic_errors_map_to_key_paths_from_the_models_fields(change, key):
    cfg = {**BASE, "regions": {**BASE["regions"],
                               "fixed": [{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}]},
           "handle": {"transform": {"rotate": {"axis": [0, 0, 1], "degrees": 3}}}}
    change(cfg)
    with pytest.raises(ConfigError) as info:
        parse_edit(cfg, "edit.yaml")
    assert info.value.file == "edit.yaml" and info.value.key == key, str(info.value)
    assert "function-after" not in str(info.value) and "list[float]" not in str(info.value)
