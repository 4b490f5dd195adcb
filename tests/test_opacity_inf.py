"""Opacity logits of +-inf (issue 34 item 3): valid in PLY (read and kept), NaN still an error;
byte 255 in .compressed.ply decodes to alpha 1 (logit +inf), as splat-transform reads it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from splat_oracle import scene_source, write_scene

from splatdeform.errors import FormatError
from splatdeform.io import load, save
from splatdeform.io.ply_format import write_ply
from splatdeform.io.splats import LossyWriteWarning


def _scene_with(tmp_path, values):
    source = scene_source(50, 1, 2)
    data = source.element("vertex").data
    for i, v in enumerate(values):
        data["opacity"][i] = v
    path = tmp_path / "scene.ply"
    with open(path, "wb") as f:
        write_ply(source, f)
    return path


def test_infinite_opacity_ply_round_trip(tmp_path):
    path = _scene_with(tmp_path, [np.inf, -np.inf])
    model = load(path)
    assert model.gaussians.opacity[0] == np.inf and model.gaussians.opacity[1] == -np.inf
    out = tmp_path / "out.ply"
    save(model, out)
    back = load(out)
    assert back.gaussians.opacity[0] == np.inf and back.gaussians.opacity[1] == -np.inf
    assert np.array_equal(back.gaussians.opacity, model.gaussians.opacity)


def test_nan_opacity_is_still_an_error(tmp_path):
    with pytest.raises(FormatError, match="scene.ply: 1 vertex"):
        load(_scene_with(tmp_path, [np.nan]))


def test_compressed_byte_255_is_alpha_1(tmp_path):
    path = _scene_with(tmp_path, [np.inf, 30.0])
    out = tmp_path / "x.compressed.ply"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        save(load(path), out)
    model = load(out)
    assert model.gaussians.opacity[0] == np.inf and model.gaussians.opacity[1] == np.inf
    assert np.isfinite(model.gaussians.opacity[2:]).all()
    assert write_scene  # the shared scene writer stays the source of the layout
