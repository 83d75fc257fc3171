"""The facts a conformance report states, gathered from a recording's streams.

An ``Analyzer`` is fed what a recording holds, in order: TCP reads and
connection events.  It runs one ``Session`` per connection over the raw bytes
(never trusting decoded fields stored in the file) and keeps, in memory that
does not grow with the recording: per-connection summaries, violations (every
one counted, the first ``max_violations`` kept in full), latency statistics,
Set Configuration checksums, and down-sampled series for plots.

For a recording made with the proxy in the middle (``middle=True``), each
connection it changed is judged by what each side did (``sides``), and the
changes are counted by cause and action.
"""

from __future__ import annotations

from collections import Counter
from functools import partial

from whiztap.analyzer.analysis.facts import (
    NS,
    RAW_KEPT,
    Analysis,
    ConnectionSummary,
    SetConfigCheck,
    Series,
    ViolationRecord,
)
from whiztap.analyzer.analysis.sides import CLIENT, SERVER, Settled, Sides, Verdict, side_of
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule, satisfied_rules
from whiztap.analyzer.protocol.channels import format_channels
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelResponse, ServoPositionRequest, SetConfiguration
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.session import Limits, Session
from whiztap.analyzer.protocol.text import plural
from whiztap.analyzer.traffic import (
    Closed,
    ConnectionEvent,
    Continued,
    Data,
    Delivered,
    Gap,
    HalfClosed,
    Intervention,
    Opened,
    RecordingStarted,
    RecordingStopped,
    Traffic,
    TrafficEvent,
    UpstreamFailed,
)

ENDS = frozenset({HalfClosed, UpstreamFailed, Closed, Gap})  # the connection events sessions take
ASSUMED_NOTE = "channel map assumed (--channels {}): the server never announced one"
MIDDLE_NOTE = "the proxy stood in the middle: each side judged by what it sent and what it received"


class Analyzer:
    """Feeds a recording's traffic through one session per connection (``Traffic``)
    and gathers the facts of a report."""

    def __init__(self, file: str = "", checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                 limits: Limits = Limits(), max_violations: int = 10_000, every_event: bool = True,
                 middle: bool = False) -> None:
        """``every_event=False``: ``receive()`` may leave out clean commands (see
        ``Session``), for a report, which needs only what they add up to.
        ``middle``: the recording was made with the proxy in the middle (its
        metadata says so), so each connection the proxy changed is judged by
        what each side did; it costs two more sessions per connection, so
        only such recordings pay for it.  Without it, what each side received
        is left aside and the changes are only counted."""
        self.file = file
        self._rule = get_rule(checksum_rule)
        self.traffic = Traffic(partial(limits.session, self._rule.name, every_event), self._ended)
        self._assumed = format_channels(limits.assumed_channels) if limits.assumed_channels else ""
        self.sessions = self.traffic.sessions
        self.summaries: dict[int, ConnectionSummary] = {}
        # connections whose close came; the others are open, whether or not a session has
        # begun (in the middle a read waits for its delivery before its session takes it)
        self.closed: set[int] = set()
        self.result = Analysis([file] if file else [], checksum_rule, max_violations=max_violations)
        self._counted: dict[int, Counter] = {}  # per connection: counts already put in a bin
        self._bin_second = 0
        self._next_second = -1
        self._sides = Sides(partial(limits.session, self._rule.name, False), self._record,
                            max_violations, self.traffic, self._read) if middle else None

    def receive(self, event: TrafficEvent) -> list[Event]:
        """One traffic event; returns the session's events (for views like ``cat``).
        In the middle, the session takes a read once its delivery shows whether
        the proxy changed it (``Sides``): its events come with that event."""
        if not isinstance(event, Data):
            return self._connection_event(event)
        conn = event.conn
        sides = self._sides
        if sides is not None:
            held = sides.flush(conn)  # another connection's reads, first
            if event.t_ns >= self._next_second:
                self._new_bin(event.t_ns)
            if conn not in self.sessions and conn not in self.summaries:
                self.summaries[conn] = ConnectionSummary(self.file, conn)
            events = sides.receive(event)
            return held + events if held else events
        if event.t_ns >= self._next_second:
            self._new_bin(event.t_ns)
        if conn not in self.sessions and conn not in self.summaries:
            self.summaries[conn] = ConnectionSummary(self.file, conn)
        events = self.traffic.receive(event)
        if events:
            self._collect(conn, events)
        return events

    def _read(self, event: Data) -> list[Event]:
        """In the middle, a read into the one session (``Sides`` says when):
        its frames are counted in the second it came in, even when it waited
        for its delivery while a later read began a new second."""
        conn = event.conn
        events = self.traffic.receive(event)
        if events:
            self._collect(conn, events)
            if self._sides is not None:  # always: only the middle's Sides calls this
                self._sides.batch(conn, SERVER if event.direction is Direction.S2C else CLIENT)
        if event.t_ns < self._bin_second * NS:  # it waited (a recording's times never go back)
            self._bin(conn, self.sessions[conn], event.t_ns // NS)
        return events

    def _connection_event(self, event: Delivered | Intervention | ConnectionEvent) -> list[Event]:
        """Names, notes and closes; a gap ends the session (``Traffic``)."""
        kind = type(event)
        if isinstance(event, (RecordingStarted, RecordingStopped)):
            return []
        if isinstance(event, (Delivered, Intervention)):
            return self._middle_event(event)
        summary = self.summaries.setdefault(event.conn, ConnectionSummary(self.file, event.conn))
        if isinstance(event, (Opened, Continued)):
            summary.client = event.client or summary.client
            summary.upstream = event.upstream or summary.upstream
            if kind is Continued:
                summary.notes.append("continues a connection from the previous file")
        elif isinstance(event, UpstreamFailed):
            summary.notes.append(f"upstream failed: {event.detail}")
        elif isinstance(event, Gap):
            # a capture's hole, or bytes the proxy forwarded unrecorded (--when-behind gap): the detail says which
            why = event.detail or "bytes missing from the recording"
            length = event.length
            direction = event.direction
            summary.notes.append(f"gap of {plural(length, 'byte')} in {direction}: {why}" if length is not None
                                 else f"gap in {direction}: {why}")
        elif isinstance(event, Closed):
            summary.closed_by = event.by or ""
            self.closed.add(event.conn)
        sides = self._sides
        held = None
        if sides is not None and kind in ENDS:  # the sessions take it: a read held was never delivered before it
            held = sides.flush()
        events = self.traffic.receive(event)
        self._collect(event.conn, events)
        if sides is not None:
            sides.batch(event.conn, SERVER)
            sides.receive(event)
            if kind is Closed or kind is Gap:
                self._settle(event.conn, sides.settle(event.conn, closed=kind is Closed))
        return held + events if held else events

    @property
    def open_connections(self) -> int:
        """Connections seen and not closed yet."""
        return len(self.summaries) - len(self.closed)

    def open_judgements(self) -> list[tuple[int, Settled]]:
        """In the middle, how each connection not yet settled would be judged if
        its traffic ended now (``Sides.provisional``); elsewhere violations are
        counted as they are found, and there is nothing more to say."""
        return self._sides.provisional() if self._sides is not None else []

    def finish(self) -> Analysis:
        """Close what is still open (a recording cut short) and return the facts."""
        self.close_all()
        self.result.connections = [self.summaries[c] for c in sorted(self.summaries)]
        return self.result

    def close_all(self) -> list[tuple[int, list[Event]]]:
        """Like finish, for views that print events: the late ones per connection
        (in the middle, what became of reads still held, too)."""
        sides = self._sides
        out = []
        if sides is not None and sides.holder is not None:  # reads never delivered
            out.append((sides.holder, sides.flush()))
        for conn, events in self.traffic.finish():
            self._collect(conn, events)
            if sides is not None:
                sides.batch(conn, SERVER)
            out.append((conn, events))
        if sides is not None:
            for conn, settled in sides.finish():
                self._settle(conn, settled)
            # connections are settled as they end: the report lists their violations in time order
            self.result.violations.sort(key=lambda v: v.t_ns)
            self.result.effects.sort(key=lambda v: v.t_ns)
        return out

    # -- internals ---------------------------------------------------------------------

    def _ended(self, conn: int, session: Session) -> None:
        """A session ended (``Traffic``): what it counted goes into the summary
        and the result."""
        self._bin(conn, session)
        del self._counted[conn]
        summary = self.summaries[conn]
        # a connection may be judged in pieces (a capture gap): the summary adds them up
        if summary.first_ns is None or (session.first_t_ns is not None and session.first_t_ns < summary.first_ns):
            summary.first_ns = session.first_t_ns
        summary.last_ns = max(t for t in (summary.last_ns, session.last_t_ns, 0) if t is not None) or None
        if summary.mode == "unknown" or session.mode.value != "unknown":
            summary.mode = str(session.mode)
            summary.handshake = session.handshake_outcome
        summary.frames.update({(str(d), str(k)): n for (d, k), n in session.counts.items()})
        summary.channel_map.update(session.channel_map)
        if session.assumed and ASSUMED_NOTE.format(self._assumed) not in summary.notes:
            summary.notes.append(ASSUMED_NOTE.format(self._assumed))
            self.result.assumed_channels = self._assumed
        result = self.result
        sides = self._sides
        if sides is None:
            summary.violations.update(session.violation_counts)
        if sides is None or sides.judged_alone(conn):  # else the server's own view says (_settle)
            for title, stats in session.latencies.items():
                result.latencies[title].merge(stats)
            if sides is not None and sides.is_middle(conn):  # in step all along: what the client waited too
                for title, stats in session.latencies.items():
                    result.client_latencies[title].merge(stats)
        result.frames += sum(session.counts.values())
        for t_edge in (session.first_t_ns, session.last_t_ns):
            if t_edge is not None:
                result.first_ns = t_edge if result.first_ns is None else min(result.first_ns, t_edge)
                result.last_ns = t_edge if result.last_ns is None else max(result.last_ns, t_edge)

    def _new_bin(self, t_ns: int) -> None:
        """Frames by kind per second of recording time: at each new second, what
        every session counted since the last one goes into the bin just ended."""
        for conn, session in self.sessions.items():
            self._bin(conn, session)
        self._bin_second = t_ns // NS
        self._next_second = (self._bin_second + 1) * NS

    def _bin(self, conn: int, session: Session, second: int | None = None) -> None:
        counted = self._counted.setdefault(conn, Counter())
        bins = self.result.frames_per_second[self._bin_second if second is None else second]
        for key, n in session.counts.items():
            delta = n - counted[key]
            if delta:
                bins[str(key[1])] += delta
                counted[key] = n

    def _collect(self, conn: int, events: list[Event]) -> None:
        """What the report needs from each event.  Runs once per item of the
        recording, so the common case (a clean frame) costs a few checks."""
        result = self.result
        values = result.values
        response, set_config = ItemKind.RESPONSE, ItemKind.SET_CONFIG
        for e in events:
            if isinstance(e, LateViolation):
                title = None
                if e.violation.rule_id == "PW-PAIR-UNANSWERED":
                    title = e.about.message.title if e.about.message is not None else "request"
                self._violation(conn, e.violation, e.about, e.t_ns, True, title)
                continue
            if e.violations:
                for v in e.violations:
                    self._violation(conn, v, e, e.item.t_end_ns, late=False)
            kind = e.item.kind
            if kind is response:
                request, answer = e.answers, e.message
                if request is not None and isinstance(answer, ChannelResponse):  # an answer may not parse
                    servo = request.message.__class__ is ServoPositionRequest
                    key = ("servo" if servo else "sensor", answer.channel)
                    series = values.get(key)
                    if series is None:
                        series = values[key] = Series()
                    series.add(e.item.t_end_ns, answer.data / 4 if servo else answer.data)
            elif kind is set_config and isinstance(e.message, SetConfiguration):
                m = e.message
                result.set_configs.append(SetConfigCheck(
                    self.file, conn, e.item.t_end_ns, m.checksum, self._rule.compute(m.entries),
                    satisfied_rules(m.entries, m.checksum)))

    def _violation(self, conn: int, violation: Violation, about: Observation, t: int, late: bool,
                   unanswered: str | None = None) -> None:
        """One violation of the one session (``unanswered``: the title of the
        request it says was never answered); in the middle, held until the
        connection shows whether the proxy changed it."""
        if self._sides is not None:
            self._sides.single(conn, (self._record(conn, violation, about, t, late), unanswered), about.item.raw)
            return
        result = self.result
        self._tally(violation.rule_id, side_of(violation.rule_id, str(about.direction)), unanswered)
        if len(result.violations) < result.max_violations:
            result.violations.append(self._record(conn, violation, about, t, late))

    def _tally(self, rule_id: str, side: str, unanswered: str | None, n: int = 1) -> None:
        """A violation counted (``side``: whose conduct; ``unanswered``: the
        request's title, for the unanswered table), whether or not it is kept in full."""
        result = self.result
        result.violation_counts[rule_id] += n
        result.side_counts[(rule_id, side)] += n
        if unanswered is not None:
            result.unanswered[unanswered] += n

    def _record(self, conn: int, violation: Violation, about: Observation, t: int, late: bool) -> ViolationRecord:
        raw = about.item.raw
        direction = str(about.direction)
        rule_id = violation.rule_id
        return ViolationRecord(rule_id, self.file, conn, direction, t, raw[:RAW_KEPT], violation.detail, late,
                               len(raw) > RAW_KEPT, side_of(rule_id, direction), section=violation.section,
                               index=about.index)

    # -- the proxy in the middle ---------------------------------------------------------

    def _middle_event(self, event: Delivered | Intervention) -> list[Event]:
        """What a side received, or a change the proxy made: counted, and in
        the middle handed to ``Sides``; returns what the one session made of
        the read a delivery completed, if any."""
        conn = event.conn
        summary = self.summaries.get(conn) or self.summaries.setdefault(conn, ConnectionSummary(self.file, conn))
        if type(event) is Intervention:
            self.result.interventions[(str(event.cause), event.action.value)] += 1
            summary.interventions += 1
        if self._sides is None:
            return []
        if not summary.middle:
            summary.middle = True
            summary.notes.append(MIDDLE_NOTE)
        return self._sides.receive(event)

    def _settle(self, conn: int, settled: Settled) -> None:
        """A connection's sessions ended: its violations as judged go into the
        summary and the result, and its intervention effects beside them."""
        verdicts, more, effects, latencies, client_latencies = settled
        summary = self.summaries.setdefault(conn, ConnectionSummary(self.file, conn))
        result = self.result
        for verdict in verdicts:
            self._add(summary, verdict)
        for (rule_id, side, title), n in more.items():
            summary.violations[rule_id] += n
            self._tally(rule_id, side, title, n)
        for record in effects:
            result.effect_counts[record.rule_id] += 1
            if len(result.effects) < result.max_violations:
                result.effects.append(record)
        for title, stats in (latencies or {}).items():
            result.latencies[title].merge(stats)
        for title, stats in (client_latencies or {}).items():
            result.client_latencies[title].merge(stats)

    def _add(self, summary: ConnectionSummary, verdict: Verdict) -> None:
        record, unanswered = verdict
        result = self.result
        summary.violations[record.rule_id] += 1
        self._tally(record.rule_id, record.side, unanswered)
        if len(result.violations) < result.max_violations:
            result.violations.append(record)
