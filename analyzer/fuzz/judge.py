"""The verdict on one execution: the analyzer's own ``Session`` over both directions.

The runner feeds the judge what it wrote and what it read, as it happens; the
judge says how many answers the server owes right now (``due``: the runner
waits for them, up to its deadline) and, at the end, the rules the *server*
broke.  The fuzzer's own frames break client rules on purpose, so only
violations on what the server sent count; a request the server must answer is
one the session awaits for certain and that broke no rule of warning weight
or more, bar where it came (its first command not Fetch Configuration): what
the spec leaves open, such as the answer to a malformed frame, is never owed.
Answers are matched by what answers them (kind and channel), not by the
session's pairing: a server that answers a malformed request it may ignore
does not make the clean one after it look unanswered (nor does the answer
count for a clean request sent after it).  A password is owed its verdict
once its bytes are complete or go wrong (the spec gives it no end marker).

Two checks are the fuzzer's own, as no analyzer rule can make them (the
analyzer does not know the password, and pairs answers by kind and channel,
not by order).  ``FUZZ-ANSWER-ORDER``: answers come in the order of their
requests; an answer that overtakes an owed one is only noted, and the breach
is the overtaken answer coming after all (one that never comes is a hang, a
dropped answer rather than a reordered one).  ``FUZZ-WRONG-PASSWORD-ACCEPTED``
(Winsock): `readytogo` after a first line that is not the password.
"""

from __future__ import annotations

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
ORDER_RULE = "FUZZ-ANSWER-ORDER"
PASSWORD_RULE = "FUZZ-WRONG-PASSWORD-ACCEPTED"
Key = tuple[ItemKind, int | None]  # what answers a request: the answer's kind, its channel


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
        # requests unanswered, in the order sent, by what answers them; True: owed
        # (clean), False: may be answered or not (the spec leaves it open)
        self._waiting: list[tuple[Key, bool]] = []
        self._overtaken: list[Key] = []  # owed requests a later request's answer came before
        self._password_judged = False
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
                if kind is not None:
                    self._waiting.append(((kind, channel), certain and _clean(event)))
                continue
            if event.item.kind in _ANSWERS:
                channel = event.message.channel if isinstance(event.message, ChannelResponse) else None
                self._answered((event.item.kind, channel))
            self._judge_password()  # first: it says more than PW-HS-ORDER on the same readytogo
            if self._breach is None:
                self._breach = next((Verdict(VIOLATION, _line(v), v.rule_id) for v in event.violations
                                     if v.severity >= Severity.WARNING), None)

    def _answered(self, key: Key) -> None:
        """An answer came: it answers the oldest owed request it fits, else
        the oldest it may answer.  Owed requests before the one answered were
        overtaken, and an answer to one of them later is out of order; but
        only where no request in between may go unanswered (then the answer
        may be that one's, and order says nothing)."""
        if key in self._overtaken:
            self._overtaken.remove(key)
            self._breached(Verdict(VIOLATION, f"{ORDER_RULE}: an answer ({key[0].value}"
                                   f"{'' if key[1] is None else f' on channel {key[1]}'}) came after the "
                                   "answer to a later request", ORDER_RULE))
            return
        fits = [i for i, (k, _) in enumerate(self._waiting) if k == key]
        owed = [i for i in fits if self._waiting[i][1]]
        if not owed:
            if fits:
                del self._waiting[fits[0]]
            return  # it answers a request that was not owed one
        before, self._waiting = self._waiting[:owed[0]], self._waiting[owed[0] + 1:]
        if all(o for _, o in before):
            self._overtaken += [k for k, _ in before]
        else:
            self._waiting[:0] = [(k, o) for k, o in before if o]

    def _judge_password(self) -> None:
        """Winsock: `readytogo` must follow the real password only."""
        if self._password_judged or self.mode is not Mode.WINSOCK or self.session.state is not HandshakeState.READY:
            return
        self._password_judged = True
        if self._line[:len(self.password)] != self.password:
            self._breached(Verdict(VIOLATION, f"{PASSWORD_RULE}: the server said readytogo after a first "
                                   "line that is not the password", PASSWORD_RULE))

    def _breached(self, verdict: Verdict) -> None:
        if self._breach is None:
            self._breach = verdict

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
        return sum(owed for _, owed in self._waiting) + len(self._overtaken)

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

