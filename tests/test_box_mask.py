"""Box selection one column at a time: the same points as the (x - origin) / scale box test on
whole rows it replaced, for float64 and float32 models, with and without a relative frame."""

from __future__ import annotations

import numpy as np
import pytest

from splatdeform.edit.selectors.box import Box, in_frame
from splatdeform.model import PointModel


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_box_mask_equals_the_row_test(dtype):
    rng = np.random.default_rng(11)
    pts = (rng.normal(size=(50_001, 3)) * 1e3 + 5e5).astype(dtype)
    model = PointModel(positions=pts.astype(np.float64))
    lo, hi = model.bbox()
    frame = {"origin": tuple(lo), "scale": tuple(hi - lo)}
    for box_min, box_max in (((0, 0, 0), (1, 1, 1)), ((0.3, 0.1, 0), (0.7, 1, 0.5)),
                             ((1, 1, 1), (1, 1, 1))):
        box = Box(box_min, box_max, **frame)
        rel = in_frame(model.positions, box.origin, box.scale)
        want = np.all((rel >= box_min) & (rel <= box_max), axis=1)
        np.testing.assert_array_equal(box.mask(model), want)
    # a box reaching 1 in relative units holds the extreme points
    assert Box((0, 0, 0), (1, 1, 1), **frame).mask(model).all()
    plain = Box(tuple(lo + 100), tuple(hi - 100))
    want = np.all((model.positions >= lo + 100) & (model.positions <= hi - 100), axis=1)
    np.testing.assert_array_equal(plain.mask(model), want)
