"""The one filter over observed items, shared by ``whiztap cat`` and the TUI,
and its words (``conn:2 dir:c2s kind:response ch:12 since:1.5 until:9
violations`` and free text), as typed in the TUI's filter bar or ``cat --filter``."""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from typing import Any

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Observation

NS = 1_000_000_000


def channel_of(observation: Observation) -> int | None:
    """The channel an item is about, whatever it means (None if it has none)."""
    subject = observation.message or (observation.candidates[0] if observation.candidates else None)
    return getattr(subject, "channel", None)


@dataclass(frozen=True)
class ItemFilter:
    conns: frozenset[int] = frozenset()
    direction: str | None = None
    kinds: frozenset[str] = frozenset()
    channels: frozenset[int] = frozenset()
    since_s: float | None = None
    until_s: float | None = None
    violations_only: bool = False
    text: str = ""  # a substring of the item's escaped bytes or meaning (the TUI's free text)
    interventions: frozenset[str] = frozenset()  # held, injected, ...: judged by the TUI from its marks

    def accepts(self, conn: int, observation: Observation, start_ns: int, late: bool = False) -> bool:
        item = observation.item
        if self.conns and conn not in self.conns:
            return False
        if self.direction and observation.direction != self.direction:
            return False
        if self.kinds and item.kind not in self.kinds:
            return False
        if self.channels and channel_of(observation) not in self.channels:
            return False
        rel = (item.t_end_ns - start_ns) / NS
        if self.since_s is not None and rel < self.since_s:
            return False
        if self.until_s is not None and rel >= self.until_s:
            return False
        if self.violations_only and not (late or observation.violations):
            return False
        if self.text:
            from whiztap.analyzer.protocol.describe import meaning
            from whiztap.analyzer.protocol.text import escape

            needle = self.text.lower()
            return needle in escape(item.raw).lower() or needle in meaning(observation).lower()
        return True


INTERVENTION_WORDS = ("held", "injected", "edited", "dropped", "delayed", "faulted")
"""What the proxy in the middle did to a frame, as filter words (the TUI's mark kinds)."""
FILTER_HELP = ("conn:N[,N]  dir:c2s|s2c  kind:K[,K]  ch:N[,N]  since:S  until:S  violations (or !)  "
               f"{' '.join(INTERVENTION_WORDS)}  and any other words: text in the bytes or the meaning")


class FilterSyntaxError(WhiztapError, ValueError):
    """The filter bar's text does not parse; the message says which word."""


def _ints(key: str, value: str) -> frozenset[int]:
    try:
        return frozenset(int(v) for v in value.split(",") if v)
    except ValueError:
        raise FilterSyntaxError(f"{key}: wants numbers separated by commas, got {value!r}") from None


def _seconds(key: str, value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise FilterSyntaxError(f"{key}: wants seconds from the start, got {value!r}") from None


def parse_word(word: str, options: dict[str, Any]) -> bool:
    """Put one filter word into ``options`` (ItemFilter's fields by name); False
    for a word that is no filter word, which the filter bar takes as free text
    and a fault spec (analyzer/mitm/spec.py) as its own word or an error."""
    key, sep, value = word.partition(":")
    key = key.lower()
    if word.lower() in ("violations", "!", "v:1"):
        options["violations_only"] = True
    elif sep and key in ("conn", "c"):
        options["conns"] = _ints(key, value)
    elif sep and key in ("ch", "channel"):
        options["channels"] = _ints(key, value)
    elif sep and key in ("dir", "d"):
        if value not in ("c2s", "s2c"):
            raise FilterSyntaxError(f"dir: wants c2s or s2c, got {value!r}")
        options["direction"] = value
    elif sep and key in ("kind", "k"):
        kinds = value.split(",")
        known = {k.value for k in ItemKind}
        bad = [k for k in kinds if k not in known]
        if bad:
            raise FilterSyntaxError(f"kind: {bad[0]!r} is not one of {', '.join(sorted(known))}")
        options["kinds"] = frozenset(ItemKind(k) for k in kinds)
    elif sep and key == "since":
        options["since_s"] = _seconds(key, value)
    elif sep and key == "until":
        options["until_s"] = _seconds(key, value)
    else:
        return False
    return True


def parse_filter(text: str) -> ItemFilter:
    """The filter bar's words as an ItemFilter (an empty text accepts everything).
    Any other word is text to find, as is ``text:WORD``, the only way a fault
    SPEC takes it (analyzer/mitm/spec.py): both are accepted here."""
    try:
        words = shlex.split(text)
    except ValueError as e:
        raise FilterSyntaxError(str(e)) from None
    options: dict[str, Any] = {}
    free = [word[5:] if word[:5].lower() == "text:" else word for word in words
            if not parse_word(word, options) and not _intervention_word(word, options)]
    return ItemFilter(text=" ".join(free), **options)


def _intervention_word(word: str, options: dict[str, Any]) -> bool:
    """``held``, ``injected``, ... (``INTERVENTION_WORDS``): the frames the proxy
    in the middle did that to.  Only the TUI knows (its marks); ``accepts``
    leaves them to it."""
    if word.lower() not in INTERVENTION_WORDS:
        return False
    options["interventions"] = options.get("interventions", frozenset()) | {word.lower()}
    return True
