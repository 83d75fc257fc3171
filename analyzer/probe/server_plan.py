"""The vocabulary of ``probe server``'s cases, sans-IO: a case, its steps, and the target it runs against.

A case is a list of steps per connection (send bytes, whole or cut; pause;
wait until the session reaches a point) and what it expects of the server
(``ServerCase``'s fields); the catalogue (``server_cases.py``) builds them,
the runner (``whiztap.sniffer.probe.server_run``) plays them and
``judging.py`` judges what crossed the sockets.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

from whiztap.analyzer.probe.client_cases import GARBAGE_ALPHABET, Cut, field_cuts
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.handshake import VERDICTS, HandshakeState
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.protocol.session import Session

SEPARATOR = b"--"
FETCH = encode(m.FetchConfiguration())  # the canary: always valid, always answered
SLOW_GAP_S = 0.05  # the slow client's pause between bytes
SPLIT_GAP_S = 0.002  # between the pieces of a split frame, so each is a read of its own
IDLE_S = 1.0  # how long the idle client says nothing
MANY = 16  # connections open at once
DEFAULT_DEV = 12  # the spec's default Dev#

SECTION_FLOW = "Functional Flow"
SECTION_API = "API Definition"
SECTION_MESSAGES = "API Message Descriptions"
CLOSE_AFTER_BAD_FRAME = ("the server closed the connection after a frame that breaks the spec; the spec does not "
                         "say whether a server may")


class Mode(StrEnum):
    WINSOCK = "winsock"
    VPN = "vpn"


@dataclass(frozen=True, slots=True)
class Target:
    """What the probe learnt of the server before the cases: its handshake
    mode, the password to give it and its channel map."""

    mode: Mode
    password: bytes
    channels: tuple[m.ChannelConfig, ...]
    checksum_rule: str = DEFAULT_CHECKSUM_RULE
    seed: int = 0  # chooses the stray bytes
    greets: bool = True  # a Winsock server asks for the password on connect (one that does not is waited for once)

    def garbage(self) -> bytes:
        """Eight stray bytes no item begins with, chosen by the seed."""
        rng = random.Random(f"whiztap-probe-server:{self.seed}")
        return bytes(rng.choice(GARBAGE_ALPHABET) for _ in range(8))

    def of_unit(self, unit: m.UnitType) -> list[int]:
        return [ch for ch, config in enumerate(self.channels) if config.unit_type == unit]


# -- steps -------------------------------------------------------------------------------------------


class Until(StrEnum):
    """A point of the session the runner waits for (at most its wait, or until the server closes)."""

    ASKED = "asked"  # the server's first handshake word
    VERDICT = "verdict"  # readytogo or Failed Validation
    ANSWERED = "answered"  # every request that broke no rule has its answer


@dataclass(frozen=True, slots=True)
class Send:
    data: bytes
    cut: Cut = Cut.NONE
    gap_s: float = 0.0  # the pause between pieces
    pieces: tuple[bytes, ...] = ()  # explicit pieces (for cuts no Cut names)

    def chunks(self) -> list[bytes]:
        if self.pieces:
            return list(self.pieces)
        if self.cut is Cut.BYTES:
            return [self.data[i:i + 1] for i in range(len(self.data))]
        if self.cut is Cut.FIELDS:
            return field_cuts(self.data)
        return [self.data]


@dataclass(frozen=True, slots=True)
class Pause:
    seconds: float


Step = Send | Pause | Until


def reached(point: Until, session: Session, words: list[bytes]) -> bool:
    """Whether the live ``session`` has come to ``point``; ``words``: the
    handshake words the server said so far (a server out of step says its
    verdict where the session's handshake does not move)."""
    if point is Until.ASKED:
        return session.state is not HandshakeState.START or bool(words)
    if point is Until.VERDICT:
        return session.state in (HandshakeState.READY, HandshakeState.FAILED) or any(w in VERDICTS for w in words)
    return not any(p.certain and not broke_a_rule(p.request.violations) for p in session.awaited.pending)


def broke_a_rule(violations: Iterable) -> bool:
    """A frame of the probe's that breaks a rule of warning severity or more:
    the spec does not say whether a server answers it."""
    return any(v.severity >= Severity.WARNING for v in violations)


# -- cases -------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ServerCase:
    """One case.  ``build`` makes its steps for a target (a string: why it
    cannot run there); ``login``: the handshake and Fetch Configuration come
    first; ``may_close``: the server may close the connection (the reason a
    close is a skip), empty when a close is a failure (a close after
    'Failed Validation' is neither: docs/protocol.md, A16); ``silent_ok``:
    a request left wholly unanswered is a skip, for this reason; ``verdict``: the
    handshake word the server must answer the password with; ``greeting``:
    the server must ask for the password; ``mode``: the only mode it runs in."""

    id: str
    title: str
    spec: str
    build: Callable[[Target], list[Step] | str] = field(repr=False, compare=False)
    login: bool = True
    may_close: str = ""
    silent_ok: str = ""
    verdict: bytes | None = None
    greeting: bool = False
    mode: Mode | None = None
    connections: int = 1

    def plan(self, target: Target) -> list[Step] | str:
        """The steps of each connection, opening included, or why the case cannot run."""
        if self.mode is not None and target.mode is not self.mode:
            return f"the server uses the {target.mode} handshake; this case is for {self.mode} servers"
        body = self.build(target)
        if isinstance(body, str):
            return body
        return (opening(target) if self.login else []) + body


def opening(target: Target) -> list[Step]:
    """The Functional Flow up to the Configuration Settings."""
    asked: list[Step] = [Until.ASKED] if target.greets else []
    login = [*asked, Send(target.password), Until.VERDICT] if target.mode is Mode.WINSOCK else []
    return login + [Send(FETCH), Until.ANSWERED]


def canary(*steps: Step) -> list[Step]:
    """``steps``, then a Fetch Configuration that must be answered: the server still serves."""
    return [*steps, Send(FETCH), Until.ANSWERED]
