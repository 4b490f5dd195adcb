"""What a metaphor kind can take part in: each kind module declares ``CAPABILITIES`` (a
:class:`Capabilities`), and :func:`splatdeform.edit.capable.refusal` is the one query the
pre-flight, streaming and the editor ask (issue 44: the stream-or-not rule had been written
twice, and points edits were refused only after planning)."""

from __future__ import annotations

from dataclasses import dataclass, field

MANY = 2**31  # no limit on the number of entries


@dataclass(frozen=True)
class Capabilities:
    """The most entries of one kind an edit may hold and still take part in each run (0:
    none): ``streams`` (an out-of-core or Dask run), ``reusable`` (``--reuse`` stores and
    reloads its basis), ``editable`` (the editor edits it on the page); ``why``: the refusal
    line per capability; ``keys``: per capability, the config keys whose entries take part
    (absent: every key; e.g. a single ``handle:`` streams, a ``handles:`` list does not)."""

    streams: int = MANY
    reusable: int = MANY
    editable: int = MANY
    why: dict[str, str] = field(default_factory=dict)
    keys: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def refusal(self, entry_keys: list[str], capability: str) -> str:
        """Why entries with these config keys cannot take part in ``capability`` ('' when
        they can)."""
        allowed = self.keys.get(capability)
        if len(entry_keys) > getattr(self, capability) or (
                allowed is not None and any(k not in allowed for k in entry_keys)):
            return self.why[capability]
        return ""
