"""What a session says about the traffic it is fed: its events.

Kept apart from the session so that what reads them (pairing, descriptions,
every view and report) needs nothing of the session's machinery.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

from whiztap.analyzer.protocol.framing import Item
from whiztap.analyzer.protocol.messages import Message
from whiztap.analyzer.protocol.rules import Violation


class Direction(StrEnum):
    C2S = "c2s"  # client to server
    S2C = "s2c"  # server to client

    @property
    def sender(self) -> str:
        return "client" if self is Direction.C2S else "server"


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
