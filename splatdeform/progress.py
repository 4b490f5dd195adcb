"""Progress through tqdm only: a tqdm bar on a terminal, and on a log or a pipe a tqdm whose
every display is one plain line (:class:`LineBar`). tqdm decides when to show progress in both
cases (``mininterval`` seconds apart); the callers only say what a line reads.

Users: the streamed passes (:class:`splatdeform.edit.stream.progress.Progress`: a line at most
every 2 s, then a closing line) and batch runs (a line per scan).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from tqdm import tqdm


class _Nowhere:
    """The file a :class:`LineBar` hands tqdm: its bar drawing (carriage returns) goes nowhere."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


class LineBar(tqdm):
    """A tqdm for logs and pipes: each display tqdm decides on (``mininterval`` seconds apart,
    every update with the default ``miniters=1``) is one line, ``line(self.format_dict)``, given
    to ``sink``; ``line`` returning None writes nothing. Nothing is written at the start (no
    progress yet) or at :meth:`close`, and no redrawn bar, carriage return or monitor thread."""

    monitor_interval = 0  # no TMonitor thread: lines are written from update() only

    def __init__(self, *, line: Callable[[dict[str, Any]], str | None],
                 sink: Callable[[str], None], **kwargs: Any) -> None:
        self._line, self._sink = line, sink
        kwargs.setdefault("miniters", 1)
        super().__init__(file=_Nowhere(), leave=False, **kwargs)
        self._time = time.perf_counter  # monotonic: a clock set back must not hold a line back
        self.reset(total=self.total)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        if msg is None and self.n:  # not the first draw (n = 0) nor close's clearing (msg='')
            text = self._line(self.format_dict)
            if text is not None:
                self._sink(text)
        return True


__all__ = ["LineBar", "tqdm"]
