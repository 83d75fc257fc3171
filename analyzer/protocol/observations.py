"""What a session says about the traffic it is fed: its events.

Kept apart from the session so that what reads them (pairing, descriptions,
every view and report) needs nothing of the session's machinery.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

from whiztap.analyzer.protocol.framing import (
    COMMAND_HEADER, CONFIG_HEADER, RESPONSE_HEADER, SET_CONFIG_PREFIX, Item, ItemKind)
from whiztap.analyzer.protocol.handshake import HANDSHAKE_WORDS
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


# What an item of each kind begins with, where the spec fixes it, longest first
# where one begins another (a client's Set Configuration begins like the
# server's Configuration Settings).
OPENINGS: tuple[tuple[bytes, ItemKind], ...] = (
    (SET_CONFIG_PREFIX, ItemKind.SET_CONFIG), (COMMAND_HEADER, ItemKind.COMMAND),
    (RESPONSE_HEADER, ItemKind.RESPONSE), (CONFIG_HEADER, ItemKind.CONFIG),
    *((word, ItemKind.HANDSHAKE) for word in HANDSHAKE_WORDS),
)
LONGEST_OPENING = max(len(opening) for opening, _ in OPENINGS)


def sender_of(first: bytes) -> Direction | None:
    """Which side sends bytes that begin with ``first``, by the opening of the
    item they begin with and the way that kind travels: C2S for a command or a
    Set Configuration, S2C for an answer, Configuration Settings or a
    handshake word.  So a conversation's first bytes tell which side serves
    (a Winsock server speaks first, a VPN client does).  None when ``first``
    does not tell: it begins with no opening, or too little of one has come
    (``may_tell``)."""
    for opening, kind in OPENINGS:
        if first.startswith(opening):
            return _TRAVELS[kind]
        if opening.startswith(first):
            return None  # more bytes may make it this opening, or one after it
    return None


def may_tell(first: bytes) -> bool:
    """Whether ``first`` is all or the start of an opening: bytes that begin
    with it tell their sender (``sender_of``) now or once more of them come."""
    return any(opening.startswith(first) for opening, _ in OPENINGS)


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

    # position in the session, both directions together
    index: int  # type: ignore[assignment]  # a field named index shadows tuple.index, which nothing calls
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
