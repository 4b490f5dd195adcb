"""One stats builder (splatdeform/edit/result.py) for every path: an in-memory edit and the
same edit streamed report the same figures under the same keys, each path adding only its own
extras; ``run_edit`` takes typed streaming options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from data_tools.synth import bumpy_bar
from splatdeform.edit.config import load_edit
from splatdeform.edit.result import fit_stats, format_report
from splatdeform.edit.run import run_edit
from splatdeform.edit.stream import StreamOptions, run_stream
from splatdeform.errors import ConfigError
from splatdeform.io import save

EDIT = """\
input: bar.ply
output: mem.ply
regions:
  units: relative
  fixed: [{box: {min: [0, 0, 0], max: [0.2, 1, 1]}}]
  handle: [{box: {min: [0.8, 0, 0], max: [1, 1, 1]}}]
handle: {transform: {translate: [0, 0.15, 0.05]}}
fit: {tolerance: 1.0e-3}
"""
IN_MEMORY_ONLY = {"refused_splats"}
STREAMED_ONLY = {"border_points", "chunk"}


@pytest.fixture(scope="module")
def edit(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("result")
    save(bumpy_bar(20_000, seed=11), folder / "bar.ply")
    path = folder / "edit.yaml"
    path.write_text(EDIT)
    return folder, path


def test_in_memory_and_streamed_stats_share_their_keys(edit) -> None:
    folder, path = edit
    cfg = load_edit(path)
    mem = run_edit(cfg, folder)
    streamed = run_stream(cfg, folder, output=folder / "st.ply", chunk=3_000, quiet=True)
    assert mem.model is not None and streamed.model is None
    assert set(mem.stats) - IN_MEMORY_ONLY == set(streamed.stats) - STREAMED_ONLY
    assert set(fit_stats(mem.deformation, 1, 1)) < set(mem.stats)
    assert IN_MEMORY_ONLY <= set(mem.stats) and STREAMED_ONLY <= set(streamed.stats)
    # the same figures where the two paths do the same work (same rings, same fit)
    for key in ("points", "free_points", "constraints", "kept", "centers", "method",
                "converged", "tolerance"):
        assert mem.stats[key] == streamed.stats[key], key
    assert streamed.stats["constraint_error"] <= 10 * max(mem.stats["constraint_error"], 1e-9)
    # one report for both: same lines up to the figures
    lines = [format_report(r).splitlines() for r in (mem, streamed)]
    assert [s.split()[0] for s in lines[0][:3]] == [s.split()[0] for s in lines[1][:3]]
    assert lines[1][-1] == f"wrote {folder / 'st.ply'}"
    assert np.isfinite(streamed.stats["constraint_error_rel"])


def test_run_edit_takes_typed_stream_options(edit) -> None:
    """Dask with --reuse is refused before any work (no cluster started, no output)."""
    folder, path = edit
    cfg = load_edit(path)
    out = folder / "never.ply"
    with pytest.raises(ConfigError, match="--scheduler/--workers: cannot be combined"):
        run_edit(cfg, folder, output=out, reuse=folder / "r.npz",
                 stream=StreamOptions(workers=2, quiet=True))
    assert not out.exists()
    # over no budget and without Dask the edit runs in memory
    result = run_edit(cfg, folder, output=out, stream=StreamOptions(budget="64GB"))
    assert result.model is not None and out.exists()
    with pytest.raises(ConfigError, match="--memory-budget: expected a size"):
        run_edit(cfg, folder, output=folder / "bad.ply", stream=StreamOptions(budget="lots"))
