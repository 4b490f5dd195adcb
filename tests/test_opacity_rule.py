"""One opacity rule for every reader (issue 47 item 3): an 8-bit opacity of 255 / 0 is alpha
1 / 0, a logit of +inf / -inf, in ``.splat`` (which read byte 0 as alpha 0.5/255), SOG, SPZ,
``.ksplat`` and compressed PLY alike; a plain PLY written from such a file holds the finite
logits +-13.8155 (alpha 1 -+ 1e-6, splat-transform's own clamp) that splat-transform's ``-N``
keeps (it drops a -inf opacity), and those become byte 255 / 0 again in every quantised
writer. A PLY input's own +-inf logits are kept (tests/test_opacity_inf.py)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from splat_oracle import scene_source

from data_tools import ksplat_oracle, splat_transform
from splatdeform.io import load, save
from splatdeform.io.ply_format import write_ply
from splatdeform.io.sog_order import order
from splatdeform.io.splats import FINITE_OPACITY, sigmoid

QUANTISED = (".splat", ".sog", ".spz", ".compressed.ply")
ENDS = [np.inf, -np.inf, 30.0, -30.0]          # alpha 1, 0, and logits that round to them
WANT = np.array([np.inf, -np.inf, np.inf, -np.inf])


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _scene(tmp_path, n: int = 300):
    source = scene_source(n, 1, 4)
    data = source.element("vertex").data
    data["opacity"][:len(ENDS)] = ENDS
    path = tmp_path / "scene.ply"
    with open(path, "wb") as f:
        write_ply(source, f)
    return path


def test_every_reader_reads_the_ends_alike(tmp_path) -> None:
    model = load(_scene(tmp_path))
    decoded = {}
    for ext in QUANTISED:
        out = tmp_path / f"s{ext}"
        with order("keep"):   # SOG in the input's order (by default: Morton order)
            save(model, out)
        opacity = load(out).gaussians.opacity
        assert np.array_equal(opacity[:len(ENDS)], WANT), ext
        decoded[ext] = opacity
    # the other splats: the same byte gives the same logit in every format that keeps order
    alpha = np.clip(np.round(sigmoid(model.gaussians.opacity) * 255), 0, 255)
    for ext in (".splat", ".sog", ".spz"):
        inner = (alpha > 0) & (alpha < 255)
        want = np.log(alpha[inner] / 255 / (1 - alpha[inner] / 255))
        np.testing.assert_allclose(decoded[ext][inner], want, rtol=1e-6, atol=1e-6,
                                   err_msg=ext)


def test_ksplat_reads_the_ends_alike(tmp_path) -> None:
    try:
        ksplat_oracle.install()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"the .ksplat oracle is required: {exc}")
    src = _scene(tmp_path, 50)
    out = ksplat_oracle.convert(src, tmp_path / "s.ksplat", 0, 1)
    ours, theirs = load(src), load(out)
    # the converter reorders splats: match them by position; it writes alpha 1 / 0 as byte
    # 255 / 0 (a logit of 30 it rounds down to byte 254: its encoding, not the reader's)
    order = [int(np.argmin(np.linalg.norm(theirs.positions - p, axis=1)))
             for p in ours.positions[:2]]
    assert np.array_equal(theirs.gaussians.opacity[order], WANT[:2])


def test_plain_ply_from_a_quantised_file_is_kept_by_splat_transform(tmp_path) -> None:
    try:
        splat_transform.install()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"splat-transform is required: {exc}")
    model = load(_scene(tmp_path))
    with order("keep"):   # the input's order (by default: Morton order)
        save(model, tmp_path / "s.sog")
    plain = tmp_path / "plain.ply"
    save(load(tmp_path / "s.sog"), plain)
    back = load(plain)
    opacity = back.gaussians.opacity
    assert np.isfinite(opacity).all()
    assert np.array_equal(opacity[:len(ENDS)],
                          np.float32([FINITE_OPACITY, -FINITE_OPACITY] * 2))
    kept = tmp_path / "kept.ply"
    splat_transform.run("-w", "-q", str(plain), "-N", str(kept))
    assert load(kept).n_points == back.n_points
    # splat-transform's own filter drops our -inf (alpha 0) splats: why the PLY is finite
    raw = tmp_path / "raw.ply"
    save(model, raw)   # a PLY input's own +-inf kept
    dropped = tmp_path / "dropped.ply"
    splat_transform.run("-w", "-q", str(raw), "-N", str(dropped))
    assert load(dropped).n_points < model.n_points
    # and quantised again, the finite ends are byte 255 / 0: +-inf once more
    for ext in QUANTISED:
        again = tmp_path / f"again{ext}"
        with order("keep"):
            save(back, again)
        assert np.array_equal(load(again).gaussians.opacity[:len(ENDS)], WANT), ext
