"""Parts of one-line error messages that name the fix: the nearest valid name, and lists or values cut short.

An error about a name (a config key, a joint, a frame, a bag topic) suggests the valid one nearest to it
(``difflib.get_close_matches``); anything shown from the user's data is cut so the message stays one readable line.
"""
from __future__ import annotations

from difflib import get_close_matches
from typing import Iterable

__all__ = ["did_you_mean", "listing", "nearest", "shorten"]

SHOWN_NAMES = 10             # names a listing shows before "and N more"


def nearest(word: str, choices: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The choice most like ``word`` (``difflib`` ratio at least ``cutoff``), or None."""
    found = get_close_matches(word, list(choices), n=1, cutoff=cutoff)
    return found[0] if found else None


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the choice nearest ``word``, or ``""`` when none is near."""
    found = nearest(word, choices)
    return "" if found is None else f"; did you mean {found!r}?"


def listing(names: Iterable[str], limit: int = SHOWN_NAMES) -> str:
    """``names`` comma-separated, the first ``limit`` of them and how many more."""
    names = list(names)
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def shorten(text: str, limit: int = 40) -> str:
    """``text`` on one line, cut to ``limit`` characters (an ellipsis marks the cut)."""
    line = " ".join(text.split())
    return line if len(line) <= limit else line[:limit - 1] + "…"
