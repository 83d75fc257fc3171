"""The fault SPEC grammar: what ``whiztap record --fault SPEC`` does to which frames.

A SPEC is words, split as a shell splits them (so quotes group a word)::

    ACTION [FILTER WORDS] [OPTIONS]

The ACTION comes first; ``ACTIONS`` describes each:

    delay:D  drop  dup  corrupt  replace:TEXT  slice:N  slice:MIN-MAX
    bandwidth:RATE  blackhole  reset  close

FILTER WORDS choose the frames, and are the TUI's filter bar words
(analyzer/analysis/item_filter.py): ``dir:c2s|s2c``, ``kind:K[,K]``,
``ch:N[,N]``, ``conn:N[,N]``, ``violations``, and ``text:WORD`` (quotes for
spaces: ``text:"a b"``), text to find in the frame's bytes or meaning.  Unlike
the filter bar, a word without a colon (but ``violations``) is an error, with a
guess at what was meant: a typo such as ``every2`` or ``delay:200 ms`` would
otherwise be taken as text to find and the fault would silently never act.
``since:`` and ``until:`` are not taken: a fault says when with ``after:`` and
``for:``.

OPTIONS (``OPTIONS`` describes each): ``nth:N`` or ``every:N`` (not both),
``prob:P`` (0 to 1), ``after:D`` or ``after:N`` (a duration, or a count of
chosen frames), ``for:D``, ``jitter:D``, ``pause:D`` (between slices, 1 ms
unless given).

A duration D is a number and a unit, ``ns``, ``us``, ``ms``, ``s`` or ``m``
(minutes): ``200ms``, ``1.5s``; a bare number is milliseconds, except in
``after:``, where it counts frames.  A RATE is a number, a unit (``B``, ``kB``
or ``KB`` = 1000 B, ``KiB`` = 1024 B, ``MB``, ``MiB``) and ``/s``: ``2kB/s``.
The TEXT of ``replace:`` is escaped frame text as ``whiztap decode`` takes it
(``\\r``, ``\\n``, ``\\xNN``); quote it, in single quotes to keep every
backslash: ``replace:'cr1-12--999--0-ss1\\r\\n'``.  Examples::

    delay:200ms dir:s2c jitter:50ms
    drop dir:s2c kind:response ch:12 every:2
    replace:"cr1-12--999--0-ss1" dir:s2c kind:response ch:12 nth:1
    slice:2-8 dir:s2c pause:5ms
    bandwidth:2kB/s dir:s2c
    blackhole dir:s2c after:2s

This module only says what a fault is (``fault_file.py`` reads a file of
them; carrying them out is the proxy's).  Every error is a FaultSpecError of
one line that names the offending word.
"""

from __future__ import annotations

import re
import shlex
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from itertools import pairwise
from typing import Any

from whiztap.analyzer.analysis.item_filter import FilterSyntaxError, ItemFilter, parse_word
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.mitm.hints import did_you_mean
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.text import escape, shorten, unescape

ACTIONS: dict[str, str] = {
    "delay": "delay:D  hold each chosen frame for the duration D before forwarding it",
    "drop": "drop  do not forward the chosen frame",
    "dup": "dup  forward the chosen frame twice",
    "corrupt": "corrupt  forward the chosen frame with some of its bytes changed",
    "replace": "replace:TEXT  forward TEXT (escaped frame text) instead of the chosen frame",
    "slice": "slice:N or slice:MIN-MAX  forward the chosen frame in pieces of N (or MIN to MAX) bytes",
    "bandwidth": "bandwidth:RATE  forward the chosen frames no faster than RATE (such as 2kB/s)",
    "blackhole": "blackhole  forward nothing more in the chosen direction, keeping the connection open",
    "reset": "reset  abort the connection (TCP RST)",
    "close": "close  close the connection (FIN)",
}
ACTIONS_WITH_ARGUMENT = {"delay", "replace", "slice", "bandwidth"}
CONNECTION_ACTIONS = ("reset", "close")  # they end the connection rather than act on a frame
MAX_REPLACEMENT = 64 << 10  # bytes a replace: fault may deliver in place of one frame (memory stays bounded)
FILTER_WORDS: dict[str, str] = {
    "dir": "dir:c2s|s2c  frames of one direction",
    "kind": "kind:K[,K]  frames of these kinds (command, response, set_config, ...)",
    "ch": "ch:N[,N]  frames about these channels",
    "conn": "conn:N[,N]  frames of these connections",
    "violations": "violations  frames that break a rule",
    "text": "text:WORD  frames whose bytes or meaning contain WORD (quotes for spaces: text:\"a b\")",
}
OPTIONS: dict[str, str] = {
    "nth": "nth:N  only the Nth chosen frame (1 is the first)",
    "every": "every:N  every Nth chosen frame",
    "prob": "prob:P  each chosen frame with probability P (0 to 1)",
    "after": "after:D or after:N  only once D has passed, or N frames were chosen",
    "for": "for:D  only for D once it began",
    "jitter": "jitter:D  add a random delay of up to D",
    "pause": "pause:D  time between slices (1ms unless given)",
}
DEFAULT_PAUSE_NS = 1_000_000
# what a word that is not taken may have meant (hints.did_you_mean): the KEY: words, and their known values
_HINT_KEYS = (*OPTIONS, *(w for w in FILTER_WORDS if w != "violations"))
_HINT_VALUES = {"dir": ("c2s", "s2c"), "kind": tuple(k.value for k in ItemKind if k is not ItemKind.PASSWORD)}
_WORD_LIST = ("filter words: " + " ".join(f"{w}:" for w in FILTER_WORDS if w != "violations")
              + " violations, options: " + " ".join(f"{w}:" for w in OPTIONS))
_ACTION_LIST = " ".join(f"{a}:" if a in ACTIONS_WITH_ARGUMENT else a for a in ACTIONS)

_NUMBER = r"([0-9]{1,15}(?:\.[0-9]{1,9})?)"
_DURATION = re.compile(_NUMBER + r"(ns|us|ms|s|m)?", re.ASCII)
_DURATION_UNITS = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000, "m": 60_000_000_000}
_RATE = re.compile(_NUMBER + r"(B|kB|KB|KiB|MB|MiB)/s", re.ASCII)
_RATE_UNITS = {"B": 1, "kB": 1000, "KB": 1000, "KiB": 1024, "MB": 1_000_000, "MiB": 1 << 20}


class FaultSpecError(WhiztapError, ValueError):
    """A fault spec (or a file of them) is wrong; one line naming the offending word."""


@dataclass(frozen=True)
class FaultSpec:
    """One fault: ``action`` done to the frames ``select`` chooses, as the options
    narrow them.  ``text`` is the spec as written, ``name`` its name in a file."""

    text: str
    action: str
    name: str = ""
    select: ItemFilter = ItemFilter()
    delay_ns: int = 0
    jitter_ns: int = 0
    replacement: bytes | None = None
    slice_sizes: tuple[int, int] | None = None
    pause_ns: int = DEFAULT_PAUSE_NS
    rate: int | None = None  # bytes per second
    nth: int | None = None
    every: int | None = None
    prob: float | None = None
    after_ns: int | None = None
    after_frames: int | None = None
    for_ns: int | None = None

    def selects(self, conn: int, observation: Observation) -> bool:
        """Whether the filter words choose this frame (the options, which count
        and time, are the proxy's to apply)."""
        return self.select.accepts(conn, observation, 0)

    def describe(self) -> str:
        """The spec in canonical form, which parses back to the same fault: the
        action, the filter words, then the options, each in one fixed order."""
        return " ".join([self._action_word(), *_filter_words(self.select), *self._option_words()])

    def explain(self) -> str:
        """What the fault will do, in words (``delay 200 ms, s2c, all frames``):
        what ``record``, ``tui`` and ``demo`` print for each fault at start, so
        a SPEC that says something else than meant is seen before traffic flows."""
        direction = self.select.direction or "both directions"
        if self.action in CONNECTION_ACTIONS and self.after_ns is not None:  # on a timer: no frame is chosen
            return f"{self.action} each connection {_spoken(self.after_ns)} after it opens (or the fault is added)"
        return ", ".join([self._doing(), direction, self._choosing(), *self._when()])

    def _doing(self) -> str:
        if self.action == "delay":
            return f"delay {_spoken(self.delay_ns)}" + (f" ± {_spoken(self.jitter_ns)}" if self.jitter_ns else "")
        if self.action == "replace":
            return f"replace with '{shorten(escape(self.replacement or b''), 40)}'"
        if self.action == "slice" and self.slice_sizes is not None:
            low, high = self.slice_sizes
            return f"slice in pieces of {low if low == high else f'{low} to {high}'} bytes, " \
                   f"{_spoken(self.pause_ns)} apart"
        if self.action == "bandwidth" and self.rate is not None:
            return f"bandwidth {_apart(_format_rate(self.rate))}"
        return self.action

    def _choosing(self) -> str:
        """The frames chosen: how many of which."""
        select = self.select
        if select.kinds:
            frames = "frames of kind " + " or ".join(sorted(str(k) for k in select.kinds))
        else:
            frames = "frames"
        if select.channels:
            frames += f" on channel{'s' if len(select.channels) > 1 else ''} " + _listed(select.channels)
        if select.conns:
            frames += f" of connection{'s' if len(select.conns) > 1 else ''} " + _listed(select.conns)
        if select.violations_only:
            frames += " that break a rule"
        if select.text:
            frames += f" containing '{shorten(select.text, 40)}'"
        singular = frames.replace("frames", "frame", 1)
        if self.nth is not None:
            return f"only the {_ordinal(self.nth)} {singular} of each connection"
        if self.every is not None and self.every > 1:
            return f"every {_ordinal(self.every)} {singular} of each connection"
        return f"all {frames}"

    def _when(self) -> list[str]:
        when = [] if self.prob is None else [f"each with probability {self.prob:g}"]
        if self.after_ns is not None:
            when.append(f"from {_spoken(self.after_ns)} after the connection opens (or the fault is added)")
        if self.after_frames and self.action in CONNECTION_ACTIONS:
            when.append(f"right after the {_ordinal(self.after_frames)} such frame of each connection")
        elif self.after_frames:
            when.append(f"once {self.after_frames} such frames of each connection went by")
        if self.for_ns is not None:
            when.append(f"for {_spoken(self.for_ns)} once it begins")
        return when

    def _action_word(self) -> str:
        if self.action == "delay":
            return f"delay:{_format_duration(self.delay_ns)}"
        if self.action == "replace" and self.replacement is not None:
            return "replace:" + shlex.quote(escape(self.replacement))
        if self.action == "slice" and self.slice_sizes is not None:
            low, high = self.slice_sizes
            return f"slice:{low}" if low == high else f"slice:{low}-{high}"
        if self.action == "bandwidth" and self.rate is not None:
            return f"bandwidth:{_format_rate(self.rate)}"
        return self.action

    def _option_words(self) -> list[str]:
        options: tuple[tuple[str, Any, Callable[[Any], str]], ...] = (
            ("nth", self.nth, str), ("every", self.every, str), ("prob", self.prob, repr),
            ("after", self.after_frames, str), ("after", self.after_ns, _format_duration),
            ("for", self.for_ns, _format_duration), ("jitter", self.jitter_ns or None, _format_duration),
            ("pause", None if self.pause_ns == DEFAULT_PAUSE_NS else self.pause_ns, _format_duration))
        return [f"{key}:{show(value)}" for key, value, show in options if value is not None]


def _filter_words(select: ItemFilter) -> list[str]:
    words = []
    if select.direction:
        words.append(f"dir:{select.direction}")
    if select.kinds:
        words.append("kind:" + ",".join(sorted(str(k) for k in select.kinds)))
    if select.channels:
        words.append("ch:" + ",".join(str(c) for c in sorted(select.channels)))
    if select.conns:
        words.append("conn:" + ",".join(str(c) for c in sorted(select.conns)))
    if select.violations_only:
        words.append("violations")
    if select.text:
        words.append("text:" + shlex.quote(select.text))
    return words


def _format_duration(ns: int) -> str:
    if ns == 0:
        return "0ms"
    for unit in ("m", "s", "ms", "us"):
        if ns % _DURATION_UNITS[unit] == 0:
            return f"{ns // _DURATION_UNITS[unit]}{unit}"
    return f"{ns}ns"


def _spoken(ns: int) -> str:
    """A duration as people read it: ``1500 ms``, ``2 s``, ``3 min``."""
    return _apart(_format_duration(ns)).replace(" m", " min") if ns % _DURATION_UNITS["m"] == 0 and ns else \
        _apart(_format_duration(ns))


def _apart(text: str) -> str:
    """``200ms`` as ``200 ms``: the number, a space, the unit."""
    unit = text.lstrip("0123456789")
    return f"{text[:len(text) - len(unit)]} {unit}"


def _ordinal(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _listed(numbers: frozenset[int]) -> str:
    return ", ".join(str(n) for n in sorted(numbers))


def _format_rate(rate: int) -> str:
    for unit in ("MB", "MiB", "kB", "KiB"):
        if rate % _RATE_UNITS[unit] == 0:
            return f"{rate // _RATE_UNITS[unit]}{unit}/s"
    return f"{rate}B/s"


# -- values ---------------------------------------------------------------------------------


def parse_duration(text: str, bare_unit_ns: int = 1_000_000) -> int:
    """A duration in nanoseconds: a number and a unit (ns, us, ms, s, m for
    minutes), or a bare number in ``bare_unit_ns`` (milliseconds unless told).
    ValueError for anything else."""
    match = _DURATION.fullmatch(text)
    if match is None:
        raise ValueError(f"{text!r} is not a duration such as 200ms, 1.5s or 2m")
    number, unit = match.groups()
    return round(Fraction(number) * (_DURATION_UNITS[unit] if unit else bare_unit_ns))


def _rate(text: str) -> int:
    match = _RATE.fullmatch(text)
    if match is None:
        raise ValueError(f"{text!r} is not a rate such as 2kB/s (units B, kB, KB, KiB, MB, MiB, then /s)")
    rate = round(Fraction(match.group(1)) * _RATE_UNITS[match.group(2)])
    if rate < 1:
        raise ValueError(f"{text!r} is under 1 byte a second")
    return rate


def _count(text: str, least: int = 1) -> int:
    if not (text.isascii() and text.isdigit()) or int(text) < least:
        raise ValueError(f"wants a whole number {least} or more, got {text!r}")
    return int(text)


def _probability(text: str) -> float:
    try:
        p = float(text)
    except ValueError:
        p = -1.0
    if not 0 <= p <= 1:  # NaN too
        raise ValueError(f"wants a probability from 0 to 1, got {text!r}")
    return p


def _slice_sizes(text: str) -> tuple[int, int]:
    low, sep, high = text.partition("-")
    sizes = (_count(low), _count(high) if sep else _count(low))
    if sizes[1] < sizes[0]:
        raise ValueError(f"wants a size or a range MIN-MAX with MIN <= MAX, got {text!r}")
    return sizes


def _replacement(text: str) -> bytes:
    try:
        data = unescape(text)
    except UnicodeEncodeError:
        raise ValueError("holds a character that is no byte (a lone surrogate)") from None
    if len(data) > MAX_REPLACEMENT:
        raise ValueError(f"is {len(data):,} bytes; a replacement is at most {MAX_REPLACEMENT:,} (64 KiB)")
    return data


def _after(text: str) -> dict[str, int]:
    if text.isascii() and text.isdigit():
        return {"after_frames": _count(text, least=0)}
    if not text[-1:].isalpha():
        raise ValueError(f"wants a duration with its unit (2s) or a count of frames (10), got {text!r}")
    return {"after_ns": parse_duration(text)}


_ACTION_FIELDS: dict[str, Callable[[str], dict[str, Any]]] = {
    "delay": lambda v: {"delay_ns": parse_duration(v)},
    "replace": lambda v: {"replacement": _replacement(v)},
    "slice": lambda v: {"slice_sizes": _slice_sizes(v)},
    "bandwidth": lambda v: {"rate": _rate(v)},
}
_OPTION_FIELDS: dict[str, Callable[[str], dict[str, Any]]] = {
    "nth": lambda v: {"nth": _count(v)},
    "every": lambda v: {"every": _count(v)},
    "prob": lambda v: {"prob": _probability(v)},
    "after": _after,
    "for": lambda v: {"for_ns": parse_duration(v)},
    "jitter": lambda v: {"jitter_ns": parse_duration(v)},
    "pause": lambda v: {"pause_ns": parse_duration(v)},
}


# -- words ----------------------------------------------------------------------------------


def _value(fields: dict[str, Callable[[str], dict[str, Any]]], word: str, text: str) -> dict[str, Any]:
    """The fields one ``key:value`` word sets; FaultSpecError naming the word."""
    key, _, value = word.partition(":")
    try:
        return fields[key.lower()](value)
    except ValueError as e:
        raise FaultSpecError(f"bad word {word!r} in fault {text!r}: {key.lower()}: {e}") from None


def _action(word: str, text: str) -> dict[str, Any]:
    key, sep, value = word.partition(":")
    action = key.lower()
    if action not in ACTIONS:
        raise FaultSpecError(f"unknown action {word!r} in fault {text!r} (it starts with one of: {_ACTION_LIST})")
    if action not in ACTIONS_WITH_ARGUMENT:
        if sep:
            raise FaultSpecError(f"bad word {word!r} in fault {text!r}: {action} takes no argument")
        return {"action": action}
    if not value:
        raise FaultSpecError(f"bad word {word!r} in fault {text!r}: {action} needs its argument, "
                             f"as in {ACTIONS[action].split()[0]}")
    return {"action": action, **_value(_ACTION_FIELDS, word, text)}


def _word(word: str, text: str, select: dict[str, Any], options: dict[str, str], previous: str) -> None:
    """Sort one word after the action into the filter's fields (``select``,
    ``text:`` included) or the options (``options``: key -> the word);
    FaultSpecError for any other, with a guess at what was meant (``previous``
    is the word before it: ``delay:200 ms`` meant ``delay:200ms``)."""
    key, sep, value = word.partition(":")
    key = key.lower()
    if key in ACTIONS:
        raise FaultSpecError(f"second action {word!r} in fault {text!r}: one action per fault, first")
    if sep and key in ("since", "until"):
        raise FaultSpecError(f"word {word!r} in fault {text!r} is not allowed: a fault says when with after: and for:")
    if sep and (key in OPTIONS or key == "text"):
        if key in options:
            raise FaultSpecError(f"word {word!r} in fault {text!r}: {key}: is given twice"
                                 + (' (quote a phrase: text:"a b")' if key == "text" else ""))
        if key == "text" and not value:
            raise FaultSpecError(f"word {word!r} in fault {text!r}: text: needs the text to find, as in text:sensor")
        options[key] = word
        return
    try:
        if parse_word(word, select):
            return
    except FilterSyntaxError as e:
        raise FaultSpecError(f"bad word {word!r} in fault {text!r}: {e}") from None
    if not sep and key in _HINT_KEYS:
        raise FaultSpecError(f"word {word!r} in fault {text!r} wants a value: "
                             f"{(OPTIONS.get(key) or FILTER_WORDS[key]).split()[0]}")
    guess = did_you_mean(word, previous, _HINT_KEYS, _HINT_VALUES, ("violations",))
    if sep:
        raise FaultSpecError(f"unknown word {word!r} in fault {text!r} ({_WORD_LIST})"
                             + (f"; did you mean {guess}?" if guess else ""))
    meant = f"did you mean {guess}?" if guess else "words after the action are KEY:VALUE or violations"
    raise FaultSpecError(f"bare word {word!r} in fault {text!r}: {meant} "
                         f"(text to find in frames is written text:{shlex.quote(word)})")


def parse_fault(text: str, name: str = "") -> FaultSpec:
    """The fault a SPEC describes (the grammar is this module's docstring);
    FaultSpecError, naming the word, for anything it does not take."""
    try:
        words = shlex.split(text)
    except ValueError as e:
        raise FaultSpecError(f"fault {text!r} does not split into words: {e}") from None
    if not words:
        raise FaultSpecError(f"empty fault {text!r}: it starts with one of: {_ACTION_LIST}")
    select: dict[str, Any] = {}
    options: dict[str, str] = {}
    for previous, word in pairwise(words):  # before the action: "bandwidth:2 kB/s" is about kB/s
        _word(word, text, select, options, previous)
    fields = _action(words[0], text)
    if "nth" in options and "every" in options:
        raise FaultSpecError(f"both {options['nth']!r} and {options['every']!r} in fault {text!r}: "
                             "nth: and every: do not go together")
    found = options.pop("text", ":").partition(":")[2]
    for word in options.values():
        fields.update(_value(_OPTION_FIELDS, word, text))
    return FaultSpec(text=text, name=name, select=ItemFilter(text=found, **select), **fields)
