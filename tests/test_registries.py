"""The registries of the config layer: selectors (a pydantic tagged union built from one module
per selector) and metaphors (handle, curve), and the one prepare_handle signature."""

from __future__ import annotations

import typing
from dataclasses import dataclass

import numpy as np
import pytest

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.edit.config import parse_edit
from splatdeform.edit.metaphors import KINDS, Context, entries
from splatdeform.edit.plain import metaphors
from splatdeform.edit.selectors import REGISTRY, SelectorCfg, select
from splatdeform.errors import ConfigError

EXAMPLES = {
    "box": {"box": {"min": [0.0, -1.0, -1.0], "max": [0.5, 1.0, 1.0]}},
    "sphere": {"sphere": {"center": [4.0, 0.0, 0.0], "radius": 0.4}},
    "plane": {"plane": {"point": [3.5, 0.0, 0.0], "normal": [1.0, 0.0, 0.0]}},
    "indices": {"indices": [0, 5, 7]},
    "property": {"property": {"name": "x", "equals": 0.0}},
    "all": {"all": [{"box": {"min": [0.0, -1.0, -1.0], "max": [0.5, 1.0, 1.0]}},
                    {"not": {"property": {"name": "x", "in": [0.0, 1.0], "max": 2.0}}}]},
    "not": {"not": {"sphere": {"center": [4.0, 0.0, 0.0], "radius": 0.4}}},
}


def edit_with(fixed: list[dict]) -> dict:
    return {"input": "a.ply", "output": "b.ply", "regions": {"fixed": fixed},
            "handles": [{"region": [EXAMPLES["sphere"]],
                         "transform": {"translate": [0, 0.1, 0]}}]}


def test_registry_is_the_union():
    """Every registered module gives the union one member, and every example validates into
    its own entry whose plain selector writes back the same mapping (the editor's YAML)."""
    members = typing.get_args(typing.get_args(SelectorCfg)[0])
    assert [typing.get_args(m)[0] for m in members] == [m.Entry for m in REGISTRY.values()]
    assert set(EXAMPLES) == set(REGISTRY)
    cfg = parse_edit(edit_with(list(EXAMPLES.values())), "edit.yaml")
    for name, entry in zip(EXAMPLES, cfg.regions.fixed, strict=True):
        assert isinstance(entry, REGISTRY[name].Entry)
        plain = entry.to_selector()
        for method in ("mask", "in_units", "to_config"):
            assert callable(getattr(plain, method))
        assert plain.to_config() == EXAMPLES[name]


@pytest.mark.parametrize(("selector", "key", "words"), [
    ({"box": {"min": [0, 0, 0], "max": [1, 1, 1]}, "sphere": {"center": [0, 0, 0],
                                                               "radius": 1}},
     "regions.fixed[0]", "expected exactly one of box, sphere, plane, indices, property, all, not"),
    ({"cube": {"size": 1}}, "regions.fixed[0]", "expected exactly one of box"),
    ({}, "regions.fixed[0]", "expected exactly one of box"),
    ({"box": {"min": [0, 0, 0]}}, "regions.fixed[0].box.max", "required key is missing"),
    ({"sphere": {"center": [0, 0, 0], "radius": -1}}, "regions.fixed[0].sphere.radius",
     "greater than 0"),
    ({"box": {"min": [0, 0, 0], "max": [1, 1, 1]}, "bogus": 1}, "regions.fixed[0].bogus",
     "unknown key"),
    ({"indices": [0, -3]}, "regions.fixed[0].indices[1]", "greater than or equal to 0"),
])
def test_union_errors_name_the_key(selector, key, words):
    with pytest.raises(ConfigError) as info:
        parse_edit(edit_with([selector]), "edit.yaml")
    assert info.value.key == key and words in info.value.message, str(info.value)
    assert "selector" not in info.value.key  # union tags never leak into key paths


def test_select_takes_any_object_with_the_selector_protocol():
    """Masks are built through the protocol (mask / in_units), not by type: what a new
    selector module needs to provide."""

    @dataclass(frozen=True)
    class Slab:  # |x - center| <= half, no units of its own
        center: float
        half: float

        def mask(self, model, base_dir=None):
            return np.abs(model.positions[:, 0] - self.center) <= self.half

        def in_units(self, units, frame):
            return self

    model = bumpy_bar(3000, seed=4)
    got = select(model, [Slab(2.0, 0.25), sd.Sphere((4.0, 0.0, 0.0), 0.4)], "relative")
    want = (np.abs(model.positions[:, 0] - 2.0) <= 0.25) | select(
        model, [sd.Sphere((4.0, 0.0, 0.0), 0.4)], "relative")
    np.testing.assert_array_equal(got, want)


def test_metaphor_registry_orders_the_columns():
    model = bumpy_bar(3000, seed=4)
    cfg = parse_edit({
        "input": "a.ply", "output": "b.ply",
        "regions": {"fixed": [{"box": {"min": [1.8, -1, -1], "max": [2.2, 1, 1]}}]},
        "handles": [{"region": [{"box": {"min": [-1, -1, -1], "max": [0.3, 1, 1]}}],
                     "transform": {"translate": [0, 0.1, 0]}}],
        "curve": {"control_points": [[2.6, 0.45, 0], [3.2, 0.45, 0], [3.8, 0.45, 0]],
                  "moved_to": [[2.6, 0.45, 0], [3.2, 0.6, 0], [3.8, 0.45, 0]],
                  "degree": 2, "capture_radius": 0.2}}, "edit.yaml")
    assert [kind.__name__.rsplit(".", 1)[1] for kind in KINDS] == ["handle", "curve", "points"]
    assert [key for _, key, _ in entries(cfg)] == ["handles[0]", "curve"]
    mphs = metaphors(cfg, model, None)
    assert [m.k for m in mphs] == [4, 3]
    assert Context.of(cfg, model, None).units == "model"


def test_prepare_handle_has_one_signature():
    model = bumpy_bar(3000, seed=4)
    fixed = select(model, [sd.Box((0.45, 0, 0), (0.55, 1, 1))], "relative")
    handle = select(model, [sd.Box((0.9, 0, 0), (1, 1, 1))], "relative")
    by_settings = sd.prepare_handle(model, fixed, handle, tolerance=1e-3, backend="numpy")
    by_fns = sd.prepare_handle(model, fixed, handle,
                               fit_fn=sd.deform.fit_settings(model, tolerance=1e-3),
                               basis_fn=sd.deform.basis_settings("numpy"))
    np.testing.assert_array_equal(by_settings.basis.values, by_fns.basis.values)
    with pytest.raises(TypeError, match="tolerence"):
        sd.prepare_handle(model, fixed, handle, tolerence=1e-3)
