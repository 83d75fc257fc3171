"""What follows directly from a frame the proxy made or changed.

A module of its own, beside ``sides.py``, because it is one idea with its own
state: the interventions that changed bytes (an injection, a hand edit, a
``replace``, a ``corrupt``, a ``dup``'s copies) read as facts about the
answering, and the client's answering violations that those facts account for.

Such a change adds or takes away requests and answers.  Read from the
intervention itself (its action, its direction, its frame before and after,
decoded as ``whiztap decode`` would): every request or answer in ``after``
and not in ``before`` is an *extra* (the server answers a request the client
never sent; the client gets an answer it never asked for), and every one in
``before`` and not in ``after`` is a *missing* one (the client's request never
reached the server as sent, or the answer to it never reached the client).
They are keyed by what pairs them: the answer's item kind and channel.

At the end of a connection, an answering violation only the client's view
has is an effect of the intervention when a credit of the same key, made no
later than the violation, accounts for it: a ``PW-PAIR-UNSOLICITED`` answer
takes an extra, a ``PW-PAIR-UNANSWERED`` request a missing one.  The rest (an
answer the proxy dropped, delayed or held) stays the client's experience.
Drops, delays, holds and the connection's end change no bytes and make no
credit: a client really waited for those answers.
"""

from __future__ import annotations

from bisect import insort
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import NamedTuple

from whiztap.analyzer.protocol.frame_text import frame_alone
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelResponse
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.pairing import answer_spec
from whiztap.analyzer.traffic import Action, Intervention

MAKES_FRAMES = frozenset({Action.INJECT, Action.EDIT, Action.REPLACE, Action.CORRUPT, Action.DUP})
"""The actions that put bytes on the wire that their sender did not send."""
ANSWER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})
CREDITS_KEPT = 10_000  # per connection, with their times; past that, counted without (any time will do)

Key = tuple[ItemKind, int | None]  # what pairs a request and its answer: the answer's kind, its channel


class Credit(NamedTuple):
    t_ns: int
    cause: str


def answer_key(answer: Observation) -> Key:
    """What an answer (a server item) is an answer to."""
    message = answer.message
    return answer.item.kind, message.channel if isinstance(message, ChannelResponse) else None


def request_key(request: Observation) -> Key | None:
    """What answers a request (a client command); None if nothing does."""
    kind, channel, _certain = answer_spec(request.message, request.candidates)
    return None if kind is None else (kind, channel)


def _keys(data: bytes, direction: Direction) -> Counter[Key]:
    """The requests (c2s) or answers (s2c) in ``data``, by what pairs them."""
    keys: Counter[Key] = Counter()
    observations, _ = frame_alone(data, direction)
    for observation in observations:
        kind, message = observation.item.kind, observation.message
        if direction is Direction.C2S and kind is ItemKind.COMMAND:
            answer_kind, channel, _ = answer_spec(message, observation.candidates)
            if answer_kind is not None:
                keys[(answer_kind, channel)] += 1
        elif direction is Direction.S2C and kind in ANSWER_KINDS:
            keys[(kind, message.channel if isinstance(message, ChannelResponse) else None)] += 1
    return keys


def _fits(credit: Key, wanted: Key) -> bool:
    """A credit accounts for a violation of the same kind and channel (a channel
    unknown on either side fits any, as an answer without one pairs with any)."""
    return credit[0] == wanted[0] and (credit[1] == wanted[1] or credit[1] is None or wanted[1] is None)


@dataclass(slots=True)
class Consequences:
    """One connection's credits, and the last change of each direction (the
    cause an effect of no credit is put down to)."""

    extra: dict[Key, list[Credit]] = field(default_factory=lambda: defaultdict(list))
    missing: dict[Key, list[Credit]] = field(default_factory=lambda: defaultdict(list))
    untimed: dict[str, Counter] = field(default_factory=lambda: {"extra": Counter(), "missing": Counter()})
    last_change: dict[Direction, str] = field(default_factory=dict)
    kept: int = 0

    def note(self, event: Intervention) -> None:
        """An intervention: the credits it makes, if it changed bytes."""
        if event.action not in MAKES_FRAMES or event.secret:
            return  # a password is no request: what the proxy did to one pairs nothing
        cause = str(event.cause)
        self.last_change[event.direction] = cause
        before, after = _keys(event.before, event.direction), _keys(event.after, event.direction)
        if event.action is Action.DUP:  # each dup is one more copy of the frame (``after`` is the frame once)
            before = Counter()
        for book, name, keys in ((self.extra, "extra", after - before), (self.missing, "missing", before - after)):
            for key, n in keys.items():
                for _ in range(n):
                    if self.kept < CREDITS_KEPT:
                        self.kept += 1
                        insort(book[key], Credit(event.t_ns, cause))
                    else:
                        self.untimed[name][key] += 1

    def cause_of(self, direction: Direction | str | None) -> str:
        """The latest change to frames of ``direction`` (an effect's likely cause), or ''."""
        return self.last_change.get(Direction(direction), "") if direction else ""

    def account(self, wanted: list[tuple[int, str, Key | None]]) -> list[str | None]:
        """For each answering violation (time, rule, key), in any order, the
        cause of the change that accounts for it, or None: the client's
        experience.  Earliest violations first, each takes the earliest fitting
        credit made no later than it.  Leaves this object as it was."""
        extra = {k: list(v) for k, v in self.extra.items()}
        missing = {k: list(v) for k, v in self.missing.items()}
        untimed = {name: Counter(c) for name, c in self.untimed.items()}
        out: list[str | None] = [None] * len(wanted)
        for i in sorted(range(len(wanted)), key=lambda i: wanted[i][0]):
            t_ns, rule_id, key = wanted[i]
            if key is None:
                continue
            name = "extra" if rule_id == "PW-PAIR-UNSOLICITED" else "missing"
            out[i] = _take(extra if name == "extra" else missing, untimed[name], key, t_ns)
        return out


def _take(book: dict[Key, list[Credit]], untimed: Counter, wanted: Key, t_ns: int) -> str | None:
    """The earliest credit that fits ``wanted`` and came no later than ``t_ns``, taken; its cause."""
    best: tuple[Key, int] | None = None
    for key, credits in book.items():
        if (credits and _fits(key, wanted) and credits[0].t_ns <= t_ns
                and (best is None or credits[0].t_ns < book[best[0]][0].t_ns)):
            best = (key, 0)
    if best is not None:
        return book[best[0]].pop(0).cause
    for key, n in untimed.items():
        if n and _fits(key, wanted):
            untimed[key] -= 1
            return "one of the interventions on this connection"
    return None
