"""``select`` on a scan bigger than the memory budget: the regions streamed (the labels pass of
``deform``'s streaming plan, one byte a point), counts without rings (the rings need the kNN
graph of the whole scan; ``deform`` reports them), and a sampled preview coloured by region."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.edit.config import EditConfig
from splatdeform.edit.selection import RegionCounts, Selection, moving_label
from splatdeform.edit.stream.plan import FIXED, HANDLE, bbox_pass, labels_pass
from splatdeform.edit.stream.run import check_streamable
from splatdeform.edit.stream.sample import RenderInput, load_for_render
from splatdeform.memory import select_chunk, select_preview_budget


def stream_select(cfg: EditConfig, base_dir: Path, budget: int, *, preview: bool = False
                  ) -> tuple[RegionCounts, RenderInput | None, Selection | None]:
    """(counts, the preview sample, its selection) within ``budget`` bytes (None, None
    without ``preview``)."""
    in_path = Path(base_dir) / cfg.input
    src = check_streamable(cfg, in_path, in_path)
    n = src.n_points
    chunk = select_chunk(budget, n, src.record_bytes)
    lo, hi, _, _ = bbox_pass(src, chunk, quiet=True)
    labels, _, _, _ = labels_pass(src, cfg, Path(base_dir), lo, hi, chunk, quiet=True,
                                  max_handle=0)
    fixed, moving = int(np.count_nonzero(labels == FIXED)), int(np.count_nonzero(labels == HANDLE))
    counts = RegionCounts(n, fixed, moving, n - fixed - moving, moving_name=moving_label(cfg))
    if not preview:
        return counts, None, None
    shown = load_for_render(in_path, select_preview_budget(budget, n))
    lab = labels if shown.index is None else labels[shown.index]
    return counts, shown, Selection(lab == FIXED, lab == HANDLE, [], [], counts.moving_name)
