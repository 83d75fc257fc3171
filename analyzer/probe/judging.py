"""A ``probe server`` case's verdict, sans-IO: its traffic read by the analyzer's own session.

The runner hands over what crossed each of the case's connections (``Trace``:
every write and read with its time, and whether the server closed first);
``judge`` feeds it to a fresh ``Session``, exactly as ``whiztap analyze``
would read a recording of it, and keeps what the server is to blame for:

- the rules of error severity broken by what the server sent;
- ``PW-PAIR-UNANSWERED`` for a request of the probe's that broke no rule (a
  frame that breaks one is sent to see the server survive it, and the spec
  does not say whether a server answers it);
- the probe's own expectations, which no rule of the session states:
  ``PROBE-ORDER`` (answers in another order than their requests),
  ``PROBE-NO-ANSWER`` (no handshake word where the Functional Flow wants one),
  ``PROBE-WRONG-VERDICT`` (``readytogo`` for a wrong password, or ``Failed
  Validation`` for the right one), ``PROBE-CLOSED`` (the server closed or reset
  a connection that had given it no reason, and not after ``Failed
  Validation``) and ``PROBE-DOWN`` (the server
  stopped accepting connections).

What the probe sends on purpose breaks client rules; those are the probe's,
never the server's, and are left out.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from whiztap.analyzer.probe.model import Finding, Outcome
from whiztap.analyzer.probe.server_plan import ServerCase, Target, broke_a_rule
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO, SENDCHKPASS, VERDICTS
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.protocol.text import escape

SHOWN = 60  # characters of a frame quoted in a finding

PROBE_RULES = {
    "PROBE-ORDER": "Answers come in the order of their requests (nothing else pairs them)",
    "PROBE-NO-ANSWER": "The server says the handshake word the Functional Flow calls for",
    "PROBE-WRONG-VERDICT": "'readytogo' for the right password only, 'Failed Validation' for a wrong one",
    "PROBE-CLOSED": "The server keeps a connection open while the client keeps the spec",
    "PROBE-DOWN": "The server keeps accepting connections whatever a client sent",
}
"""The probe's own expectations, by id: what a report's reader looks up."""


@dataclass(slots=True)
class Trace:
    """One connection of a case as the probe saw it.  ``events``: (direction,
    bytes, arrival time in ns) in order; ``closed_early``: the server closed or
    reset the connection before the probe had finished with it (``how`` says
    which); ``end_ns``: when the probe was done with it."""

    events: list[tuple[Direction, bytes, int]] = field(default_factory=list)
    closed_early: bool = False
    how: str = ""
    end_ns: int = 0


def quote(raw: bytes) -> str:
    text = escape(raw)
    return text if len(text) <= SHOWN else f"{text[:SHOWN]}... ({len(raw)} bytes)"


def session_events(trace: Trace) -> tuple[Session, list[Event]]:
    """``trace`` read by a fresh session, closed at its end."""
    session = Session()
    events: list[Event] = []
    for direction, data, t_ns in trace.events:
        events += session.receive(direction, data, t_ns)
    events += session.close(trace.end_ns)
    return session, events


def server_findings(events: Iterable[Event]) -> Iterator[Finding]:
    """What the server is to blame for in a session's events (module docstring)."""
    for event in events:
        if isinstance(event, LateViolation):
            v = event.violation
            if v.rule_id == "PW-PAIR-UNANSWERED" and not broke_a_rule(event.about.violations):
                yield Finding(v.rule_id, f"{v.detail}: {quote(event.about.item.raw)}")
        elif event.direction is Direction.S2C:
            for v in event.violations:
                if v.severity >= Severity.ERROR:
                    yield Finding(v.rule_id, f"{v.detail}: {quote(event.item.raw)}")


def order_findings(events: Iterable[Event]) -> Iterator[Finding]:
    """PROBE-ORDER for each answer to a request older than one answered before it."""
    latest: Observation | None = None
    for event in events:
        if isinstance(event, Observation) and event.answers is not None:
            asked = event.answers
            if latest is not None and asked.index < latest.index:
                yield Finding("PROBE-ORDER", f"{quote(event.item.raw)} answers {quote(asked.item.raw)}, "
                                             f"sent before {quote(latest.item.raw)}, which was answered first")
            if latest is None or asked.index > latest.index:
                latest = asked


def _words(events: Iterable[Event]) -> list[bytes]:
    return [e.item.raw for e in events if isinstance(e, Observation) and e.direction is Direction.S2C
            and e.item.kind is ItemKind.HANDSHAKE]


def handshake_findings(case: ServerCase, target: Target, events: list[Event]) -> Iterator[Finding]:
    """The Functional Flow's words the case wants from the server."""
    words = _words(events)
    if case.greeting and SENDCHKPASS not in words:
        yield Finding("PROBE-NO-ANSWER", "the server did not ask for the password ('sendchkpass')")
    wanted = case.verdict or (READYTOGO if case.login and target.mode == "winsock" else None)
    if wanted is None:
        return
    verdicts = [w for w in words if w in VERDICTS]
    if not verdicts:
        yield Finding("PROBE-NO-ANSWER", f"no '{wanted.decode()}' (nor any verdict) after the password")
    elif verdicts[0] != wanted:
        which = "a wrong password" if wanted == FAILED_VALIDATION else "the right password"
        yield Finding("PROBE-WRONG-VERDICT", f"'{verdicts[0].decode()}' for {which}")


def _camera_silence(finding: Finding) -> bool:
    return finding.rule == "PW-PAIR-UNANSWERED" and finding.detail.startswith(m.FetchCameraImage.title)


def judge(case: ServerCase, target: Target, traces: list[Trace],
          down: str = "") -> tuple[Outcome, tuple[Finding, ...], str]:
    """The verdict of ``case`` on its ``traces``, its findings and the reason
    for a skip; ``down``: why the server was found to accept no more connections after it."""
    found: list[Finding] = []
    closed = ""
    for trace in traces:
        _, events = session_events(trace)
        found += server_findings(events)
        found += order_findings(events)
        found += handshake_findings(case, target, events)
        refused = FAILED_VALIDATION in _words(events)  # then closing is what the server should do (A16)
        if trace.closed_early and not refused and not closed:
            closed = trace.how or "closed"
    if down:
        found.append(Finding("PROBE-DOWN", down))
    if case.silent_ok and found and all(_camera_silence(f) for f in found):
        return Outcome.SKIP, (), case.silent_ok
    if closed:
        if case.may_close:
            kept = [f for f in found if f.rule not in ("PW-PAIR-UNANSWERED", "PROBE-NO-ANSWER")]
            return (Outcome.FAIL, tuple(kept), "") if kept else (Outcome.SKIP, (), case.may_close)
        found.append(Finding("PROBE-CLOSED", f"the server {closed} the connection before the case was over"))
    return (Outcome.FAIL if found else Outcome.PASS), tuple(found), ""
