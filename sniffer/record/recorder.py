"""Traffic events in, recording out: the sessions, redaction and channels.

The proxy, the pcap importer and the live capture all say what happened as the
typed events of ``whiztap.analyzer.traffic`` (a connection opened, bytes
arrived on one direction at a time, a side shut down, bytes are missing, the
connection closed), and the Recorder (``receive(event)``) turns them into the
recording layout of ``whiztap.analyzer.recording.format``: every read, every
framer item with what the live session model made of it, violations (each
also a ``foxglove.Log`` message), plottable values (a topic per channel) and
the events themselves.  It runs on one thread (the writer's), so
messages reach each channel in the order they happened and ``log_time`` never
goes backwards.

Passwords are masked unless asked otherwise, by the rule of
``whiztap.analyzer.recording.redaction`` (only the client's first line, only
when the server begins with ``sendchkpass``).  Masking comes first: the
session model, and so every frame, violation and printed line, sees the bytes
as the file has them.  A client read still undecided waits, and everything
after it waits behind it (the file keeps arrival order), for a bounded time
(``HOLD_LIMIT_S``, and caps on the bytes), after which it is masked.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, NamedTuple

from whiztap.analyzer.analysis.verdict import Judge
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.recording.encode import (
    DIR_TEXT,
    RUN_INLINE_MAX,
    FrameEncoder,
    encode,
    encode_plots,
    encode_read,
    encode_violation,
    intervention_message,
    run_message,
)
from whiztap.analyzer.recording.format import (MASK_BYTE, MITM_TOPICS, TOPIC_DELIVERED, TOPIC_EVENTS, TOPIC_FRAMES,
                                                TOPIC_INTERVENTIONS, TOPIC_LOG, TOPIC_READS, TOPIC_VIOLATIONS)
from whiztap.analyzer.recording.notice import Notice
from whiztap.analyzer.recording.redaction import HOLD_LIMIT_S, Redactor
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.session import Limits
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
    UpstreamConnected,
    UpstreamFailed,
    to_json,
)
from whiztap.sniffer.record.summary import verdict_dict
from whiztap.sniffer.record.writer import RecordingFile

C2S, S2C = Direction.C2S, Direction.S2C
_NOT_FRAMES = frozenset({ItemKind.EOL, ItemKind.UNFRAMED})  # not protocol: written in runs

ViolationHook = Callable[[int, int, Violation, Observation | None, bool], None]
Work = Callable[[], None]


@dataclass
class _Conn:
    """What the recorder keeps per connection besides its session (``Traffic``)."""

    client: str
    upstream: str
    received: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})
    written: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})  # less while reads wait
    framed: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})
    delivered: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})  # with the proxy in the middle


class _ReadNote(NamedTuple):
    """What the recorder keeps with a read while it waits to be written."""

    c: _Conn
    read: Data  # at the recorder's time
    offset: int


@dataclass
class Summary:
    """What a recording holds, for the line printed at exit."""

    connections: int = 0
    upstream_failures: int = 0
    frames: Counter[str] = field(default_factory=Counter)  # by direction
    bytes: Counter[str] = field(default_factory=Counter)  # by direction
    violations: Counter[str] = field(default_factory=Counter)  # by severity
    messages: int = 0
    files: list[str] = field(default_factory=list)
    verdict: dict | None = None  # in the middle: analyze's verdict (summary.verdict_dict), ``violations`` its counts

    def as_dict(self) -> dict:
        return {"connections": self.connections, "upstream_failures": self.upstream_failures,
                "frames": dict(self.frames), "bytes": dict(self.bytes),
                "violations": dict(self.violations), "messages": self.messages, "files": self.files,
                "verdict": self.verdict}


class Recorder:
    """Feeds each connection's bytes to its own Session and writes the recording:
    ``start()``, then ``receive(event)`` for every traffic event (``tick()``
    often), then ``stop()``."""

    def __init__(self, file: RecordingFile, *, keep_secrets: bool = False,
                 checksum_rule: str = DEFAULT_CHECKSUM_RULE, limits: Limits = Limits(),
                 on_violation: ViolationHook | None = None, middle: bool = False) -> None:
        """``middle``: the proxy stands in the middle (the metadata says so), so
        the summary's violations are ``analyze``'s verdict (``verdict``)."""
        self.file = file
        self.keep_secrets = keep_secrets
        self.on_violation = on_violation
        self.summary = Summary()
        self._traffic = Traffic(partial(limits.session, checksum_rule))
        # In the middle, analyze's judging of what the file gets (each side by what it sent and
        # received); without it, the session's violations are analyze's verdict already.
        self.judge = Judge(checksum_rule, limits, middle=True) if middle else None
        for topic in MITM_TOPICS if middle else ():  # known from the start (each part defines it at its
            file.channel_id(topic)  # first message), so a live viewer has them before it
        self._conns: dict[int, _Conn] = {}  # open, as far as the input goes
        self._live: dict[int, _Conn] = {}  # open, as far as the file goes
        # None with --keep-secrets; a queued record is a _ReadNote, or the work of a connection event
        self._redactor: Redactor[_ReadNote | Work] | None = None if keep_secrets else Redactor(HOLD_LIMIT_S)
        self._inputs: dict[type, Callable[[Any], Work]] = {
            Opened: self._input_opened, UpstreamConnected: self._input_upstream_connected,
            UpstreamFailed: self._input_upstream_failed, HalfClosed: self._input_half_closed,
            Gap: self._input_gap, Closed: self._input_closed, Delivered: self._input_delivered,
            Intervention: self._input_intervention, Notice: self._input_notice}
        self._watch: Callable[[TrafficEvent], None] | None = None  # see extend()
        self._frames = FrameEncoder()
        self._frame_counts = {C2S: 0, S2C: 0}
        self._bytes = {C2S: 0, S2C: 0}  # of closed connections
        self._t = 0  # the latest input time
        self._now = 0  # the time of what is being written: log times follow it
        file.on_new_part = self._continued
        self._split = file.part is not None

    # -- input -----------------------------------------------------------------------

    def start(self, t_ns: int, detail: str = "") -> None:
        """Open the file; ``detail`` says where the traffic comes from."""
        self._t = self._now = t_ns
        self.file.open(t_ns)
        self._write_event(RecordingStarted(t_ns, detail))
        self.file.flush()  # schemas, channels and metadata on disk at once

    def receive(self, event: TrafficEvent | Notice) -> None:
        """One traffic event of a connection (the recording's own start and
        stop are ``start()`` and ``stop()``).  Hot loop for reads: each one
        costs a little bookkeeping here before it is written."""
        if isinstance(event, Data):
            conn, direction, t_ns, data, _offset, _masked = event
            if t_ns > self._t:
                self._t = t_ns
            t = self._t
            if t != t_ns:
                event = Data(conn, direction, t, data)  # a pcap's times may go back; the file's never do
            c = self._conns[conn]
            offset = c.received[direction]
            c.received[direction] = offset + len(data)
            redactor = self._redactor
            if redactor is None or redactor.passing(conn):
                self._write_read(c, event, offset, None)
                return
            redactor.read(conn, direction, data, _ReadNote(c, event, offset), time.monotonic())
            self._release(redactor)
            return
        t = self._clock(event.t_ns)
        if t != event.t_ns:
            event = event._replace(t_ns=t) if isinstance(event, Delivered) else replace(event, t_ns=t)
        work = self._inputs[type(event)](event)
        if self._redactor is not None:
            self._redactor.tell(event)
        self._then(event.conn, work)

    def tick(self, t_ns: int) -> None:
        """Called often (at least every few hundred ms): bounded holds, flush, rotation."""
        if self._redactor is not None:
            self._redactor.tick(time.monotonic())
            self._release(self._redactor)
        self.file.tick(max(t_ns, self._t))

    def stop(self, t_ns: int, detail: str = "") -> Summary:
        """Close every connection still open, then finish the file(s)."""
        self.file.closing = True  # the closing events end the part they belong to
        t = self._clock(t_ns)
        for conn in list(self._conns):
            self.receive(Closed(conn, t, "recorder", detail or "recording stopped"))
        # every connection is closed, so nothing waits any more
        stopped = RecordingStopped(t, "recorder", detail)
        self._then(0, lambda: self._write_event(stopped))
        if self.judge is not None:  # the connections are judged as analyze will judge the file
            verdict = self.judge.finish()
            self.summary.violations = Counter(verdict.by_severity)
            self.summary.verdict = self.verdict()
        self.summary.messages = self.file.messages
        self.summary.frames.update({d.value: n for d, n in self._frame_counts.items()})
        self.summary.bytes.update({d.value: n for d, n in self._bytes.items()})
        self.summary.files = self.file.finish()
        return self.summary

    def extend(self, inputs: dict[type, Callable[[Any], Work]], watch: Callable[[TrafficEvent], None]) -> None:
        """More event types for ``receive``, each done in turn; ``watch`` sees what the file gets (--mirror)."""
        self._inputs.update(inputs)
        self._watch = watch

    # -- connection events as they come: the bookkeeping, and the work for their turn ----------

    def _input_opened(self, e: Opened) -> Work:
        c = self._conns[e.conn] = _Conn(e.client, e.upstream)
        self._traffic.session(e.conn)
        self.summary.connections += 1
        return lambda: self._opened(c, e)

    def _input_upstream_connected(self, e: UpstreamConnected) -> Work:
        return lambda: self._write_event(e)

    def _input_upstream_failed(self, e: UpstreamFailed) -> Work:
        self.summary.upstream_failures += 1
        c = self._conns[e.conn]
        return lambda: self._upstream_failed(c, e)

    def _input_half_closed(self, e: HalfClosed) -> Work:
        c = self._conns[e.conn]
        return lambda: self._half_closed(c, e)

    def _input_gap(self, e: Gap) -> Work:
        """``length`` bytes of one direction are not in the recording (a capture
        missed them, or the proxy left them out: ``--when-behind gap``)."""
        c = self._conns[e.conn]
        offset = c.received[e.direction]
        length = e.length or 0
        c.received[e.direction] = offset + length
        self._bytes[e.direction] -= length  # counted as received at close; never seen
        gap = replace(e, offset=offset, length=length)
        return lambda: self._gap(c, gap, offset + length)

    def _input_delivered(self, e: Delivered) -> Work:
        """What the proxy wrote toward one side when it stands in the middle:
        /tcp/delivered, in that side's stream offsets (a password masked)."""
        c = self._conns.get(e.conn)
        if c is None:  # after its connection closed: nothing more is delivered on it
            return lambda: None
        offset = c.delivered[e.direction]
        c.delivered[e.direction] = offset + len(e.data)
        masked = e.secret and not self.keep_secrets

        def work() -> None:
            self._at(e.t_ns)
            data = MASK_BYTE * len(e.data) if masked else e.data
            spans = [(0, len(data))] if masked else None
            self.file.write_late(TOPIC_DELIVERED, e.t_ns, encode_read(e.conn, DIR_TEXT[e.direction], e.t_ns, offset,
                                                                       data, spans))
            if self.judge is not None:  # as the file has it
                self.judge.receive(e._replace(data=data) if masked else e)
        return work

    def _input_intervention(self, e: Intervention) -> Work:
        def work() -> None:
            self._at(e.t_ns)
            self.file.write_late(TOPIC_INTERVENTIONS, e.t_ns,
                                 encode(intervention_message(e, not self.keep_secrets)))
            self._judged(e)
        return work

    def _input_notice(self, e: Notice) -> Work:  # the proxy's own line (a fault that chose nothing) for /log
        return lambda: self.file.write(TOPIC_LOG, max(e.t_ns, self._now), e.log())

    def _input_closed(self, e: Closed) -> Work:
        c = self._conns.pop(e.conn)
        for direction, n in c.received.items():
            self._bytes[direction] += n
        return lambda: self._closed(c, e)

    # -- internals ---------------------------------------------------------------------

    def _clock(self, t_ns: int) -> int:
        """Times never go backwards (a pcap's may): each input is at least the last."""
        if t_ns > self._t:
            self._t = t_ns
        return self._t

    def _at(self, t: int) -> None:
        """Writing reached time ``t``: what is written now is logged at it (so
        log times never go back, whatever waited), and a new part begins here
        if a split limit was reached."""
        self._now = t
        if self._split:
            self.file.rotate_if_due(t)

    def _then(self, conn: int, work: Work) -> None:
        """A connection event's work: now, or after the reads that came before it."""
        redactor = self._redactor
        if redactor is None or redactor.idle:
            work()
        else:
            redactor.event(conn, work)
            self._release(redactor)

    def _release(self, redactor: Redactor[_ReadNote | Work]) -> None:
        """Write the reads (and do the events) whose turn has come."""
        for r in redactor.released():
            note = r.record
            if isinstance(note, _ReadNote):
                self._write_read(note.c, note.read._replace(data=r.data), note.offset, r.spans)
            else:
                note()

    def _write_read(self, c: _Conn, read: Data, offset: int, spans: list[tuple[int, int]] | None) -> None:
        """One read into /tcp/reads (as it may be shown), and what the session makes of it."""
        conn, direction, t, data, _offset, _masked = read
        self._at(t)
        self.file.write(TOPIC_READS, t, encode_read(conn, DIR_TEXT[direction], t, offset, data, spans))
        c.written[direction] = offset + len(data)  # after: a part that begins before the read does not count it
        self._observe_all(conn, c, self._traffic.receive(read))
        if self.judge is not None:
            self.judge.receive(read)
        if self._watch is not None:
            self._watch(read)

    def _write_event(self, event: ConnectionEvent) -> None:
        t = self._now = event.t_ns
        self.file.write(TOPIC_EVENTS, t, encode(to_json(event)))

    def verdict(self) -> dict | None:
        """In the middle, ``analyze``'s verdict on what is written so far (``summary.verdict_dict``)."""
        judge = self.judge
        if judge is None:
            return None
        analyzer = judge.analyzer
        return verdict_dict(judge.verdict(), analyzer.open_connections, sum(analyzer.result.interventions.values()))

    def _judged(self, e: TrafficEvent) -> None:
        """An event written: the judge (in the middle) and the watcher (``extend``) take it in the same place."""
        if self.judge is not None:
            self.judge.receive(e)
        if self._watch is not None:
            self._watch(e)

    def _opened(self, c: _Conn, e: Opened) -> None:
        self._at(e.t_ns)
        self._live[e.conn] = c
        self._write_event(e)
        self._judged(e)

    def _upstream_failed(self, c: _Conn, e: UpstreamFailed) -> None:
        self._observe_all(e.conn, c, self._traffic.receive(e))  # the server will never speak
        self._judged(e)
        self._write_event(e)

    def _half_closed(self, c: _Conn, e: HalfClosed) -> None:
        self._at(e.t_ns)
        self._observe_all(e.conn, c, self._traffic.receive(e))
        self._judged(e)
        # after what the session made of the side's last bytes: the file keeps each stream's order
        self._write_event(e)

    def _gap(self, c: _Conn, e: Gap, offset_after: int) -> None:
        self._write_event(e)
        c.written[e.direction] = offset_after
        # The framer cannot know what the missing bytes were: it finishes what it
        # has and starts a fresh session model after the hole.
        self._observe_all(e.conn, c, self._traffic.receive(e))
        self._judged(e)
        self._traffic.session(e.conn)
        c.framed = dict(c.written)

    def _closed(self, c: _Conn, e: Closed) -> None:
        self._at(e.t_ns)
        del self._live[e.conn]
        session = self._traffic.sessions[e.conn]
        self._observe_all(e.conn, c, self._traffic.receive(e))
        self._judged(e)
        self._write_event(Closed(e.conn, e.t_ns, e.by, e.detail, c.received[C2S], c.received[S2C],
                                 session.mode.value, session.handshake_outcome))

    def _observe_all(self, conn: int, c: _Conn, events: list[Event]) -> None:
        """Write what the session made of a read: the hot loop of recording.
        Its messages go to the file in one call, in the order they were made,
        logged at the time of what is being written (an item the session held,
        like a password sent before 'sendchkpass', comes out after later ones).
        Unframed items and line breaks in a row are written together
        (``_write_run``)."""
        now = self._now
        ids = self.file.channel_ids
        frames_id = ids[TOPIC_FRAMES]
        out: list[tuple[int, int, bytes]] = []
        add = out.append
        encode_frame = self._frames.encode
        redact = not self.keep_secrets
        framed = c.framed
        frames = self._frame_counts
        run: list[Observation] = []
        for obs in events:
            if isinstance(obs, LateViolation):
                if run:
                    self._write_run(conn, c, run, out)
                    run = []
                self._violation(out, conn, obs.violation, obs.about, obs.t_ns, late=True)
                continue
            _, direction, item, message, _, violations, _, _ = obs
            kind, raw, _, t, _ = item
            if kind in _NOT_FRAMES:
                if run and run[0].direction is not direction:
                    self._write_run(conn, c, run, out)
                    run = []
                run.append(obs)
                continue
            if run:
                self._write_run(conn, c, run, out)
                run = []
            offset = framed[direction]
            framed[direction] = offset + len(raw)
            add((frames_id, now, encode_frame(conn, obs, offset, redact)))
            if message is not None:
                for topic, plot in encode_plots(conn, obs):
                    try:
                        add((ids[topic], now, plot))
                    except KeyError:  # a plot topic's first message in the recording
                        add((self.file.channel_id(topic), now, plot))
            frames[direction] += 1
            for v in violations:
                self._violation(out, conn, v, obs, t, late=False)
        if run:
            self._write_run(conn, c, run, out)
        if out:
            self.file.write_all(out)

    def _write_run(self, conn: int, c: _Conn, run: list[Observation], out: list[tuple[int, int, bytes]]) -> None:
        """Unframed items and line breaks in a row, from one read: a lone one of
        at most ``RUN_INLINE_MAX`` bytes as the item it is; any other run as one
        /frames message (``run_message``), and one /violations message per rule
        its items break, with how many times (the totals count every break)."""
        now = self._now
        frames_id = self.file.channel_ids[TOPIC_FRAMES]
        direction = run[0].direction
        offset = c.framed[direction]
        size = sum(len(o.item.raw) for o in run)
        c.framed[direction] = offset + size
        t = run[-1].item.t_end_ns
        if len(run) == 1 and size <= RUN_INLINE_MAX:
            out.append((frames_id, now, self._frames.encode(conn, run[0], offset, not self.keep_secrets)))
            for v in run[0].violations:
                self._violation(out, conn, v, run[0], t, late=False)
            return
        out.append((frames_id, now, encode(run_message(conn, run, offset))))
        broken: dict[str, list] = {}  # rule id -> [first violation, its item, how many]
        for o in run:
            for v in o.violations:
                seen = broken.get(v.rule_id)
                if seen is None:
                    broken[v.rule_id] = [v, o, 1]
                else:
                    seen[2] += 1
        for v, about, count in broken.values():
            if count > 1:
                v = Violation(v.rule_id, f"{v.detail} (the first of {count} in {size} bytes of unframed data)")
            self._violation(out, conn, v, about, t, late=False, count=count)

    def _violation(self, out: list[tuple[int, int, bytes]], conn: int, v: Violation, about: Observation | None,
                   t: int, late: bool, count: int = 1) -> None:
        """Count and report a violation (``count`` breaks of its rule: see
        ``_write_run``); add its /violations message to ``out``, and the
        ``foxglove.Log`` made from it, to /log, right after it."""
        self.summary.violations[str(v.severity)] += count
        if self.on_violation is not None:
            self.on_violation(conn, t, v, about, late)
        violation, log = encode_violation(conn, v, about, t, late, not self.keep_secrets, count)
        ids = self.file.channel_ids
        out.append((ids[TOPIC_VIOLATIONS], self._now, violation))
        out.append((ids[TOPIC_LOG], self._now, log))

    def _continued(self, part: int) -> None:
        """A new file began: say which connections are open and where their streams are."""
        for conn, c in self._live.items():
            self._write_event(Continued(conn, self._now, c.client, c.upstream, c.written[C2S], c.written[S2C],
                                        f"connection open when part {part} began"))
        self.file.flush()

