"""The verdict on one execution: the analyzer's own ``Session`` over both directions.

The runner feeds the judge what it wrote and what it read, as it happens; the
judge says how many answers the server owes right now (``due``: the runner
waits for them, up to its deadline) and, at the end, the rules the *server*
broke.  The fuzzer's own frames break client rules on purpose, so only
violations on what the server sent count; a request the server must answer is
one the session awaits for certain and that broke no rule of warning weight
or more, bar where it came (its first command not Fetch Configuration): what
the spec leaves open, such as the answer to a malformed frame, is never owed.
Answers are counted by what answers them (kind and channel), not by the
session's pairing: a server that answers a malformed request it may ignore
does not make the clean one after it look unanswered (nor does the answer
count for a clean request sent after it).  A password is owed its verdict
once its bytes are complete or go wrong (the spec gives it no end marker).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.handshake import HandshakeState, Mode
from whiztap.analyzer.protocol.messages import ChannelConfig, ChannelResponse
from whiztap.analyzer.protocol.observations import Direction, Event, Observation
from whiztap.analyzer.protocol.pairing import answer_spec
from whiztap.analyzer.protocol.rules import Severity, Violation
from whiztap.analyzer.protocol.session import Limits

CRASH, HANG, VIOLATION = "crash", "hang", "violation"
KINDS = (CRASH, HANG, VIOLATION)
BEHAVIOUR_ITEMS = 16
_ANSWERS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})


@dataclass(frozen=True, slots=True)
class Verdict:
    """What went wrong in an execution: its ``kind`` (crash, hang or
    violation), the ``rule`` a violation broke ('' otherwise) and a line of
    detail.  ``signature`` is what shrinking keeps and findings are told apart by."""

    kind: str
    detail: str
    rule: str = ""

    @property
    def signature(self) -> tuple[str, str]:
        return self.kind, self.rule


class Judge:
    """One execution's session, fed as it happens; ``mode``: the server's
    handshake; ``password``: the real one (to know when it is complete);
    ``channels``: the configuration the server announced before, which the
    session starts from (one robot's configuration holds for every
    connection, and without it a request on a channel of the wrong unit
    would look owed an answer)."""

    def __init__(self, mode: Mode, password: bytes, channels: tuple[ChannelConfig, ...] = (),
                 limits: Limits = Limits()) -> None:
        self.session = limits.session()
        self.session.channel_map = dict(enumerate(channels))
        self.mode = mode
        self.password = password
        self.events: list[Event] = []
        self._line = b""  # the client's first bytes, as long as a password may be
        self._owed: Counter[tuple[ItemKind, int | None]] = Counter()  # clean requests unanswered, by what answers them
        self._breach: Verdict | None = None

    def client(self, data: bytes, t_ns: int) -> None:
        if len(self._line) <= len(self.password):
            self._line += data[:len(self.password) + 1 - len(self._line)]
        self._take(self.session.receive(Direction.C2S, data, t_ns))

    def server(self, data: bytes, t_ns: int) -> None:
        self._take(self.session.receive(Direction.S2C, data, t_ns))

    def close(self, t_ns: int) -> None:
        self._take(self.session.close(t_ns))

    def _take(self, events: list[Event]) -> None:
        self.events.extend(events)
        for event in events:
            if not isinstance(event, Observation):
                continue
            if event.direction is Direction.C2S:
                kind, channel, certain = answer_spec(event.message, event.candidates)
                if kind is not None and certain and _clean(event):
                    self._owed[kind, channel] += 1
                continue
            if event.item.kind in _ANSWERS:
                channel = event.message.channel if isinstance(event.message, ChannelResponse) else None
                if self._owed[event.item.kind, channel] > 0:  # else it answers a request that was not owed one
                    self._owed[event.item.kind, channel] -= 1
            if self._breach is None:
                self._breach = next((Verdict(VIOLATION, _line(v), v.rule_id) for v in event.violations
                                     if v.severity >= Severity.WARNING), None)

    @property
    def ready(self) -> bool:
        """Commands may be sent and are answered."""
        return self.session.state is HandshakeState.READY

    def due(self) -> int:
        """Answers the server owes now: the greeting, a verdict, clean requests."""
        state = self.session.state
        if self.mode is Mode.WINSOCK and state is HandshakeState.START:
            return 1  # 'sendchkpass'
        if state in (HandshakeState.AWAIT_PASSWORD, HandshakeState.AWAIT_VERDICT, HandshakeState.EARLY_PASSWORD):
            line = self._line
            whole = len(line) >= len(self.password) or not self.password.startswith(line)
            return 1 if line and whole else 0
        return sum(self._owed.values())

    def breach(self) -> Verdict | None:
        """The first rule the server broke, of warning weight or more."""
        return self._breach

    def behaviour(self) -> tuple[str, ...]:
        """What happened, in short: how the handshake ended, the client
        rules the frames broke and the kinds of the first ``BEHAVIOUR_ITEMS``
        client items (the corpus keeps a session that shows a new one).
        Only what the session decides, never how many of the server's bytes
        had come when it ended (which timing decides): the corpus, and so
        every later execution, must be the same on every run of a seed."""
        sent = [e for e in self.events if isinstance(e, Observation) and e.direction is Direction.C2S]
        rules = sorted({v.rule_id for e in sent for v in e.violations})
        kinds = [e.item.kind.value for e in sent[:BEHAVIOUR_ITEMS]]
        return (self.session.handshake_outcome, *rules, "|", *kinds)


# Rules a request may break and still be owed its answer: about where it
# comes in the session, not about the request.
_STILL_OWED = frozenset({"PW-WINSOCK-CONFIG-FIRST", "PW-VPN-CONFIG-FIRST"})


def _clean(request: Observation) -> bool:
    return all(v.severity < Severity.WARNING or v.rule_id in _STILL_OWED for v in request.violations)


def _line(v: Violation) -> str:
    return f"{v.rule_id}: {v.detail}"

