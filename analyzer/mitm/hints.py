"""A guess at what a word of a fault SPEC that is not taken was meant to be.

A SPEC is typed in a hurry, on a command line or in the TUI; before ``text:``
was needed, a word without a colon was text to find, so a slip such as
``every2`` or ``delay:200 ms`` made a fault that silently never acted.  Now
such a word is an error, and this module finds the word most likely meant,
for the error to suggest (``did you mean every:2?``).  It knows no table of
its own: the SPEC grammar (``spec.py``) passes its keys and their values.
"""

from __future__ import annotations

import difflib
from collections.abc import Collection, Mapping

# what follows a number in a duration or a rate: typed apart from it, it is still its unit
UNITS = frozenset({"ns", "us", "ms", "s", "m", "b/s", "kb/s", "kib/s", "mb/s", "mib/s"})
_CLOSE = 0.6  # how alike (difflib's ratio) a word and a known one must be to suggest it


def did_you_mean(word: str, previous: str, keys: Collection[str], values: Mapping[str, Collection[str]],
                 bare: Collection[str] = ()) -> str | None:
    """The SPEC word most likely meant by ``word`` (which no rule takes), or
    None: a unit typed apart from its number (``200 ms`` after ``delay:200``),
    a key run into its value (``every2``, ``dirs2c``), a known value without its
    key or misspelt (``s2c``, ``respones``), a misspelt key (``evry:2``), or a
    misspelt word that stands alone (``bare``: ``violation``).  ``previous``
    is the word before it; ``values`` the known values of some keys."""
    lower = word.lower()
    if lower in UNITS and previous[-1:].isdigit():
        return previous + word
    key, sep, value = lower.partition(":")
    if sep:
        close = difflib.get_close_matches(key, keys, n=1, cutoff=_CLOSE)
        return f"{close[0]}:{word.partition(':')[2]}" if close and value else None
    for known in sorted(keys, key=len, reverse=True):  # the longest first: "conn" before "c"
        rest = word[len(known):].lstrip("=-_")
        if lower.startswith(known) and rest and (rest[0].isdigit() or rest.lower() in values.get(known, ())):
            return f"{known}:{rest}"
    for known, choices in values.items():
        close = difflib.get_close_matches(lower, choices, n=1, cutoff=_CLOSE)
        if close:
            return f"{known}:{close[0]}"
    close = difflib.get_close_matches(lower, bare, n=1, cutoff=_CLOSE)
    return close[0] if close else None
