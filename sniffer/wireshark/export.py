"""A recording as TCP packets in a pcapng file, for Wireshark and tshark.

Each connection becomes one TCP conversation between the client's address
and the server's (the ``opened`` event's ``client`` and ``upstream``):
a handshake when it opened (SYN) and when the server answered
(``upstream_connected``: SYN-ACK, ACK), one segment per recorded read with
the read's time, FINs for half-closes and the close, a RST for a reset or a
server that refused.  Sequence numbers follow the reads' stream offsets, so
bytes missing from a recording (a capture gap, a missing part of a split
recording) are a jump in them, which Wireshark marks as a segment not
captured.  Reads are what each side *sent* (``/tcp/reads``), also in a
recording made with the proxy in the middle, where ``/tcp/delivered`` (what
each side received) is left out: a TCP conversation has one byte stream per
direction, and the sent one is the stream the analyzer judges.  Passwords
stay as the recording has them: masked, unless it was made with
--keep-secrets.  docs/wireshark.md says all this for users.
"""

from __future__ import annotations

import itertools
import shlex
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import IO

from whiztap.analyzer import __version__
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.sets import PartError, RecordingSet, scan_set
from whiztap.analyzer.traffic import (
    Closed,
    Continued,
    Data,
    Gap,
    HalfClosed,
    Opened,
    TrafficEvent,
    UpstreamConnected,
    UpstreamFailed,
)
from whiztap.sniffer.nettext import parse_address
from whiztap.sniffer.wireshark.pcapng import (
    ACK,
    FIN,
    MAX_PAYLOAD,
    PSH,
    RST,
    SYN,
    Endpoint,
    PcapNgWriter,
    endpoint,
    tcp_packet,
)

C2S, S2C = Direction.C2S, Direction.S2C
FALLBACK_SERVER = {4: endpoint("10.0.0.1", 5000), 6: endpoint("fd00::1", 5000)}
FALLBACK_CLIENT = {4: "10.0.0.2", 6: "fd00::2"}
MASKED_COMMENT = "whiztap: a password, masked ('*') in the recording"


def _other(direction: Direction) -> Direction:
    return S2C if direction is C2S else C2S


class ExportError(WhiztapError):
    """A recording could not be exported; one line for the user."""


def recorded_streams(recording: RecordingSet) -> Iterator[TrafficEvent]:
    """The traffic of every part of a recording, through the one reader of
    recording sets (``scan_set``), its reads with their stream offsets and
    masked flags.  Raises ``ExportError``."""
    try:
        yield from scan_set(recording)
    except PartError as e:
        if e.truncated:
            raise ExportError(f"{e}; first make a complete copy: whiztap recover {shlex.quote(str(e.path))}") from None
        raise ExportError(str(e)) from None
    except OSError as e:  # a URL's connection lost in the middle
        raise ExportError(f"{recording}: cannot read ({e.strerror or e})") from None


def _endpoint(text: str) -> Endpoint | None:
    """A recorded HOST:PORT as an endpoint; None for one that is not an IP address and a port 1-65535."""
    try:
        host, port = parse_address(text, None, "address")
        return endpoint(host, port) if port else None
    except ValueError:  # AddressError too
        return None


def addresses(conn: int, client: str, upstream: str) -> tuple[Endpoint, Endpoint]:
    """The client's and the server's endpoints for connection ``conn``: as
    recorded, else 10.0.0.x (fd00::x) stand-ins.  A client of another address
    family than the server's (a proxy listening on IPv6 in front of an IPv4
    server) gets a stand-in too: one TCP conversation has one family."""
    server = _endpoint(upstream) or FALLBACK_SERVER[4]
    found = _endpoint(client)
    if found is None or found.version != server.version or found == server:
        found = endpoint(FALLBACK_CLIENT[server.version], 1024 + (conn - 1) % 64000)
    return found, server


@dataclass
class _Conn:
    """One connection's TCP state: sequence numbers follow stream offsets."""

    ends: dict[Direction, tuple[Endpoint, Endpoint]]
    isn: dict[Direction, int]
    sent: dict[Direction, int] = field(default_factory=lambda: {C2S: 0, S2C: 0})
    fin: dict[Direction, bool] = field(default_factory=lambda: {C2S: False, S2C: False})
    synchronized: bool = False  # the handshake is done (or the connection began before the recording)
    over: bool = False  # reset, refused or closed: nothing more is sent

    def seq(self, direction: Direction) -> int:
        return self.isn[direction] + 1 + self.sent[direction] + self.fin[direction]


@dataclass
class ExportSummary:
    connections: int = 0
    packets: int = 0
    bytes: int = 0


class TcpExport:
    """Reads and connection events in, TCP packets out to a ``PcapNgWriter``."""

    def __init__(self, writer: PcapNgWriter) -> None:
        self.writer = writer
        self.summary = ExportSummary()
        self._conns: dict[int, _Conn] = {}
        self._ip_ids = itertools.count(1)

    def receive(self, item: TrafficEvent) -> None:
        """One event of the recording as packets; what each side received
        (``Delivered``) and the proxy's changes are not part of a TCP
        conversation's one stream per direction, and are left out."""
        match item:
            case Data():
                self._read(item)
            case Opened() | Continued():
                self._open(item)
            case UpstreamConnected():
                self._handshake(self._conn(item.conn), item.t_ns)
            case UpstreamFailed():
                self._refused(item)
            case Gap():
                self._gap(item)
            case HalfClosed():
                self._fin(self._conn(item.conn), item.direction, item.t_ns)
            case Closed():
                self._closed(item)

    # -- events ------------------------------------------------------------------------

    def _open(self, event: Opened | Continued) -> None:
        client, server = addresses(event.conn, event.client, event.upstream)
        isn = (event.conn * 2654435761) & 0xFFFFFFFF  # fixed: the same recording exports the same bytes
        conn = _Conn({C2S: (client, server), S2C: (server, client)}, {C2S: isn, S2C: isn ^ 0x5A5A5A5A})
        self._conns[event.conn] = conn
        self.summary.connections += 1
        if type(event) is Continued:  # it began before this recording: no handshake to show
            conn.sent = {C2S: event.c2s_offset, S2C: event.s2c_offset}
            conn.synchronized = True
        else:
            self._send(conn, C2S, event.t_ns, SYN)

    def _conn(self, conn_id: int) -> _Conn:
        """The connection, made up as joined mid-stream if the recording never said it opened."""
        conn = self._conns.get(conn_id)
        if conn is None:
            self._open(Continued(conn_id, 0))
            conn = self._conns[conn_id]
        return conn

    def _handshake(self, conn: _Conn, t_ns: int) -> None:
        if conn.synchronized or conn.over:
            return
        conn.synchronized = True
        self._send(conn, S2C, t_ns, SYN | ACK)
        self._send(conn, C2S, t_ns, ACK)

    def _read(self, read: Data) -> None:
        conn = self._conn(read.conn)
        self._handshake(conn, read.t_ns)  # bytes the client sent before the server answered
        direction = read.direction
        data = read.data
        if read.offset > conn.sent[direction]:
            conn.sent[direction] = read.offset  # bytes missing: the sequence numbers jump
        elif read.offset < conn.sent[direction]:
            data = data[conn.sent[direction] - read.offset:]
        for start in range(0, len(data), MAX_PAYLOAD):
            piece = data[start:start + MAX_PAYLOAD]
            last = start + MAX_PAYLOAD >= len(data)
            comment = MASKED_COMMENT if read.masked and start == 0 else ""
            self._send(conn, direction, read.t_ns, ACK | (PSH if last else 0), piece, comment)
            conn.sent[direction] += len(piece)
            self.summary.bytes += len(piece)

    def _gap(self, gap: Gap) -> None:
        conn = self._conn(gap.conn)
        start = conn.sent[gap.direction] if gap.offset is None else gap.offset
        conn.sent[gap.direction] = max(conn.sent[gap.direction], start + (gap.length or 0))

    def _refused(self, event: UpstreamFailed) -> None:
        conn = self._conn(event.conn)
        if not conn.synchronized and not conn.over:
            self._send(conn, S2C, event.t_ns, RST | ACK)
            conn.over = True

    def _fin(self, conn: _Conn, direction: Direction, t_ns: int) -> None:
        if conn.fin[direction] or conn.over:
            return
        self._handshake(conn, t_ns)
        self._send(conn, direction, t_ns, FIN | ACK)
        conn.fin[direction] = True

    def _closed(self, event: Closed) -> None:
        conn = self._conns.pop(event.conn, None)
        if conn is None or conn.over:
            return
        closer = C2S if event.by == "client" else S2C
        if not conn.synchronized or event.detail.startswith("reset"):
            self._send(conn, closer, event.t_ns, RST | (ACK if conn.synchronized else 0))
            return
        last = None
        for direction in (closer, _other(closer)):
            if not conn.fin[direction]:
                self._fin(conn, direction, event.t_ns)
                last = direction
        if last is None:  # both had half-closed: the last FIN is the later one's
            last = _other(closer)
        self._send(conn, _other(last), event.t_ns, ACK)

    def _send(self, conn: _Conn, direction: Direction, t_ns: int, flags: int, payload: bytes = b"",
              comment: str = "") -> None:
        src, dst = conn.ends[direction]
        seq = conn.isn[direction] if flags & SYN else conn.seq(direction)
        ack = conn.seq(_other(direction)) if conn.synchronized or flags & SYN else 0
        self.writer.packet(t_ns, tcp_packet(src, dst, seq, ack, flags, payload, next(self._ip_ids)), comment)
        self.summary.packets += 1


def export_pcapng(recording: RecordingSet, out: IO[bytes]) -> ExportSummary:
    """Write ``recording`` to ``out`` as pcapng; what was written.  Raises ``ExportError``."""
    writer = PcapNgWriter(out, f"whiztap {__version__}", f"Progwhiz traffic exported by whiztap from {recording}")
    export = TcpExport(writer)
    for item in recorded_streams(recording):
        export.receive(item)
    return export.summary
