"""The editor's memory budget (``splatdeform edit --memory-budget``).

The editor holds the whole model, its fit and its stored basis (b and grad b of every point) in
memory: it cannot stream. So before anything is read, the model file is judged from its header
(:func:`splatdeform.memory.file_cost`) and the in-memory estimate with a stored basis
(:func:`splatdeform.memory.deform_peak`) goes through the one budget rule
(:func:`splatdeform.memory.choose`): over the budget, the editor is refused with one line naming
the estimate and the budget. The budget: ``--memory-budget``, else the edit YAML's
``memory_budget``, else half the RAM (a cap here too: the editor has no streamed path to fall
back on).
"""

from __future__ import annotations

from pathlib import Path

from splatdeform.edit.config import load_edit

from ..errors import InputError
from ..io import extension_of
from ..memory import budget_bytes, choose, default_budget, deform_peak, file_cost

WHY_NOT = "the editor holds the whole model, its fit and its basis in memory"


def editor_estimate(model: str | Path, neighbors: int = 10,
                    max_centers: int | None = None) -> int:
    """Peak bytes of the editor on ``model`` (interpreter included): the in-memory deform's
    estimate with the basis kept (the page's fit), from the file's header and size only."""
    cost = file_cost(model)
    if max_centers is None:
        return deform_peak(cost, neighbors, stored=True)
    return deform_peak(cost, neighbors, max_centers, stored=True)


def check_budget(path: str | Path, flag: str | int | None = None) -> int:
    """Refuse (InputError, one line) to open MODEL or EDIT.yaml ``path`` when the editor's
    estimate is over the budget: ``flag`` (``--memory-budget``), else the YAML's
    ``memory_budget``, else half the RAM. Returns the estimate in bytes."""
    path = Path(path)
    if extension_of(path) in (".yaml", ".yml"):   # as EditorController.open decides
        cfg = load_edit(path)
        model = path.resolve().parent / cfg.input
        config_value, neighbors, centers = (cfg.memory_budget, cfg.boundary.neighbors,
                                            cfg.fit.max_centers)
    else:
        model, config_value, neighbors, centers = path, None, 10, None
    budget = budget_bytes(flag, config_value)
    name = ("--memory-budget" if flag is not None else
            "memory_budget" if config_value is not None else
            "--memory-budget, default half the RAM")
    need = editor_estimate(model, neighbors, centers)
    choice = choose(need, default_budget() if budget is None else budget, streamable=False,
                    name=model, budget_name=name, why_not=WHY_NOT)
    if choice.mode == "refuse":
        raise InputError(choice.message)
    return need
