"""The one query of what an edit can take part in (issue 44): each metaphor kind declares its
:class:`~splatdeform.edit.metaphors.capabilities.Capabilities`; the pre-flight
(:mod:`splatdeform.edit.plan`), streaming (:mod:`splatdeform.edit.stream`) and the editor ask
:func:`refusal` / :func:`stream_refusal` here instead of branching on the config's keys."""

from __future__ import annotations

from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import KINDS


def refusal(cfg: EditConfig, capability: str) -> str:
    """Why this edit cannot take part in ``capability`` (``"streams"``, ``"reusable"``,
    ``"editable"``: a :class:`~splatdeform.edit.metaphors.capabilities.Capabilities` field),
    '' when it can. Asked of every kind the edit holds."""
    for kind in KINDS:
        why = kind.CAPABILITIES.refusal([key for key, _ in kind.entries(cfg)], capability)
        if why:
            return why
    return ""


def stream_refusal(cfg: EditConfig) -> str:
    """Why this edit cannot stream ('' when it can): the metaphors' capabilities, then what
    needs the whole model. The one rule: the pre-flight
    (:func:`splatdeform.edit.stream.edit_choice`) and the stream's reader
    (:func:`splatdeform.edit.stream.run.check_streamable`) both ask it."""
    why = refusal(cfg, "streams")
    if not why and cfg.normals == "estimate":
        why = "normals: estimate needs the whole model"
    return why
