"""Models bigger than the memory budget, for rendering: a view-independent sample streamed
from the file in chunks (a seeded uniform choice of points, the same for every camera), so
``render``, ``select -o``, ``deform --render`` (streamed edits included) and batch thumbnails
look at any scan within the budget. The choice of how many points fit is
:func:`splatdeform.memory.render_points` (the one memory estimator)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform import memory
from splatdeform.io import STREAMABLE, open_chunks
from splatdeform.model import PointModel

SEED = 20240524
CHUNK_BYTES = memory.SAMPLE_CHUNK_BYTES   # the budget figures are memory's (sample_sizes)
MIN_SAMPLE = memory.MIN_SAMPLE_POINTS


@dataclass
class RenderInput:
    """A model to render and how many points the file holds (``model.n_points`` < ``total``
    when it is a sample)."""

    model: PointModel
    total: int
    index: np.ndarray | None = None   # (M,) int64 rows of the file the sample holds

    @property
    def sampled(self) -> bool:
        return self.model.n_points < self.total

    def line(self) -> str:
        """'rendered 4,000,000 of 25,900,000 points' for a sample, else ''."""
        if not self.sampled:
            return ""
        return f"rendered {self.model.n_points:,} of {self.total:,} points (memory budget)"


def load_for_render(path: str | Path, budget: int, *, drop_nonfinite: bool = False,
                    share: float = 1.0, explicit: bool = False) -> RenderInput:
    """The whole model when it fits ``budget`` bytes (times ``share``: two models side by side
    take half each), else a streamed uniform sample of as many points as fit. ``explicit``:
    the budget is a cap (``--memory-budget``): a model of a format that cannot be sampled
    whose estimate (from its validated header) exceeds it is refused with one line. The
    header is validated before anything is read (a LAS with a corrupt VLR count is refused
    at once)."""
    from splatdeform.edit.stream import COSTED
    from splatdeform.io import extension_of, load

    path = Path(path)
    limit = int(budget * share) if share < 1 else budget
    ext = extension_of(path)
    if ext not in STREAMABLE:
        if explicit and ext in COSTED and path.is_file():
            cost = memory.file_cost(path)
            need = memory.BASE_BYTES + cost.load_bytes + memory.render_bytes(cost.points,
                                                                             cost.record_bytes)
            choice = memory.choose(need, limit, streamable=False, name=path,
                                   why_not=f"{ext} files cannot be sampled")
            if choice.mode == "refuse":
                from splatdeform.errors import InputError

                raise InputError(choice.message)
        model = load(path, drop_nonfinite=drop_nonfinite)
        return RenderInput(model, model.n_points)
    cost = memory.file_cost(path)
    chunk_bytes, keep = memory.sample_sizes(limit, cost)
    if keep >= cost.points:
        model = load(path, drop_nonfinite=drop_nonfinite)
        return RenderInput(model, model.n_points)
    return sample_file(path, max(keep, memory.MIN_SAMPLE_POINTS), chunk_bytes=chunk_bytes,
                       drop_nonfinite=drop_nonfinite)


def sample_file(path: str | Path, keep: int, seed: int = SEED,
                chunk_bytes: int = memory.SAMPLE_CHUNK_BYTES, *,
                drop_nonfinite: bool = False) -> RenderInput:
    """About ``keep`` points of ``path``, each kept with probability keep / N (seeded: the
    same sample every time, whatever the camera), read chunk by chunk; the model keeps every
    property of the kept points. ``drop_nonfinite``: sampled records with a NaN/Inf coordinate
    or Gaussian attribute are left out (else the model refuses them, as a whole load does)."""
    src = open_chunks(path)
    n = src.n_points
    rng = np.random.default_rng(seed)
    p = min(keep / max(n, 1), 1.0)
    chunk = max(chunk_bytes // max(src.record_bytes, 1), 10_000)
    parts, index = [], []
    for a in range(0, n, chunk):
        b = min(a + chunk, n)
        rows = src.rows(a, b)
        kept = np.flatnonzero(rng.random(b - a) < p)
        if drop_nonfinite:
            kept = kept[~src.nonfinite(rows[kept])]
        parts.append(rows[kept].copy())   # not a view: frees the chunk
        index.append(kept + a)
        del rows
    rows = np.concatenate(parts)
    del parts
    return RenderInput(src.model_of(rows), n, np.concatenate(index))
