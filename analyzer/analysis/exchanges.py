"""A recording as exchanges: what each client sent, and what its server answered.

Replaying a client's side, serving a server's side and showing either in the
TUI all start from the same facts: each connection's client items in stream
order with their offsets and times, the recorded answer paired to each request
by the session model, the server's handshake, and the client's raw reads (for
replays that re-send the original read boundaries).  This module rebuilds them
from a recording's raw reads, as every reader of recordings does.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from pathlib import Path

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.analysis.compare import ServoMotion
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import FailedValidation
from typing import NamedTuple

from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.recording.format import METADATA_NAME
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.analyzer.recording.sets import RecordingSet, scan_set
from whiztap.analyzer.traffic import Closed, Data, Opened, Traffic

C2S, S2C = Direction.C2S, Direction.S2C


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
    answer: Observation | None = None
    at_rest: bool = False  # the answer is a servo position reached and held

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
                self.motion.observe(obs)
            elif obs.item.kind is ItemKind.HANDSHAKE:
                self.rec.handshake.append(obs)
            elif obs.answers is not None:
                self.answers[obs.answers.index] = (obs, self.motion.at_rest(obs))

    def finish(self, mode: Mode) -> RecordedConnection:
        rec = self.rec
        rec.mode = mode
        for obs, offset in self.pending:
            end = offset + len(obs.item.raw)
            i = bisect.bisect_left(self.read_ends, end)
            t = self.read_times[min(i, len(self.read_times) - 1)] if self.read_times else obs.item.t_end_ns
            answer, at_rest = self.answers.get(obs.index, (None, False))
            rec.items.append(ClientItem(obs, offset, t, answer, at_rest))
        return rec


def _checksum_rule(metadata: dict[str, dict[str, str]]) -> str:
    name = metadata.get(METADATA_NAME, {}).get("checksum_rule") or DEFAULT_CHECKSUM_RULE
    try:
        return get_rule(name).name
    except ValueError:
        return DEFAULT_CHECKSUM_RULE


def load_exchanges(recording) -> RecordedSessions:  # noqa: ANN001 - a RecordingSet or a path
    """Read a recording (all parts of a split one, as one); raises OSError, or
    RecordingError for a file that is no complete recording (one line)."""
    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    metadata = read_metadata(str(recording.name))
    rule = _checksum_rule({METADATA_NAME: metadata})
    builders: dict[int, _Builder] = {}
    modes: dict[int, Mode] = {}  # each connection's mode, when its session ends
    traffic = Traffic(lambda: Session(rule), lambda conn, session: modes.__setitem__(conn, session.mode))
    done: list[RecordedConnection] = []
    clients: dict[int, str] = {}
    start_ns: int | None = None
    for event in scan_set(recording):
        conn, kind = event.conn, type(event)
        if kind is Opened:
            clients[conn] = event.client  # type: ignore[union-attr]
            builders[conn] = _Builder(conn, event.t_ns)
            builders[conn].rec.client = clients[conn]
            continue
        builder = builders.get(conn)
        if kind is Data:
            if start_ns is None:
                start_ns = event.t_ns
            if builder is None:  # a connection continued from a part not given
                builder = builders[conn] = _Builder(conn, event.t_ns)
                builder.rec.client = clients.get(conn, "")
            builder.read(event)  # type: ignore[arg-type]
        elif builder is None:
            continue
        builder.observe(traffic.receive(event))
        if kind is Closed:
            done.append(builders.pop(conn).finish(modes.pop(conn, Mode.UNKNOWN)))
    for conn, events in traffic.finish():
        builders[conn].observe(events)
    done += [b.finish(modes.pop(conn, Mode.UNKNOWN)) for conn, b in builders.items()]
    connections = sorted((c for c in done if c.reads or c.handshake), key=lambda c: c.conn)
    return RecordedSessions(str(recording.name), metadata, start_ns or 0, connections)
