"""The paths of one run, planned once (issue 44): every verb that writes (``deform``
through :class:`~splatdeform.edit.plan.EditPlan`, ``select``, ``apply``, ``convert``, ``view``
and the editor's Save) lists what it reads and writes and asks :func:`plan_io`
before any work. Two outputs that are one file (another spelling, a link) or an output that is
an input are refused there with one line naming both (:func:`splatdeform.io.atomic.check_io_paths`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from splatdeform.io import atomic
from splatdeform.io.atomic import Named


@dataclass(frozen=True)
class IoPlan:
    """What one run reads and writes, as (label, path) pairs in the order given: the labels
    name the argument or config key (``-o/--output``, ``--save-field``, ``input``)."""

    inputs: tuple[tuple[str, Path], ...]
    outputs: tuple[tuple[str, Path], ...]

    def output(self, label: str) -> Path | None:
        """The output planned under ``label`` (the first), None when there is none."""
        return next((p for what, p in self.outputs if what == label), None)


def plan_io(inputs: Iterable[Named], outputs: Iterable[Named]) -> IoPlan:
    """Check every input and output of a run together, before any work (paths None are not
    asked for and are left out), and return them as an :class:`IoPlan`. Raises InputError
    naming both paths when two outputs are one file or an output is an input."""
    ins = tuple((what, Path(p)) for what, p in inputs if p is not None)
    outs = tuple((what, Path(p)) for what, p in outputs if p is not None)
    atomic.check_io_paths(ins, outs)   # by the module: the one check, wherever it is asked
    return IoPlan(ins, outs)
