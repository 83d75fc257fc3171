"""A recording as exchanges: what each client sent, and what its server answered.

Replaying a client's side, serving a server's side and showing either in the
TUI all start from the same facts: each connection's client items in stream
order with their offsets and times, the recorded answer paired to each request
by the session model, the server's handshake, and the client's raw reads (for
replays that re-send the original read boundaries).  This module rebuilds them
from a recording's raw reads, as every reader of recordings does.

A recording made with the proxy in the middle also says what the client
received (``/tcp/delivered``), which faults may have made differ from what the
server sent: each item also has the answer the *client* got (``received``,
paired by a session over what the client sent and what it received), and
each connection the handshake words it got.  Elsewhere they are the same.
"""

from __future__ import annotations

import bisect
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.analysis.compare import ServoMotion
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig, FailedValidation
from typing import NamedTuple

from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.recording.format import METADATA_NAME
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.analyzer.recording.sets import RecordingSet, scan_set
from whiztap.analyzer.traffic import Closed, Data, Delivered, Opened, Traffic, TrafficEvent

C2S, S2C = Direction.C2S, Direction.S2C
DEFAULT_ANSWER_TIMEOUT_NS = 5_000_000_000


class ClientRead(NamedTuple):
    """One read of the client's, where it lies in the client's stream."""

    offset: int
    t_ns: int
    data: bytes


@dataclass(frozen=True, slots=True)
class ClientItem:
    """One item the client sent, and the answer the recording paired with it."""

    obs: Observation
    offset: int  # stream offset of its first byte
    t_ns: int  # when the read holding its last byte arrived
    answer: Observation | None = None  # what the server sent
    at_rest: bool = False  # the answer is a servo position reached and held
    received: Observation | None = None  # what the client got (in the middle; elsewhere the answer)

    @property
    def end(self) -> int:
        return self.offset + len(self.obs.item.raw)


@dataclass(slots=True)
class RecordedConnection:
    conn: int
    opened_ns: int
    client: str = ""
    mode: Mode = Mode.UNKNOWN
    handshake: list[Observation] = field(default_factory=list)  # the server's handshake items
    received_handshake: list[Observation] = field(default_factory=list)  # as the client got them
    items: list[ClientItem] = field(default_factory=list)  # every client item, stream order
    reads: list[ClientRead] = field(default_factory=list)  # the client's reads

    @property
    def password(self) -> ClientItem | None:
        return next((i for i in self.items if i.obs.item.kind is ItemKind.PASSWORD), None)

    @property
    def refused(self) -> bool:
        """Whether the server answered the password with Failed Validation."""
        return len(self.handshake) >= 2 and isinstance(self.handshake[1].message, FailedValidation)

    @property
    def requests(self) -> list[ClientItem]:
        return [i for i in self.items if i.obs.item.kind is ItemKind.COMMAND]


@dataclass(slots=True)
class RecordedSessions:
    path: str
    metadata: dict[str, str]
    start_ns: int  # the first read: time 0 of ``whiztap cat``, --start and --end
    connections: list[RecordedConnection]

    @property
    def secrets_kept(self) -> bool:
        return self.metadata.get("secrets") == "kept"

    @property
    def checksum_rule(self) -> str:
        """The Set Configuration checksum rule the recording was judged by."""
        return _checksum_rule({METADATA_NAME: self.metadata})


class _Builder:
    """What one connection's reads and its session's events say, gathered while
    the file is scanned (the session itself is ``Traffic``'s)."""

    def __init__(self, conn: int, opened_ns: int) -> None:
        self.rec = RecordedConnection(conn, opened_ns)
        self.framed = {C2S: 0, S2C: 0}
        self.received = {C2S: 0, S2C: 0}
        self.read_ends: list[int] = []  # end offset of each client read
        self.read_times: list[int] = []
        self.pending: list[tuple[Observation, int]] = []  # client items: (obs, offset)
        self.answers: dict[int, tuple[Observation, bool]] = {}  # request index -> (answer, at rest)
        self.motion = ServoMotion()
        self.middle = False  # the recording has what the client received
        self.sent: dict[object, deque[int]] = defaultdict(deque)  # client item -> its request index
        self.got: dict[int, Observation] = {}  # request index (the one session's) -> what the client got
        self._mine: dict[int, int] = {}  # the client's session's request index -> the one session's

    def read(self, r: Data) -> None:
        direction = r.direction
        offset = self.received[direction]
        end = self.received[direction] = offset + len(r.data)
        if direction is C2S:
            self.rec.reads.append(ClientRead(offset, r.t_ns, r.data))
            self.read_ends.append(end)
            self.read_times.append(r.t_ns)

    def observe(self, events: list) -> None:
        for obs in events:
            if not isinstance(obs, Observation):
                continue  # a late violation: replays judge unanswered requests themselves
            offset = self.framed[obs.direction]
            self.framed[obs.direction] = offset + len(obs.item.raw)
            if obs.direction is C2S:
                self.pending.append((obs, offset))
                if self.middle:
                    self.sent[obs.item].append(obs.index)
                self.motion.observe(obs)
            elif obs.item.kind is ItemKind.HANDSHAKE:
                self.rec.handshake.append(obs)
            elif obs.answers is not None:
                self.answers[obs.answers.index] = (obs, self.motion.at_rest(obs))

    def observe_received(self, events: list) -> None:
        """The events of the session over what the client sent and what it
        received: its answers, paired with the client's items (the same
        items, framed alike, as the one session's)."""
        for obs in events:
            if not isinstance(obs, Observation):
                continue
            if obs.direction is C2S:
                indexes = self.sent.get(obs.item)
                if indexes:
                    self._mine[obs.index] = indexes.popleft()
            elif obs.item.kind is ItemKind.HANDSHAKE:
                self.rec.received_handshake.append(obs)
            elif obs.answers is not None and obs.answers.index in self._mine:
                self.got[self._mine.pop(obs.answers.index)] = obs

    def finish(self, mode: Mode) -> RecordedConnection:
        rec = self.rec
        rec.mode = mode
        for obs, offset in self.pending:
            end = offset + len(obs.item.raw)
            i = bisect.bisect_left(self.read_ends, end)
            t = self.read_times[min(i, len(self.read_times) - 1)] if self.read_times else obs.item.t_end_ns
            answer, at_rest = self.answers.get(obs.index, (None, False))
            received = self.got.get(obs.index) if self.middle else answer
            rec.items.append(ClientItem(obs, offset, t, answer, at_rest, received))
        if not self.middle:
            rec.received_handshake = list(rec.handshake)
        return rec


def _checksum_rule(metadata: dict[str, dict[str, str]]) -> str:
    name = metadata.get(METADATA_NAME, {}).get("checksum_rule") or DEFAULT_CHECKSUM_RULE
    try:
        return get_rule(name).name
    except ValueError:
        return DEFAULT_CHECKSUM_RULE


def load_exchanges(recording: RecordingSet | Path | str, answer_timeout_ns: int = DEFAULT_ANSWER_TIMEOUT_NS,
                   assumed_channels: tuple[ChannelConfig, ...] = ()) -> RecordedSessions:
    """Read a recording (a ``RecordingSet`` or a path; all parts of a split
    one, as one); raises OSError, or RecordingError for a file that is no
    complete recording (one line).  ``answer_timeout_ns``: how long the
    client waited for an answer, for pairing what it received (in the
    middle, where an answer it never got leaves its request unanswered; a
    replay passes its ``--timeout``, so both pair alike).  ``assumed_channels``:
    the map ``--channels`` states (``Limits``), for a client that never fetched it."""
    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    metadata = read_metadata(str(recording.name))
    reader = _Reader(_checksum_rule({METADATA_NAME: metadata}), metadata.get("middle") == "yes", answer_timeout_ns,
                     assumed_channels)
    for event in scan_set(recording):
        reader.receive(event)
    connections = sorted((c for c in reader.finish() if c.reads or c.handshake), key=lambda c: c.conn)
    return RecordedSessions(str(recording.name), metadata, reader.start_ns or 0, connections)


class _Reader:
    """A recording's traffic events into each connection's ``_Builder``: one
    session over what each side sent, and, in the middle, one over what the
    client sent and what it received (``/tcp/delivered`` toward it)."""

    def __init__(self, rule: str, middle: bool, answer_timeout_ns: int,
                 assumed: tuple[ChannelConfig, ...] = ()) -> None:
        self.middle = middle
        self.builders: dict[int, _Builder] = {}
        self.modes: dict[int, Mode] = {}  # each connection's mode, when its session ends
        self.traffic = Traffic(lambda: Session(rule, assumed_channels=assumed),
                               lambda conn, session: self.modes.__setitem__(conn, session.mode))
        self.received = Traffic(lambda: Session(rule, answer_timeout_ns, assumed_channels=assumed)) if middle else None
        self.done: list[RecordedConnection] = []
        self.clients: dict[int, str] = {}
        self.start_ns: int | None = None

    def receive(self, event: TrafficEvent) -> None:
        conn, kind = event.conn, type(event)
        if type(event) is Opened:
            self.clients[conn] = event.client
            opened = self.builders[conn] = _Builder(conn, event.t_ns)
            opened.rec.client = self.clients[conn]
            opened.middle = self.middle
            return
        builder = self.builders.get(conn)
        if type(event) is Data:
            if self.start_ns is None:
                self.start_ns = event.t_ns
            if builder is None:  # a connection continued from a part not given
                builder = self.builders[conn] = _Builder(conn, event.t_ns)
                builder.rec.client = self.clients.get(conn, "")
                builder.middle = self.middle
            builder.read(event)
        elif builder is None:
            return
        if kind is not Delivered:
            builder.observe(self.traffic.receive(event))
        if self.received is not None:
            self._receive_received(self.received, builder, event)
        if kind is Closed:
            self.done.append(self.builders.pop(conn).finish(self.modes.pop(conn, Mode.UNKNOWN)))

    @staticmethod
    def _receive_received(received: Traffic, builder: _Builder, event: TrafficEvent) -> None:
        """What the client sent, and what it received instead of what the server sent."""
        if type(event) is Delivered:
            if event.direction is not S2C:
                return
            event = Data(event.conn, S2C, event.t_ns, event.data)
        elif type(event) is Data and event.direction is S2C:
            return
        builder.observe_received(received.receive(event))

    def finish(self) -> list[RecordedConnection]:
        if self.received is not None:
            for conn, events in self.received.finish():
                if conn in self.builders:
                    self.builders[conn].observe_received(events)
        for conn, events in self.traffic.finish():
            self.builders[conn].observe(events)
        return self.done + [b.finish(self.modes.pop(conn, Mode.UNKNOWN)) for conn, b in self.builders.items()]
