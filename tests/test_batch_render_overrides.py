"""Batch ``overrides[i].render``: the batch ``render:`` keys merged into the batch's own per
matching scan (a different up axis or colour for some scans' thumbnails), validated with the
key named, and used by the real worker."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bar_edit
from PIL import Image

from data_tools.make_archive import make_scans
from splatdeform.batch import load_batch
from splatdeform.batch.worker import process_scan
from splatdeform.errors import ConfigError

EDIT = bar_edit(fit={"tolerance": 1e-3, "max_centers": 400})


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("batch_render")
    make_scans(root, 4, 3000)
    return root


def write(path: Path, **keys) -> Path:
    path.write_text(yaml.safe_dump({"edit": EDIT, "scans": "scans/*.ply", **keys}))
    return path


def test_override_render_merges_into_the_batch_render(scans: Path) -> None:
    cfg = write(scans / "b.yaml", output_dir="out_a",
                render={"size": [128, 96], "azimuth": 10.0, "up": "+y"},
                overrides=[{"match": "sphere_*", "render": {"up": "+z", "color": "elevation",
                                                            "elevation": 45.0}}])
    jobs = {Path(j.scan.path).stem: j for j in load_batch(cfg).jobs}
    sphere = next(k for k in jobs if k.startswith("sphere"))
    bar = next(k for k in jobs if k.startswith("bar"))
    assert jobs[bar].render["up"] == "+y" and jobs[bar].render["color"] is None
    got = jobs[sphere].render
    assert (got["up"], got["color"], got["elevation"]) == ("+z", "elevation", 45.0)
    assert (got["size"], got["azimuth"]) == ([128, 96], 10.0)   # the batch's own keys kept
    assert jobs[sphere].config_hash != jobs[bar].config_hash
    # the real worker draws the merged thumbnail
    row = process_scan(jobs[sphere])
    assert row["status"] == "ok", row
    img = np.asarray(Image.open(jobs[sphere].png).convert("RGB"))
    assert img.shape[1] == 2 * 128 and np.any(img[20:] < 240)


def test_override_render_alone_gives_those_scans_thumbnails(scans: Path) -> None:
    cfg = write(scans / "c.yaml", output_dir="out_c",
                overrides=[{"match": "bar_*", "render": {"size": [64, 64]}}])
    jobs = load_batch(cfg).jobs
    assert {j.png is not None for j in jobs if "bar" in j.scan.name} == {True}
    assert {j.png is None for j in jobs if "sphere" in j.scan.name} == {True}


@pytest.mark.parametrize(("override", "key"), [
    ({"upp": "+z"}, "overrides[0].render.upp"),
    ({"color": "purple"}, "overrides[0].render.color"),
    ({"size": [1]}, "overrides[0].render.size"),
])
def test_bad_override_render_names_the_key(scans: Path, override, key) -> None:
    cfg = write(scans / "bad.yaml", output_dir="out_bad",
                overrides=[{"match": "*", "render": override}])
    with pytest.raises(ConfigError) as info:
        load_batch(cfg)
    assert info.value.key.startswith(key), str(info.value)   # e.g. render.size[0]
