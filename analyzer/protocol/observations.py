"""What a session says about the traffic it is fed: its events.

Kept apart from the session so that what reads them (pairing, descriptions,
every view and report) needs nothing of the session's machinery.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

from whiztap.analyzer.protocol.framing import Item, ItemKind
from whiztap.analyzer.protocol.messages import Message
from whiztap.analyzer.protocol.rules import Violation


class Direction(StrEnum):
    C2S = "c2s"  # client to server
    S2C = "s2c"  # server to client

    @property
    def sender(self) -> str:
        return "client" if self is Direction.C2S else "server"


# The one direction each kind of item travels in; line breaks and unframed bytes may come from either side.
_TRAVELS = {
    ItemKind.COMMAND: Direction.C2S, ItemKind.SET_CONFIG: Direction.C2S, ItemKind.PASSWORD: Direction.C2S,
    ItemKind.RESPONSE: Direction.S2C, ItemKind.CONFIG: Direction.S2C, ItemKind.IMAGE: Direction.S2C,
    ItemKind.HANDSHAKE: Direction.S2C,
}


def direction_violation(kind: ItemKind, direction: Direction) -> Violation | None:
    """PW-DIRECTION when an item of ``kind`` came the wrong way (None: it may come
    this way).  Here, beside Direction, so that the session and a frame checked
    on its own (analyzer/protocol/frame_text.py) judge it alike."""
    travels = _TRAVELS.get(kind)
    if travels is None or travels is direction:
        return None
    return Violation("PW-DIRECTION", f"{kind.words} came from the {direction.sender}")


def line_break_violation(raw: bytes, last: ItemKind | None) -> Violation | None:
    """PW-FRAME-EOL for the line break ``raw`` after an item of kind ``last``
    on its direction (None: the first item there); None after handshake text
    and passwords, which may end in one."""
    if last is ItemKind.HANDSHAKE or last is ItemKind.PASSWORD:
        return None
    after = f"after {last.words}" if last is not None else "before anything else"
    return Violation("PW-FRAME-EOL", f"line break {raw!r} {after}")


class Observation(NamedTuple):
    """One item of the session with everything known about it when it arrived."""

    index: int  # position in the session, both directions together
    direction: Direction
    item: Item
    message: Message | None  # the meaning, when there is exactly one
    candidates: tuple[Message, ...]  # every meaning the bytes allow
    violations: tuple[Violation, ...]
    answers: Observation | None = None  # for a response: the request it answers
    latency_ns: int | None = None


class LateViolation(NamedTuple):
    """A violation found after the item it concerns (a request never answered)."""

    violation: Violation
    about: Observation
    t_ns: int


Event = Observation | LateViolation
