"""PCD binary_compressed written by splatdeform (LZF, issue 34 item 5) read by an independent
reader, pypcd4 (a dev dependency): PCL's own compressed file loaded and written back, and a
generated model saved with ``pcd_data="binary_compressed"``, give the same values."""

from __future__ import annotations

import numpy as np
import pypcd4  # (a dev dependency: a missing one fails, never skips)
from conftest import shared_file

from splatdeform.io import load, pcd, save
from splatdeform.io.options import writing


def _same(path, source: pcd.PcdSource) -> None:
    theirs = pypcd4.PointCloud.from_path(str(path))
    assert theirs.metadata.data == "binary_compressed"
    assert list(theirs.fields) == source.fields
    assert theirs.points == len(source.data)
    array = theirs.numpy()
    for i, name in enumerate(source.fields):
        ours = source.data[name].astype(np.float64)
        np.testing.assert_array_equal(array[:, i].astype(np.float64), ours.reshape(len(ours)),
                                      err_msg=name)


def test_pcl_compressed_file_written_back_reads_in_pypcd4(tmp_path):
    src = shared_file("pcd/osd_learn0_organized.pcd")
    out = tmp_path / "back.pcd"
    save(load(src, drop_nonfinite=True), out)   # its NaN (invalid) points dropped
    source, _ = pcd.read_source(out)
    assert source.encoding == "binary_compressed"
    assert out.stat().st_size <= 1.05 * src.stat().st_size
    _same(out, source)


def test_generated_model_saved_compressed_reads_in_pypcd4(tmp_path):
    points = np.random.default_rng(5).normal(size=(2000, 3))
    source = pcd.PcdSource(header=[("VERSION", "0.7")], fields=["x", "y", "z"],
                           sizes=[4, 4, 4], types=["F", "F", "F"], counts=[1, 1, 1],
                           width=len(points), height=1, encoding="binary",
                           data=np.rec.fromarrays(points.astype(np.float32).T,
                                                  names="x,y,z"))
    plain = tmp_path / "plain.pcd"
    with open(plain, "wb") as f:
        pcd.write_source(source, f)
    model = load(plain)
    out = tmp_path / "x.pcd"
    with writing(pcd_data="binary_compressed"):
        save(model, out)
    back, _ = pcd.read_source(out)
    assert back.encoding == "binary_compressed"
    _same(out, back)
    np.testing.assert_array_equal(np.asarray(load(out).positions), np.asarray(model.positions))
