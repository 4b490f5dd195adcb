"""Relative units become model units in one place (splatdeform.edit.units), exactly."""

from __future__ import annotations

import numpy as np

from data_tools.synth import bumpy_bar
from splatdeform.edit import units as u
from splatdeform.edit.selectors import Box, Plane, Sphere, select


def test_relative_selectors_select_exactly_what_box_coordinates_say():
    model = bumpy_bar(5000, seed=9)
    lo, hi = model.bbox()
    rel = (model.positions - lo) / (hi - lo)  # box coordinates, as a user reads the config
    frame = u.Frame.of(model)
    box = u.selector(Box((0.7, 0, 0), (1, 1, 1)), "relative", frame)
    mask = select(model, [box])
    np.testing.assert_array_equal(mask, np.all((rel >= [0.7, 0, 0]) & (rel <= 1), axis=1))
    assert mask[np.argmax(model.positions[:, 0])]  # the extreme point is inside a box up to 1
    plane = u.selector(Plane((0.5, 0.5, 0.5), (1, 1, 0)), "relative", frame)
    np.testing.assert_array_equal(select(model, [plane]),
                                  (rel - 0.5) @ np.array([1.0, 1.0, 0.0]) >= 0)
    sphere = u.selector(Sphere((0.5, 0.5, 0.5), 0.1), "relative", frame)
    center = lo + 0.5 * (hi - lo)
    radius = 0.1 * np.linalg.norm(hi - lo)
    np.testing.assert_array_equal(
        select(model, [sphere]),
        np.sum((model.positions - center) ** 2, axis=1) <= radius * radius)
    # the convenience argument of select() is the same conversion
    np.testing.assert_array_equal(select(model, [Box((0.7, 0, 0), (1, 1, 1))], "relative"), mask)


def test_points_vectors_and_lengths():
    model = bumpy_bar(2000, seed=1)
    frame = u.Frame.of(model)
    lo, hi = model.bbox()
    np.testing.assert_allclose(u.point((1, 1, 1), "relative", frame), hi)
    np.testing.assert_allclose(u.vector((1, 0, 0), "relative", frame), [hi[0] - lo[0], 0, 0])
    assert u.length(1.0, "relative", frame) == model.diagonal()
    np.testing.assert_array_equal(u.point((1, 2, 3), "model", frame), [1, 2, 3])
