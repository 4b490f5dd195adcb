"""Progress of the long passes on stderr: a tqdm bar when stderr is a terminal, else a plain
line (points done, percent, points per second) at most every few seconds, written by tqdm too
(:class:`splatdeform.progress.LineBar`); a closing line either way. Batch runs use tqdm the same
way (a bar on a terminal, a line per scan otherwise)."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable


def _peak() -> str:
    """', peak RSS N MB' when SPLATDEFORM_SHOW_RSS is set (benchmarks), else ''."""
    if not os.environ.get("SPLATDEFORM_SHOW_RSS"):
        return ""
    import resource

    return f", peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"


class Progress:
    """Reports a pass over ``total`` points at most every ``every`` seconds, and once at the
    end; silent when ``quiet``. ``sink`` receives each line (default: stderr, where a terminal
    gets a tqdm bar instead of the intermediate lines). tqdm drives both (see
    :mod:`splatdeform.progress`)."""

    def __init__(self, name: str, total: int, *, quiet: bool = False, every: float = 2.0,
                 sink: Callable[[str], None] | None = None) -> None:
        self.name, self.total, self.quiet, self.every = name, max(int(total), 1), quiet, every
        self.sink = sink or (lambda line: print(line, file=sys.stderr, flush=True))
        self.done = 0
        self.t0 = time.perf_counter()
        self.bar = None
        if quiet:
            return
        from splatdeform.progress import LineBar, tqdm

        if sink is None and sys.stderr.isatty():
            self.bar = tqdm(total=self.total, desc=name, unit=" points", unit_scale=True,
                            mininterval=min(every, 0.5), dynamic_ncols=True, leave=False)
        else:
            self.bar = LineBar(total=self.total, mininterval=every, line=self._line,
                               sink=self.sink)

    def _line(self, bar: dict) -> str | None:
        """The intermediate line (none once every point is done: the closing line says it)."""
        done = bar["n"]
        if done >= self.total:
            return None
        rate = done / max(bar["elapsed"], 1e-9)
        return (f"{self.name}: {done:,}/{self.total:,} points "
                f"({100.0 * done / self.total:.0f}%, {rate / 1e6:.2f} M points/s)")

    def rate(self) -> float:
        return self.done / max(time.perf_counter() - self.t0, 1e-9)

    def update(self, points: int) -> None:
        self.done += int(points)
        if self.bar is not None:
            self.bar.update(int(points))

    def finish(self) -> float:
        """Print the closing line; returns the pass's seconds."""
        seconds = time.perf_counter() - self.t0
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        if not self.quiet:
            self.sink(f"{self.name}: {self.done:,} points in {seconds:.1f} s "
                      f"({self.rate() / 1e6:.2f} M points/s)" + _peak())
        return seconds
