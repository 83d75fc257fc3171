"""The facts a conformance report states, gathered from a recording's streams.

An ``Analyzer`` is fed what a recording holds, in order: TCP reads and
connection events.  It runs one ``Session`` per connection over the raw bytes
(never trusting decoded fields stored in the file) and keeps, in memory that
does not grow with the recording: per-connection summaries, violations (every
one counted, the first ``max_violations`` kept in full), latency statistics,
Set Configuration checksums, and down-sampled series for plots.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from functools import partial

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule, satisfied_rules
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig, ServoPositionRequest, SetConfiguration
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.observations import Event, LateViolation, Observation
from whiztap.analyzer.protocol.session import Limits, Session
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.traffic import (
    Closed,
    ConnectionEvent,
    Continued,
    Data,
    Gap,
    Opened,
    RecordingStarted,
    RecordingStopped,
    Traffic,
    TrafficEvent,
    UpstreamFailed,
)

NS = 1_000_000_000
RAW_KEPT = 2048  # bytes of a violating item kept for the report: every frame whole; an image or garbage cut


@dataclass(slots=True)
class ViolationRecord:
    rule_id: str
    file: str
    conn: int
    direction: str | None
    t_ns: int
    raw: bytes  # the frame's bytes (first RAW_KEPT)
    detail: str
    late: bool = False
    cut: bool = False  # the item was longer than RAW_KEPT

    @property
    def severity(self) -> Severity:
        return RULES[self.rule_id].severity


@dataclass(slots=True)
class SetConfigCheck:
    file: str
    conn: int
    t_ns: int
    checksum: int
    expected: int  # under the rule in use
    satisfies: tuple[str, ...]  # every candidate rule the checksum fits


class Series:
    """A time series down-sampled to at most ``2 * limit`` points: when full,
    every other point goes and only every ``stride``-th new one is kept."""

    __slots__ = ("points", "limit", "stride", "_skip")

    def __init__(self, limit: int = 1000) -> None:
        self.points: list[tuple[int, float]] = []
        self.limit = limit
        self.stride = 1
        self._skip = 0

    def add(self, t_ns: int, value: float) -> None:
        self._skip += 1
        if self._skip < self.stride:
            return
        self._skip = 0
        self.points.append((t_ns, value))
        if len(self.points) >= 2 * self.limit:
            del self.points[1::2]
            self.stride *= 2


@dataclass(slots=True)
class ConnectionSummary:
    file: str
    conn: int
    client: str = ""
    upstream: str = ""
    first_ns: int | None = None
    last_ns: int | None = None
    mode: str = "unknown"
    handshake: str = "not started"
    frames: Counter = field(default_factory=Counter)  # (dir, kind) -> count
    violations: Counter = field(default_factory=Counter)  # rule id -> count
    channel_map: dict[int, ChannelConfig] = field(default_factory=dict)
    closed_by: str = ""
    notes: list[str] = field(default_factory=list)  # upstream failures, capture gaps


@dataclass
class Analysis:
    """Everything a report says, for one file or merged over several."""

    files: list[str]
    checksum_rule: str
    connections: list[ConnectionSummary] = field(default_factory=list)
    violations: list[ViolationRecord] = field(default_factory=list)
    violation_counts: Counter = field(default_factory=Counter)
    latencies: dict[str, LatencyStats] = field(default_factory=lambda: defaultdict(LatencyStats))
    unanswered: Counter = field(default_factory=Counter)  # request title -> count
    set_configs: list[SetConfigCheck] = field(default_factory=list)
    frames_per_second: dict[int, Counter] = field(default_factory=lambda: defaultdict(Counter))
    values: dict[tuple[str, int], Series] = field(default_factory=dict)  # ("sensor"|"servo", ch)
    first_ns: int | None = None
    last_ns: int | None = None
    frames: int = 0
    max_violations: int = 10_000

    @property
    def duration_s(self) -> float:
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) / NS

    def worst(self, ignore: frozenset[str] = frozenset()) -> Severity | None:
        levels = [RULES[r].severity for r, n in self.violation_counts.items() if n and r not in ignore]
        return max(levels, default=None)

    def merge(self, other: Analysis) -> None:
        self.files += other.files
        self.connections += other.connections
        room = self.max_violations - len(self.violations)
        self.violations += other.violations[:max(room, 0)]
        self.violation_counts.update(other.violation_counts)
        for title, stats in other.latencies.items():
            self.latencies[title].merge(stats)
        self.unanswered.update(other.unanswered)
        self.set_configs += other.set_configs
        for second, counts in other.frames_per_second.items():
            self.frames_per_second[second].update(counts)
        for key, series in other.values.items():
            mine = self.values.setdefault(key, Series(series.limit))
            for t, v in series.points:
                mine.add(t, v)
        self.frames += other.frames
        for t in (other.first_ns, other.last_ns):
            if t is not None:
                self.first_ns = t if self.first_ns is None else min(self.first_ns, t)
                self.last_ns = t if self.last_ns is None else max(self.last_ns, t)


class Analyzer:
    """Feeds a recording's traffic through one session per connection (``Traffic``)
    and gathers the facts of a report."""

    def __init__(self, file: str = "", checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                 limits: Limits = Limits(), max_violations: int = 10_000, every_event: bool = True) -> None:
        """``every_event=False``: ``receive()`` may leave out clean commands (see
        ``Session``), for a report, which needs only what they add up to."""
        self.file = file
        self._rule = get_rule(checksum_rule)
        self.traffic = Traffic(partial(limits.session, self._rule.name, every_event), self._ended)
        self.sessions = self.traffic.sessions
        self.summaries: dict[int, ConnectionSummary] = {}
        self.result = Analysis([file] if file else [], checksum_rule, max_violations=max_violations)
        self._counted: dict[int, Counter] = {}  # per connection: counts already put in a bin
        self._bin_second = 0
        self._next_second = -1

    def receive(self, event: TrafficEvent) -> list[Event]:
        """One traffic event; returns the session's events (for views like ``cat``)."""
        if type(event) is not Data:
            return self._connection_event(event)  # type: ignore[arg-type]
        if event.t_ns >= self._next_second:
            self._new_bin(event.t_ns)
        conn = event.conn
        if conn not in self.sessions and conn not in self.summaries:
            self.summaries[conn] = ConnectionSummary(self.file, conn)
        events = self.traffic.receive(event)
        if events:
            self._collect(conn, events)
        return events

    def _connection_event(self, event: ConnectionEvent) -> list[Event]:
        """Names, notes and closes; a gap ends the session (``Traffic``)."""
        kind = type(event)
        if kind is RecordingStarted or kind is RecordingStopped:
            return []
        summary = self.summaries.setdefault(event.conn, ConnectionSummary(self.file, event.conn))
        if kind is Opened or kind is Continued:
            summary.client = event.client or summary.client  # type: ignore[union-attr]
            summary.upstream = event.upstream or summary.upstream  # type: ignore[union-attr]
            if kind is Continued:
                summary.notes.append("continues a connection from the previous file")
        elif kind is UpstreamFailed:
            summary.notes.append(f"upstream failed: {event.detail}")  # type: ignore[union-attr]
        elif kind is Gap:
            # a capture's hole, or bytes the proxy forwarded unrecorded (--when-behind gap): the detail says which
            why = event.detail or "bytes missing from the recording"  # type: ignore[union-attr]
            length = event.length  # type: ignore[union-attr]
            direction = event.direction  # type: ignore[union-attr]
            summary.notes.append(f"gap of {length} bytes in {direction}: {why}" if length is not None
                                 else f"gap in {direction}: {why}")
        elif kind is Closed:
            summary.closed_by = event.by or ""  # type: ignore[union-attr]
        events = self.traffic.receive(event)
        self._collect(event.conn, events)
        return events

    def finish(self) -> Analysis:
        """Close what is still open (a recording cut short) and return the facts."""
        for conn, events in self.traffic.finish():
            self._collect(conn, events)
        self.result.connections = [self.summaries[c] for c in sorted(self.summaries)]
        return self.result

    def close_all(self) -> list[tuple[int, list[Event]]]:
        """Like finish, for views that print events: the late ones per connection."""
        out = self.traffic.finish()
        for conn, events in out:
            self._collect(conn, events)
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
        summary.violations.update(session.violation_counts)
        summary.channel_map.update(session.channel_map)
        result = self.result
        for title, stats in session.latencies.items():
            result.latencies[title].merge(stats)
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

    def _bin(self, conn: int, session: Session) -> None:
        counted = self._counted.setdefault(conn, Counter())
        bins = self.result.frames_per_second[self._bin_second]
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
            if e.__class__ is LateViolation:
                self._violation(conn, e.violation.rule_id, e.violation.detail, e.about, e.t_ns, late=True)
                if e.violation.rule_id == "PW-PAIR-UNANSWERED":
                    title = e.about.message.title if e.about.message is not None else "request"
                    result.unanswered[title] += 1
                continue
            if e.violations:
                for v in e.violations:
                    self._violation(conn, v.rule_id, v.detail, e, e.item.t_end_ns, late=False)
            kind = e.item.kind
            if kind is response:
                request = e.answers
                if request is not None and e.message is not None:  # an answer may not parse
                    servo = request.message.__class__ is ServoPositionRequest
                    key = ("servo" if servo else "sensor", e.message.channel)
                    series = values.get(key)
                    if series is None:
                        series = values[key] = Series()
                    series.add(e.item.t_end_ns, e.message.data / 4 if servo else e.message.data)
            elif kind is set_config and isinstance(e.message, SetConfiguration):
                m = e.message
                result.set_configs.append(SetConfigCheck(
                    self.file, conn, e.item.t_end_ns, m.checksum, self._rule.compute(m.entries),
                    satisfied_rules(m.entries, m.checksum)))

    def _violation(self, conn: int, rule_id: str, detail: str, about: Observation, t: int, late: bool) -> None:
        result = self.result
        result.violation_counts[rule_id] += 1
        if len(result.violations) < result.max_violations:
            raw = about.item.raw
            result.violations.append(ViolationRecord(
                rule_id, self.file, conn, str(about.direction), t, raw[:RAW_KEPT], detail, late, len(raw) > RAW_KEPT))
