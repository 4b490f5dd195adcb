"""'Did you mean' for a mistyped name: the closest allowed names by difflib."""

from __future__ import annotations

import argparse
import difflib
import re
from collections.abc import Iterable


def close_names(word: str, names: Iterable[str], n: int = 1) -> list[str]:
    """The allowed ``names`` closest to ``word`` (difflib ratio 0.6 or more; case-blind), best
    first, at most ``n``."""
    names = [str(x) for x in names]
    by_lower = {x.lower(): x for x in names}
    found = difflib.get_close_matches(str(word).lower(), list(by_lower), n=n, cutoff=0.6)
    return [by_lower[x] for x in found]


def did_you_mean(word: str, names: Iterable[str], quote: bool = True) -> str:
    """`` (did you mean 'rotate'?)`` for the closest of ``names`` to ``word``, or ''."""
    found = close_names(word, names)
    if not found:
        return ""
    return f" (did you mean {found[0]!r}?)" if quote else f" (did you mean {found[0]}?)"


def argparse_hint(parser: argparse.ArgumentParser, message: str) -> str:
    """" (did you mean --render?)" for an unknown flag (of the verb on the command line) or
    an invalid choice; '' when nothing is close."""
    choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
    if choice:
        return did_you_mean(choice[1], (c.strip(" '") for c in choice[2].split(",")))
    if not message.startswith("unrecognized arguments: "):
        return ""
    verbs = next((a.choices for a in parser._actions
                  if isinstance(a, argparse._SubParsersAction)), {})
    verb = next((verbs[w] for w in getattr(parser, "_words", ()) if w in verbs), parser)
    flags = [f for f in verb._option_string_actions if f.startswith("--")]
    for word in message.split(": ", 1)[1].split():
        found = close_names(word.split("=", 1)[0], flags) if word.startswith("-") else []
        if found:
            return f" (did you mean {found[0]}?)"
    return ""
