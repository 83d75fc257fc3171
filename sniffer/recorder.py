"""Connection events in, recording out: the sessions, redaction and channels.

The proxy, the pcap importer and the live capture all describe traffic the same
way (a connection opened, bytes arrived on one direction at a time, a side shut
down, the connection closed) and the Recorder turns that into the recording
layout of ``analyzer.recording``: every read, every framer item with what the
live session model made of it, violations, plottable values and lifecycle
events.  It runs on one thread (the writer's), so messages reach each channel
in the order they happened and ``log_time`` never goes backwards.

Passwords are redacted unless asked otherwise.  A password is only known to be
one once the framer has seen its end, which may come in a later read or with the
server's verdict, so the client's reads that may hold one are kept back (they
and every read after them, to keep /tcp/reads in order) until it is known, then
written with the password's bytes as '*'.  That wait is bounded: after
``HOLD_LIMIT_S`` the bytes still undecided are masked anyway (a later item that
turns out not to be the password keeps its own bytes in /frames).
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from analyzer.checksum import DEFAULT_CHECKSUM_RULE
from analyzer.framing import ItemKind
from analyzer.recording import (
    EV_CLOSED,
    EV_CONTINUED,
    EV_GAP,
    EV_HALF_CLOSED,
    EV_OPENED,
    EV_RECORDING_STARTED,
    EV_RECORDING_STOPPED,
    EV_UPSTREAM_CONNECTED,
    EV_UPSTREAM_FAILED,
    MASK_BYTE,
    TOPIC_EVENTS,
    TOPIC_FRAMES,
    TOPIC_READS,
    TOPIC_VIOLATIONS,
    FrameEncoder,
    encode,
    encode_plots,
    encode_read,
    event_message,
    violation_message,
)
from analyzer.rules import Violation
from analyzer.session import Direction, Event, HandshakeState, LateViolation, Limits, Observation, Session
from sniffer.writer import RecordingFile

HOLD_LIMIT_S = 0.5
C2S, S2C = Direction.C2S, Direction.S2C
_NOT_FRAMES = frozenset({ItemKind.EOL, ItemKind.UNFRAMED})
_PASSWORD = ItemKind.PASSWORD
# states in which a client read may hold a password (START: an eager client's)
_MAY_HOLD_PASSWORD = frozenset({HandshakeState.AWAIT_PASSWORD, HandshakeState.START})
_DIR_TEXT = {d: d.value for d in Direction}  # Enum.value is a slow property

ViolationHook = Callable[[int, int, Violation, Observation | None, bool], None]


class _Read:
    """A read waiting for its turn on /tcp/reads (normally for no time at all)."""

    __slots__ = ("conn", "dir", "t", "offset", "data", "spans", "held")

    def __init__(self, conn: int, direction: Direction, t: int, offset: int, data: bytes) -> None:
        self.conn, self.dir, self.t, self.offset, self.data = conn, direction, t, offset, data
        self.spans: list[tuple[int, int]] = []
        self.held = False

    def mask(self, start: int, length: int) -> None:
        """Mask stream bytes [start, start + length) where they fall in this read."""
        lo = max(start, self.offset)
        hi = min(start + length, self.offset + len(self.data))
        if lo < hi:
            data = bytearray(self.data)
            data[lo - self.offset:hi - self.offset] = MASK_BYTE * (hi - lo)
            self.data = bytes(data)
            self.spans.append((lo - self.offset, hi - lo))


class _QueuedEvent:
    """A connection event waiting behind held reads, so the file keeps stream order."""

    __slots__ = ("conn", "message", "t")
    held = False
    dir = None  # not a read of either direction

    def __init__(self, conn: int, t: int, message: bytes) -> None:
        self.conn, self.t, self.message = conn, t, message


@dataclass
class _Conn:
    session: Session
    client: str
    upstream: str
    received: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})
    framed: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})
    held: list[_Read] = field(default_factory=list)
    hold_since: float | None = None


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

    def as_dict(self) -> dict:
        return {"connections": self.connections, "upstream_failures": self.upstream_failures,
                "frames": dict(self.frames), "bytes": dict(self.bytes),
                "violations": dict(self.violations), "messages": self.messages, "files": self.files}


class Recorder:
    """Feeds each connection's bytes to its own Session and writes the recording."""

    def __init__(self, file: RecordingFile, *, keep_secrets: bool = False,
                 checksum_rule: str = DEFAULT_CHECKSUM_RULE, limits: Limits = Limits(),
                 on_violation: ViolationHook | None = None) -> None:
        self.file = file
        self.keep_secrets = keep_secrets
        self.checksum_rule = checksum_rule
        self.limits = limits
        self.on_violation = on_violation
        self.summary = Summary()
        self._conns: dict[int, _Conn] = {}
        self._reads: deque[_Read] = deque()
        self._frames = FrameEncoder()
        self._frame_counts = {C2S: 0, S2C: 0}
        self._bytes = {C2S: 0, S2C: 0}  # of closed connections
        self._t = 0
        file.on_new_part = self._continued
        self._split = file.part is not None

    # -- input -----------------------------------------------------------------------

    def start(self, t_ns: int, **details: object) -> None:
        self._t = t_ns
        self.file.open(t_ns)
        self._event(0, EV_RECORDING_STARTED, t_ns, **details)
        self.file.flush()  # schemas, channels and metadata on disk at once

    def opened(self, conn: int, t_ns: int, client: str, upstream: str) -> None:
        t = self._clock(t_ns)
        if self._split:
            self.file.rotate_if_due(t)
        self._conns[conn] = _Conn(self.limits.session(self.checksum_rule), client, upstream)
        self.summary.connections += 1
        self._event(conn, EV_OPENED, t, client=client, upstream=upstream)

    def upstream_connected(self, conn: int, t_ns: int, detail: str = "") -> None:
        self._event(conn, EV_UPSTREAM_CONNECTED, self._clock(t_ns), detail=detail)

    def upstream_failed(self, conn: int, t_ns: int, detail: str) -> None:
        self.summary.upstream_failures += 1
        self._conns[conn].session.server_unreachable(detail)
        self._event(conn, EV_UPSTREAM_FAILED, self._clock(t_ns), by="server", detail=detail)

    def data(self, conn: int, direction: Direction, t_ns: int, data: bytes) -> None:
        if t_ns > self._t:
            self._t = t_ns
        t = self._t
        if self._split:
            self.file.rotate_if_due(t)
        c = self._conns[conn]
        offset = c.received[direction]
        c.received[direction] = offset + len(data)
        if self.keep_secrets or (not self._reads and c.session.state not in _MAY_HOLD_PASSWORD):
            # nothing held and no password can end in this read: write it now
            self.file.write(TOPIC_READS, t, encode_read(conn, _DIR_TEXT[direction], t, offset, data))
            self._observe_all(conn, c, c.session.receive(direction, data, t))
            return
        read = _Read(conn, direction, t, offset, data)
        self._reads.append(read)
        if c.held and direction is C2S:
            read.held = True
            c.held.append(read)
        self._observe_all(conn, c, c.session.receive(direction, data, t))
        self._update_hold(c, read)
        self._drain_reads()

    def half_closed(self, conn: int, direction: Direction, t_ns: int) -> None:
        """One side shut down its sending direction (TCP FIN)."""
        t = self._clock(t_ns)
        if self._split:
            self.file.rotate_if_due(t)
        c = self._conns[conn]
        self._observe_all(conn, c, c.session.end(direction, t))
        self._update_hold(c, None)
        self._drain_reads()
        # after what the session made of the side's last bytes, and after the
        # reads held for a password: the file keeps each stream's order
        self._event(conn, EV_HALF_CLOSED, t, by=direction.sender, dir=direction.value)

    def gap(self, conn: int, direction: Direction, t_ns: int, length: int,
            detail: str = "bytes missing from the capture; the session model restarts after them") -> None:
        """``length`` bytes of one direction are not in the recording (a capture
        missed them, or the proxy left them out: ``--when-behind gap``)."""
        t = self._clock(t_ns)
        c = self._conns[conn]
        offset = c.received[direction]
        c.received[direction] += length
        self._bytes[direction] -= length  # counted as received at close; never seen
        self._event(conn, EV_GAP, t, dir=direction.value, offset=offset, length=length, detail=detail)
        # The framer cannot know what the missing bytes were: it finishes what it
        # has and starts a fresh session model after the hole.
        self._observe_all(conn, c, c.session.close(t))
        self._update_hold(c, None, force=True)
        self._drain_reads()
        c.session = self.limits.session(self.checksum_rule)
        c.framed = dict(c.received)

    def closed(self, conn: int, t_ns: int, by: str, detail: str = "") -> None:
        t = self._clock(t_ns)
        if self._split:
            self.file.rotate_if_due(t)
        c = self._conns.pop(conn)
        for direction, n in c.received.items():
            self._bytes[direction] += n
        self._observe_all(conn, c, c.session.close(t))
        self._update_hold(c, None, force=True)
        self._drain_reads()
        self._event(conn, EV_CLOSED, t, by=by, detail=detail, c2s_bytes=c.received[C2S],
                    s2c_bytes=c.received[S2C], mode=c.session.mode.value,
                    handshake=c.session.handshake_outcome)

    def tick(self, t_ns: int) -> None:
        """Called often (at least every few hundred ms): bounded holds, flush, rotation."""
        now = time.monotonic()
        for c in self._conns.values():
            if c.hold_since is not None and now - c.hold_since >= HOLD_LIMIT_S:
                self._update_hold(c, None, force=True)
        self._drain_reads()
        self.file.tick(max(t_ns, self._t))

    def stop(self, t_ns: int, detail: str = "") -> Summary:
        """Close every connection still open, then finish the file(s)."""
        self.file.closing = True  # the closing events end the part they belong to
        t = self._clock(t_ns)
        for conn in list(self._conns):
            self.closed(conn, t, "recorder", detail or "recording stopped")
        self._event(0, EV_RECORDING_STOPPED, t, by="recorder", detail=detail)
        self.summary.messages = self.file.messages
        self.summary.frames.update({d.value: n for d, n in self._frame_counts.items()})
        self.summary.bytes.update({d.value: n for d, n in self._bytes.items()})
        self.summary.files = self.file.finish()
        return self.summary

    # -- internals ---------------------------------------------------------------------

    def _clock(self, t_ns: int) -> int:
        """Times never go backwards (a pcap's may): each input is at least the last."""
        if t_ns > self._t:
            self._t = t_ns
        return self._t

    def _event(self, conn: int, event: str, t: int, **details: object) -> None:
        message = encode(event_message(conn, event, t, **details))
        if self._reads:  # reads are held back (a password may end in them): the event waits its turn
            self._reads.append(_QueuedEvent(conn, t, message))  # type: ignore[arg-type]
        else:
            self.file.write(TOPIC_EVENTS, t, message)

    def _write_read(self, r: _Read) -> None:
        self.file.write(TOPIC_READS, r.t, encode_read(r.conn, _DIR_TEXT[r.dir], r.t, r.offset, r.data, r.spans))

    def _drain_reads(self) -> None:
        reads = self._reads
        while reads and not reads[0].held:
            r = reads.popleft()
            if type(r) is _QueuedEvent:
                self.file.write(TOPIC_EVENTS, r.t, r.message)
            else:
                self._write_read(r)

    def _observe_all(self, conn: int, c: _Conn, events: list[Event]) -> None:
        """Write what the session made of a read: the hot loop of recording.
        Its messages go to the file in one call, in the order they were made."""
        ids = self.file.channel_ids
        frames_id, violations_id = ids[TOPIC_FRAMES], ids[TOPIC_VIOLATIONS]
        out: list[tuple[int, int, bytes]] = []
        add = out.append
        encode_frame = self._frames.encode
        redact = not self.keep_secrets
        framed = c.framed
        frames = self._frame_counts
        for obs in events:
            if type(obs) is LateViolation:
                add((violations_id, obs.t_ns, self._violation(conn, obs.violation, obs.about, obs.t_ns, late=True)))
                continue
            _, direction, item, message, _, violations, _, _ = obs
            kind, raw, _, t, _ = item
            offset = framed[direction]
            framed[direction] = offset + len(raw)
            if kind is _PASSWORD and redact:
                # the client's reads not yet written (held ones, and the one being
                # processed) are the only ones that can hold it
                for read in self._reads:
                    if read.conn == conn and read.dir is C2S:
                        read.mask(offset, len(raw))
            add((frames_id, t, encode_frame(conn, obs, offset, redact)))
            if message is not None:
                for topic, plot in encode_plots(conn, obs):
                    add((ids[topic], t, plot))
            if kind not in _NOT_FRAMES:
                frames[direction] += 1
            for v in violations:
                add((violations_id, t, self._violation(conn, v, obs, t, late=False)))
        if out:
            self.file.write_all(out)

    def _violation(self, conn: int, v: Violation, about: Observation | None, t: int, late: bool) -> bytes:
        """Count and report a violation; its /violations message."""
        self.summary.violations[str(v.severity)] += 1
        if self.on_violation is not None:
            self.on_violation(conn, t, v, about, late)
        return encode(violation_message(conn, v, about, t, late, not self.keep_secrets))

    def _update_hold(self, c: _Conn, read: _Read | None, force: bool = False) -> None:
        """Hold the client's reads while they may end in an unfinished password."""
        session = c.session
        pending = not force and (session.holding_early or (session.state is HandshakeState.AWAIT_PASSWORD
                                                           and session.framers[C2S].buffered > 0))
        if pending:
            if read is not None and read.dir is C2S and not read.held:
                read.held = True
                c.held.append(read)
            if c.held and c.hold_since is None:
                c.hold_since = time.monotonic()
            return
        if force and c.held and (_password_mode(session) or session.holding_early):
            # undecided bytes still in the framer: mask them rather than risk a leak
            start = c.framed[C2S]
            for r in c.held:
                r.mask(start, c.received[C2S] - start)
        for r in c.held:
            r.held = False
        c.held.clear()
        c.hold_since = None

    def _continued(self, part: int) -> None:
        """A new file began: say which connections are open and where their streams are."""
        for conn, c in self._conns.items():
            self._event(conn, EV_CONTINUED, self._t, client=c.client, upstream=c.upstream,
                        c2s_offset=c.received[C2S], s2c_offset=c.received[S2C],
                        detail=f"connection open when part {part} began")
        self.file.flush()


def _password_mode(session: Session) -> bool:
    """Whether the client framer still reads a password.  The framer keeps this
    private; when it cannot be asked, assume yes (masking too much beats a leak)."""
    return bool(getattr(session.framers[C2S], "_password_mode", True))

