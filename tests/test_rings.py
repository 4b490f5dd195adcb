"""Rings over the border-restricted kNN graph equal the rings over the whole-model kNN graph."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_file

from data_tools.synth import bumpy_bar
from splatdeform.deform.rings import (
    adjacency,
    band_adjacency,
    border_band,
    boundary_rings,
    neighbours_of,
    region_adjacency,
)
from splatdeform.edit.selectors import Box, select
from splatdeform.errors import RegionError
from splatdeform.io import load
from splatdeform.model import PointModel


def slab_edit(model: PointModel, lo: float = 0.3, hi: float = 0.8):
    """Fixed: the first ``lo`` of the bbox along its longest axis; handle: beyond ``hi``."""
    axis = int(np.argmax(np.ptp(model.positions, axis=0)))
    f_max, h_min = np.ones(3), np.zeros(3)
    f_max[axis], h_min[axis] = lo, hi
    fixed = select(model, [Box((0, 0, 0), tuple(f_max))], "relative")
    handle = select(model, [Box(tuple(h_min), (1, 1, 1))], "relative")
    return fixed, handle


def rings_of(adj, fixed, handle, count=3):
    try:
        return boundary_rings(adj, fixed, handle, count)
    except RegionError as exc:
        return str(exc)


def assert_same_rings(model: PointModel, fixed, handle, neighbors=10):
    cloud = PointModel(positions=model.positions)  # as a point cloud, whatever the file holds
    full = rings_of(adjacency(cloud, neighbors), fixed, handle)
    adj = region_adjacency(cloud, fixed, handle, neighbors, 4)
    band = rings_of(adj, fixed, handle)
    local = band_adjacency(cloud, fixed, handle, neighbors, 4)  # what layout() uses
    np.testing.assert_array_equal(neighbours_of(local, handle), neighbours_of(adj, handle))
    assert str(rings_of(local, fixed, handle)) == str(band)
    if isinstance(full, str) or isinstance(band, str):
        assert full == band
        return
    for a, b, c in zip(full, band, rings_of(local, fixed, handle), strict=True):
        for x, y, z in zip(a, b, c, strict=True):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(y, z)
            assert z.dtype == np.int64


@pytest.mark.parametrize("name", ["scans/armadillo_oriented.ply", "scans/head_surfels.ply",
                                  "scans/bunny.ply", "scans/lidar_terrain_522k.ply",
                                  "splats/guitar_3dgs_sh0.ply"])
def test_border_graph_rings_equal_whole_graph_rings_on_shared_scans(name):
    model = load(shared_file(name))
    assert_same_rings(model, *slab_edit(model))


def test_border_graph_rings_with_varying_density_and_outliers():
    """Dense and sparse parts, isolated outliers: the hop expansion still finds every ring."""
    model = bumpy_bar(30_000, seed=3)
    rng = np.random.default_rng(4)
    keep = rng.random(model.n_points) > 0.8 * (model.positions[:, 0] > 2.0)  # sparse half
    pts = model.positions[keep]
    outliers = rng.uniform(pts.min(0), pts.max(0), size=(40, 3)) * [1, 3, 3]
    cloud = PointModel(positions=np.vstack([pts, outliers]))
    for lo, hi in ((0.3, 0.8), (0.45, 0.55)):
        assert_same_rings(cloud, *slab_edit(cloud, lo, hi))


def test_border_band_holds_every_point_near_another_label():
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 1, size=(20_000, 3))
    labels = (pts[:, 0] > 0.5).astype(np.int8)
    band = border_band(pts, labels, 0.05)
    near = np.abs(pts[:, 0] - 0.5) <= 0.05
    assert band[near].all()
    assert band.sum() < 0.5 * len(pts)  # and not the whole model
