"""``gaussians.split: auto`` on streamed and Dask edits (issue 46 item 3): the split test pass
decides as the in-memory apply does (the growth cap over the whole file), the PLY header counts
the children, and the output is the in-memory file byte for byte (children in place of their
parents' rows and after every original row, in the same order); no temporary left behind, no
partial output on an error."""

from __future__ import annotations

from pathlib import Path

import distributed
import numpy as np
import pytest

from data_tools.synth import gaussian_bar
from splatdeform.cli import main
from splatdeform.edit.config import parse_edit
from splatdeform.edit.run import run_edit
from splatdeform.edit.stream import run_stream
from splatdeform.errors import ProcessingError
from splatdeform.io import load, save

N = 8_000
CHUNK = 1_500   # chunks that do not divide the file, split parents in most of them


def _edit(**gaussians) -> dict:
    return {"input": "x.ply", "output": "y.ply",
            "regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.4, 1, 1]}}],
                        "handle": [{"box": {"min": [0.6, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": {"pivot": [0.6, 0.5, 0.5],
                                     "rotate": {"axis": [0, 0, 1], "degrees": 90}}},
            "fit": {"tolerance": 2e-3, "max_centers": 600}, "gaussians": gaussians}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A Gaussian bar (SH degree 1) with splats big enough to split, bent 90 degrees; the
    in-memory output (split on, the default) as mem.ply."""
    folder = tmp_path_factory.mktemp("stream_split")
    model = gaussian_bar(N, sh_degree=1, seed=2)
    model.gaussians.scale_log += np.float32(np.log(4.0))
    save(model, folder / "x.ply")
    mem = run_edit(parse_edit(_edit(), "test"), folder, output=folder / "mem.ply")
    assert mem.stats["split_splats"] > 0
    return folder


@pytest.mark.parametrize("block", [None, 8])   # 8: a chunk's children in blocks of 8
def test_streamed_split_equals_in_memory_byte_for_byte(scene: Path, block, monkeypatch
                                                       ) -> None:
    from splatdeform.edit.stream import split as ss

    if block:
        monkeypatch.setattr(ss, "CHILD_BLOCK", block)
    chunk = CHUNK
    mem = run_edit(parse_edit(_edit(), "test"), scene, output=scene / "mem2.ply")
    result = run_stream(parse_edit(_edit(), "test"), scene, output=scene / "st.ply",
                        chunk=chunk, quiet=True)
    for key in ("split_splats", "split_children", "split_capped"):
        assert result.stats[key] == mem.stats[key], key
    assert mem.stats["split_capped"] > 0   # the cap binds: it must look at the whole file
    assert (scene / "st.ply").read_bytes() == (scene / "mem.ply").read_bytes()
    grown = load(scene / "st.ply").n_points
    assert grown == N + mem.stats["split_children"] - mem.stats["split_splats"] > N
    assert not [p for p in scene.iterdir() if p.name.startswith(".")]  # no spill left


def test_streamed_split_off_keeps_the_count(scene: Path, capsys) -> None:
    """``split: off`` streams the count unchanged and runs no split test."""
    result = run_stream(parse_edit(_edit(split="off"), "test"), scene,
                        output=scene / "off.ply", chunk=CHUNK, quiet=False)
    assert load(scene / "off.ply").n_points == N and "split_splats" not in result.stats
    assert "split test" not in capsys.readouterr().err


def test_cli_streams_and_splits_under_a_small_budget(scene: Path, capsys) -> None:
    """``deform --memory-budget``: streamed (the progress names the split test), the summary
    counts the children, the file equals the in-memory one."""
    import yaml

    cfg = scene / "edit.yaml"
    cfg.write_text(yaml.safe_dump(dict(_edit(), output="cli.ply")))
    assert main(["deform", str(cfg), "--memory-budget", "64MB"]) == 0
    captured = capsys.readouterr()
    assert "streaming 8,000 points" in captured.out
    assert "split test" in captured.err
    assert "splats split" in captured.out and "not applied" not in captured.out
    assert (scene / "cli.ply").read_bytes() == (scene / "mem.ply").read_bytes()


def test_a_failing_chunk_leaves_no_output(scene: Path, monkeypatch) -> None:
    """An error in pass 5 after children were spilled: no output, no spill file."""
    from splatdeform.edit.stream import split as ss

    calls = []
    real = ss.chunk_children

    def fail_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ProcessingError("boom")
        return real(*args, **kwargs)

    monkeypatch.setattr(ss, "chunk_children", fail_second)
    with pytest.raises(ProcessingError, match="boom"):
        run_stream(parse_edit(_edit(), "test"), scene, output=scene / "bad.ply", chunk=CHUNK,
                   quiet=True)
    assert not (scene / "bad.ply").exists()
    assert not [p for p in scene.iterdir() if p.name.startswith(".")]


def test_header_count_is_checked(scene: Path) -> None:
    """The PLY chunk writer refuses to close a file whose header counts more vertices than
    were written (a wrong split count can never leave a short file)."""
    from splatdeform.io.chunks import map_chunks
    from splatdeform.io.ply import PlyChunks

    src = PlyChunks(scene / "x.ply")
    with pytest.raises(ProcessingError, match="header counts"):
        map_chunks(src, scene / "short.ply", lambda a, b: src.encode(src.read(a, b)), CHUNK,
                   extra=3)
    assert not (scene / "short.ply").exists()


def test_dask_split_equals_in_memory(scene: Path) -> None:
    """Two worker processes: the split test and the parts (children parts included) on Dask;
    the assembled file is the in-memory one."""
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
    with distributed.Client(cluster) as client:
        result = run_stream(parse_edit(_edit(), "test"), scene, output=scene / "dask.ply",
                            chunk=CHUNK, quiet=True, client=client)
    cluster.close()
    assert result.stats["split_splats"] > 0
    assert (scene / "dask.ply").read_bytes() == (scene / "mem.ply").read_bytes()
    assert not [p for p in scene.iterdir() if p.name.startswith(".")]


def test_reuse_splits_like_without_it(scene: Path) -> None:
    """``--reuse`` (a stored basis, written then read back): the split test, the sigma points
    and the children go one-shot through the same backend as a run without it, so the same
    splats split and every appended child is byte-identical; the unsplit rows differ only by
    the stored basis's rounding, as they always have."""
    from splatdeform.io.ply import read_ply

    cache = scene / "cache.npz"
    mem = read_ply(scene / "mem.ply").element("vertex").data
    for name in ("reuse1.ply", "reuse2.ply"):   # computed and saved, then loaded
        result = run_edit(parse_edit(_edit(), "test"), scene, output=scene / name,
                          reuse=cache)
        out = read_ply(scene / name).element("vertex").data
        assert out.shape == mem.shape and result.stats["split_splats"] > 0
        assert np.array_equal(out[N:], mem[N:])
        pos = [np.stack([d[c] for c in "xyz"], axis=1).astype(float) for d in (out, mem)]
        assert np.abs(pos[0] - pos[1]).max() < 1e-6 * np.ptp(pos[1], axis=0).max()
    assert (scene / "reuse1.ply").read_bytes() == (scene / "reuse2.ply").read_bytes()


def test_render_draws_the_split_file(scene: Path) -> None:
    """``deform --render`` (render_result) on a split result draws the written model,
    children included, framed with the input as one scene: the same pixels as rendering the
    input and the written file together; the streamed result's image draws its (split)
    output file the same way."""
    from PIL import Image

    from splatdeform.edit.images import edit_view, render_result
    from splatdeform.render import render_comparison

    def read_png(path: Path) -> np.ndarray:
        return np.asarray(Image.open(path).convert("RGB"))

    cfg = parse_edit(dict(_edit(), render={"size": [320, 160]}), "test")
    result = run_edit(cfg, scene, output=scene / "r.ply")
    assert result.deformed.n_points > N
    render_result(result, cfg, scene / "r.png")
    files = render_comparison(load(scene / "x.ply"), load(scene / "r.ply"), None,
                              edit_view(cfg), one_scene=True)
    assert np.array_equal(read_png(scene / "r.png"), files)
    unsplit = run_edit(parse_edit(dict(_edit(split="off"), render={"size": [320, 160]}),
                                  "test"), scene, output=scene / "u.ply")
    render_result(unsplit, cfg, scene / "u.png")
    assert not np.array_equal(read_png(scene / "u.png"), files)   # the children show
    streamed = run_stream(cfg, scene, output=scene / "rs.ply", chunk=CHUNK, quiet=True)
    render_result(streamed, cfg, scene / "rs.png", input_path=scene / "x.ply")
    assert np.array_equal(read_png(scene / "rs.png"), files)


def test_streamed_field_apply_splits_like_in_memory(scene: Path) -> None:
    """``apply FIELD MODEL`` streamed (``--memory-budget 64MB``) splits by the field's
    ``gaussians.split`` as the in-memory apply does: the same file byte for byte (and the one
    ``deform`` wrote)."""
    import yaml

    cfg = scene / "field_edit.yaml"
    cfg.write_text(yaml.safe_dump(dict(_edit(), output="fd.ply")))
    assert main(["deform", str(cfg), "--save-field", str(scene / "f.npz"), "--quiet"]) == 0
    assert main(["apply", str(scene / "f.npz"), str(scene / "x.ply"), "-o",
                 str(scene / "fm.ply")]) == 0
    from splatdeform.field_apply import apply_file
    from splatdeform.memory import parse_size

    _, streamed = apply_file(scene / "f.npz", scene / "x.ply", scene / "fs.ply",
                             budget=parse_size("64MB"))
    assert streamed
    assert load(scene / "fm.ply").n_points > N
    assert (scene / "fs.ply").read_bytes() == (scene / "fm.ply").read_bytes()
    assert (scene / "fm.ply").read_bytes() == (scene / "fd.ply").read_bytes()
    assert not [p for p in scene.iterdir() if p.name.startswith(".")]
