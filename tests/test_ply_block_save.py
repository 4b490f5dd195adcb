"""A binary PLY save builds its vertex records a block at a time (issue 45: no whole copy of
the vertex element on top of the model): the same bytes as the whole element
(``write_ply(source_for_save(model))``), and the same refusal, for every kind of file the
shared data has (big-endian, extra elements, triangle strips, 3DGS with SH, surfels), for
models made in memory (double positions, faces), deformed models and blocks of a few rows."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

import splatdeform as sd
from data_tools.synth import bumpy_bar, gaussian_bar
from splatdeform.errors import FormatError
from splatdeform.io import ply
from splatdeform.io.ply_format import write_ply

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
FILES = ["edge_cases/horse_big_endian.ply", "edge_cases/pepper_extra_elements.ply",
         "edge_cases/igea_tristrips.ply", "splats/guitar_3dgs_sh0.ply",
         "splats/tile_3dgs_sh3.ply", "scans/head_surfels.ply", "scans/bunny_res2.ply"]


def _both(model, text=None) -> tuple[bytes, bytes]:
    """(the block-wise save, the whole element) of ``model``."""
    blocks, whole = io.BytesIO(), io.BytesIO()
    ply.write_model(model, blocks, text=text)
    write_ply(ply.source_for_save(model), whole, text=text)
    return blocks.getvalue(), whole.getvalue()


def _moved(model):
    """``model`` with its geometry and attributes changed the way a deformation changes them
    (positions, normals, colours, 3DGS scales / rotations / SH / opacity on some rows)."""
    out = model.copy()
    rng = np.random.default_rng(7)
    out.positions[::3] += rng.normal(scale=0.01, size=out.positions[::3].shape)
    if out.normals is not None:
        out.normals[::5] = out.normals[::5][:, [1, 2, 0]]
    g = out.gaussians
    if g is not None:
        g.scale_log[::4] += 0.1
        g.rotation[::6] = g.rotation[::6][:, [1, 0, 3, 2]]
        if g.sh_rest is not None and g.sh_rest.size:
            g.sh_rest[::7] *= 0.5
        if g.opacity is not None:
            g.opacity[::9] += 0.25
    return out


@pytest.fixture(params=[64, 4096, 1 << 22])
def block_bytes(request, monkeypatch):
    """Blocks of a few rows (a row split across none), a few blocks, one block."""
    monkeypatch.setattr(ply, "SAVE_BLOCK_BYTES", request.param)
    return request.param


@pytest.mark.parametrize("name", FILES)
def test_shared_files_same_bytes(name, block_bytes):
    model = sd.load(SHARED / name)
    for m in (model, _moved(model)):
        blocks, whole = _both(m)
        assert blocks == whole
        blocks, whole = _both(m, text=False)
        assert blocks == whole


def test_models_made_in_memory(block_bytes):
    """No source: double positions, colours, faces (the face element after the vertices)."""
    bar = bumpy_bar(3000, seed=2)
    splats = gaussian_bar(2000, sh_degree=1, seed=3)
    mesh = sd.load(SHARED / "edge_cases/igea_tristrips.ply")
    mesh = sd.PointModel(positions=mesh.positions.copy(), faces=mesh.faces)
    for m in (bar, _moved(bar), splats, _moved(splats), mesh):
        blocks, whole = _both(m)
        assert blocks == whole and len(blocks) > 0
    empty = sd.PointModel(positions=np.zeros((0, 3)))
    assert _both(empty)[0] == _both(empty)[1]


def test_ascii_keeps_the_whole_path(tmp_path):
    """An ascii save (or an ascii source) is written as before: the kept text of the rows."""
    bar = bumpy_bar(500, seed=4)
    path = tmp_path / "bar.ply"
    sd.save(bar, path, text=True)
    model = sd.load(path)
    for m in (model, _moved(model)):
        blocks, whole = _both(m)
        assert blocks == whole and blocks.startswith(b"ply\nformat ascii")


def test_a_deformed_scan_through_save(tmp_path, block_bytes):
    """A real edit, saved through sd.save: the file holds the whole element's bytes."""
    model = sd.load(SHARED / "edge_cases/horse_big_endian.ply")
    lo, hi = model.positions.min(axis=0), model.positions.max(axis=0)
    cut = lo + (hi - lo) * [0.3, 1, 1]
    start = lo + (hi - lo) * [0.7, 0, 0]
    fixed = sd.select(model, [sd.Box(min=lo - 1, max=cut)])
    handle = sd.select(model, [sd.Box(min=start, max=hi + 1)])
    d = sd.prepare_handle(model, fixed, handle, backend="numpy")
    up = sd.compose_transform(pivot=hi, translate=(0, 0.05 * (hi - lo)[1], 0))
    bent = sd.apply(d, model, sd.delta_for(d, up), moving_matrix=up)
    sd.save(bent, tmp_path / "bent.ply")
    blocks, whole = _both(bent)
    assert (tmp_path / "bent.ply").read_bytes() == blocks == whole


def _refusal(fn) -> str:
    with pytest.raises(FormatError) as err:
        fn()
    return str(err.value)


def test_same_refusal_before_any_byte():
    """A value that does not fit its column: the whole path's line, and nothing written."""
    model = sd.load(SHARED / "edge_cases/horse_big_endian.ply")
    far = model.copy()
    far.positions[[5, 9]] = 1e300                    # beyond float32, 2 values in x
    far.positions[7, 1] = -1e300
    splats = _moved(sd.load(SHARED / "splats/guitar_3dgs_sh0.ply"))
    sh = splats.gaussians.sh_dc = splats.gaussians.sh_dc.astype(np.float64)
    sh[3, 0] = sh[11, 0] = 1e39                      # changed SH rows beyond float32
    bar = bumpy_bar(200, seed=5)
    bar.colors = np.full((200, 3), 300.0)            # beyond uchar
    for m in (far, splats, bar):
        blocks = io.BytesIO()
        said = _refusal(lambda m=m, b=blocks: ply.write_model(m, b))
        assert said == _refusal(lambda m=m: ply.source_for_save(m))
        assert blocks.getvalue() == b""
    short = model.copy()
    short.positions = short.positions[:-1]
    said = _refusal(lambda: ply.write_model(short, io.BytesIO()))
    assert said == _refusal(lambda: ply.source_for_save(short))
    assert "cannot save it verbatim" in said
