"""TCP reassembly for captures: packets in, traffic events out.

Scapy's own TCPSession fills bytes missing from a capture with zeros without a
word; a recording must never invent bytes, so whiztap reassembles itself.  Each
direction keeps the next sequence number it expects.  A segment at or before it
is a retransmission (its new part, if any, is used); one after it waits in a
small buffer for the hole to fill.  A hole is declared a gap (an event, never
zeros: a ``Gap`` event with its length) when the receiver acknowledges bytes the capture never showed, or the
sender's FIN comes after them, and they still have not shown up
``ACK_GRACE_NS`` later (a capture taken on several CPUs can list a packet
after the ACK that answered it); when the connection resets or the capture
ends; or when too much waits behind it.

At most ``MAX_OPEN`` connections are followed at once, so a SYN flood costs
bounded memory: a new one evicts a connection that has carried no byte yet
(a half-open one), else the one idle longest.  An eviction is recorded as the
connection closing by the recorder (detail ``EVICTED``), never silently; an
evicted connection that sends bytes again is followed again, as a new
connection joined mid-stream.

Also here: decoding the link, IP and TCP headers of a captured frame by hand,
which is many times faster than dissecting it with Scapy.
"""

from __future__ import annotations

import itertools
import struct
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, Data, Gap, HalfClosed, Opened, UpstreamConnected, UpstreamFailed
from whiztap.sniffer.record.consumers import Consumer

C2S, S2C = Direction.C2S, Direction.S2C
MAX_PENDING = 4 << 20  # bytes waiting behind a hole before it is declared a gap
ACK_GRACE_NS = 200_000_000  # capture time an acknowledged hole waits for its bytes
MAX_ENDED = 4096  # closed connections remembered
MAX_OPEN = 10_000  # connections followed at once (about 6 KB each, with the recorder's session)
EVICTED = f"evicted: too many open connections (whiztap follows at most {MAX_OPEN} at once)"
FIN, SYN, RST, ACK = 0x01, 0x02, 0x04, 0x10

# Link types (pcap LINKTYPE_* values).
DLT_NULL, DLT_EN10MB, DLT_RAW, DLT_LOOP, DLT_LINUX_SLL, DLT_IPV4, DLT_IPV6, DLT_LINUX_SLL2 = (
    0, 1, 101, 108, 113, 228, 229, 276)
_ETH_IPV4, _ETH_IPV6, _ETH_VLAN = 0x0800, 0x86DD, (0x8100, 0x88A8)


class Segment(NamedTuple):
    t_ns: int
    src: tuple[str, int]
    dst: tuple[str, int]
    seq: int
    ack: int
    flags: int
    payload: bytes


def _ip_payload(linktype: int, frame: bytes) -> tuple[int, int] | None:
    """(IP version, offset of the IP header) in a captured frame, or None."""
    if linktype == DLT_EN10MB:
        ethertype, offset = struct.unpack_from("!H", frame, 12)[0], 14
        while ethertype in _ETH_VLAN and len(frame) >= offset + 4:
            ethertype, offset = struct.unpack_from("!H", frame, offset + 2)[0], offset + 4
    elif linktype in (DLT_NULL, DLT_LOOP):
        family = struct.unpack_from("<I" if linktype == DLT_NULL else "!I", frame, 0)[0]
        if family > 0xFFFF:  # DLT_NULL is in the capturing host's byte order
            family = struct.unpack_from("!I", frame, 0)[0]
        return (4, 4) if family == 2 else (6, 4) if family in (10, 24, 28, 30) else None
    elif linktype == DLT_LINUX_SLL:
        ethertype, offset = struct.unpack_from("!H", frame, 14)[0], 16
    elif linktype == DLT_LINUX_SLL2:
        ethertype, offset = struct.unpack_from("!H", frame, 0)[0], 20
    elif linktype in (DLT_RAW, DLT_IPV4, DLT_IPV6, 12, 14):
        return (frame[0] >> 4, 0) if frame else None
    else:
        return None
    return (4, offset) if ethertype == _ETH_IPV4 else (6, offset) if ethertype == _ETH_IPV6 else None


def parse_frame(linktype: int, frame: bytes, t_ns: int) -> Segment | None:
    """The TCP segment in a captured frame (None for anything else, fragments included)."""
    try:
        found = _ip_payload(linktype, frame)
        if found is None:
            return None
        version, ip = found
        if version == 4:
            ihl = (frame[ip] & 0x0F) * 4
            total, frag, proto = struct.unpack_from("!H2xH1xB", frame, ip + 2)
            if proto != 6 or frag & 0x3FFF:  # not TCP, or a fragment
                return None
            src = _ip4(frame[ip + 12:ip + 16])
            dst = _ip4(frame[ip + 16:ip + 20])
            tcp, end = ip + ihl, ip + total
        elif version == 6:
            length, next_header = struct.unpack_from("!HB", frame, ip + 4)
            if next_header != 6:
                return None
            src, dst = _ip6(frame[ip + 8:ip + 24]), _ip6(frame[ip + 24:ip + 40])
            tcp, end = ip + 40, ip + 40 + length
        else:
            return None
        sport, dport, seq, ack, offset_flags = struct.unpack_from("!HHIIH", frame, tcp)
        data_at = tcp + (offset_flags >> 12) * 4
        return Segment(t_ns, (src, sport), (dst, dport), seq, ack, offset_flags & 0x3F,
                       bytes(frame[data_at:min(end, len(frame))]))
    except (struct.error, IndexError):
        return None  # a frame cut short by the capture's snap length


def _ip4(b: bytes) -> str:
    return ".".join(str(x) for x in b)


def _ip6(b: bytes) -> str:
    import ipaddress

    return str(ipaddress.IPv6Address(b))


def endpoint_text(ep: tuple[str, int]) -> str:
    return f"[{ep[0]}]:{ep[1]}" if ":" in ep[0] else f"{ep[0]}:{ep[1]}"


def _diff(a: int, b: int) -> int:
    """a - b in 32-bit sequence space (positive: a is after b)."""
    return ((a - b + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)


@dataclass
class _Half:
    """One direction of a connection."""

    started: bool = False  # a segment of it was seen, so ``next`` is known
    next: int = 0  # sequence number of the next byte expected
    pending: dict[int, bytes] = field(default_factory=dict)
    pending_bytes: int = 0
    fin: int | None = None  # sequence number of the FIN
    done: bool = False  # FIN delivered
    owed: int | None = None  # bytes up to here were acknowledged (or FIN'd) but not yet seen
    owed_since: int = 0  # capture time they were first owed


@dataclass
class _Conn:
    id: int
    client: tuple[str, int]
    server: tuple[str, int]
    halves: dict[Direction, _Half] = field(default_factory=lambda: {C2S: _Half(), S2C: _Half()})
    established: bool = False
    closed_by: str | None = None


class Reassembler:
    """Turns the TCP segments to and from ``port`` into traffic events for
    ``consumer`` (``whiztap.sniffer.record.recorder.Recorder``)."""

    def __init__(self, port: int, consumer: Consumer, max_open: int = MAX_OPEN) -> None:
        self.port = port
        self.receive = consumer.receive
        self.max_open = max_open
        self.gaps = 0
        self._conns: OrderedDict[frozenset, _Conn] = OrderedDict()  # the one idle longest first
        self._quiet: OrderedDict[frozenset, None] = OrderedDict()  # those that carried no byte yet, same order
        # connections closed lately (their last ACKs, and loopback's duplicate
        # copies, still arrive; a SYN reuses the address pair for a new one),
        # True for those evicted (bytes from them are followed again)
        self._ended: OrderedDict[frozenset, bool] = OrderedDict()
        self._ids = itertools.count(1)

    def segment(self, s: Segment) -> None:
        if self.port not in (s.src[1], s.dst[1]):
            return
        key = frozenset((s.src, s.dst))
        conn = self._conns.get(key)
        if conn is None:
            ended = self._ended.get(key)
            if s.flags & RST or (ended is not None and s.flags & (SYN | ACK) != SYN and not (ended and s.payload)):
                return  # the tail of a connection already closed, or of one never seen
            self._ended.pop(key, None)
            conn = self._open(key, s)
        else:
            self._conns.move_to_end(key)
            if key in self._quiet:
                self._quiet.move_to_end(key)
        if s.payload:
            self._quiet.pop(key, None)
        direction = C2S if s.src == conn.client else S2C
        half = conn.halves[direction]
        if s.flags & SYN:
            if not half.started:
                half.started, half.next = True, (s.seq + 1) & 0xFFFFFFFF
            if direction is S2C and s.flags & ACK and not conn.established:
                conn.established = True
                self.receive(UpstreamConnected(conn.id, s.t_ns, "SYN-ACK"))
            return
        if s.flags & RST:
            self._reset(key, conn, direction, s.t_ns)
            return
        if not half.started:  # joined mid-stream
            half.started, half.next = True, s.seq
        if s.payload:
            self._data(conn, direction, half, s.seq, s.payload, s.t_ns)
        if s.flags & FIN and half.fin is None:
            half.fin = (s.seq + len(s.payload)) & 0xFFFFFFFF
            if conn.closed_by is None:
                conn.closed_by = direction.sender  # the first FIN, even if bytes before it are late
        if s.flags & ACK:
            self._acked(conn, S2C if direction is C2S else C2S, s.ack, s.t_ns)
        for d in (C2S, S2C):
            self._settle(conn, d, s.t_ns)
            self._maybe_fin(key, conn, d, s.t_ns)

    def finish(self, t_ns: int) -> None:
        """The capture ended: declare what is missing and close what is open."""
        for key, conn in list(self._conns.items()):
            for direction in (C2S, S2C):
                self._settle(conn, direction, t_ns, force=True)
                self._maybe_fin(key, conn, direction, t_ns)
            if key not in self._conns:
                continue  # both sides had closed: nothing more was coming
            for direction, half in conn.halves.items():
                self._flush_pending(conn, direction, half, t_ns)
            self._end(key)
            self.receive(Closed(conn.id, t_ns, "recorder", "the capture ended"))

    # -- internals ---------------------------------------------------------------------

    def _end(self, key: frozenset, evicted: bool = False) -> None:
        del self._conns[key]
        self._quiet.pop(key, None)
        self._ended[key] = evicted
        if len(self._ended) > MAX_ENDED:
            self._ended.popitem(last=False)

    def _evict(self, t: int) -> None:
        """Make room for a new connection: close the oldest half-open one, else the
        one idle longest, giving up on any bytes it still waits for."""
        key = next(iter(self._quiet or self._conns))
        conn = self._conns[key]
        for direction, half in conn.halves.items():
            self._settle(conn, direction, t, force=True)
            self._flush_pending(conn, direction, half, t)
        self._end(key, evicted=True)
        self.receive(Closed(conn.id, t, "recorder", EVICTED))

    def _open(self, key: frozenset, s: Segment) -> _Conn:
        if len(self._conns) >= self.max_open:
            self._evict(s.t_ns)
        if s.flags & SYN and not s.flags & ACK:
            client, server = s.src, s.dst
        elif s.src[1] == self.port and s.dst[1] != self.port:
            client, server = s.dst, s.src
        else:
            client, server = s.src, s.dst
        conn = _Conn(next(self._ids), client, server)
        if not s.flags & SYN:
            conn.established = True  # joined mid-stream
        self._conns[key] = conn
        self._quiet[key] = None
        self.receive(Opened(conn.id, s.t_ns, endpoint_text(client), endpoint_text(server)))
        return conn

    def _data(self, conn: _Conn, direction: Direction, half: _Half, seq: int, payload: bytes, t: int) -> None:
        ahead = _diff(seq, half.next)
        if ahead <= 0:
            payload = payload[-ahead:]  # a retransmission: keep only what is new
            if not payload:
                return
            self._deliver(conn, direction, half, payload, t)
            self._drain(conn, direction, half, t)
            return
        if len(half.pending.get(seq, b"")) < len(payload):  # out of order: wait for the hole
            half.pending_bytes += len(payload) - len(half.pending.get(seq, b""))
            half.pending[seq] = payload
        if half.pending_bytes > MAX_PENDING:
            self._flush_pending(conn, direction, half, t)

    def _deliver(self, conn: _Conn, direction: Direction, half: _Half, data: bytes, t: int) -> None:
        self.receive(Data(conn.id, direction, t, data))
        half.next = (half.next + len(data)) & 0xFFFFFFFF

    def _drain(self, conn: _Conn, direction: Direction, half: _Half, t: int) -> None:
        """Deliver waiting segments that now follow on."""
        progress = True
        while half.pending and progress:
            progress = False
            for seq in list(half.pending):
                ahead = _diff(seq, half.next)
                if ahead > 0:
                    continue
                payload = half.pending.pop(seq)
                half.pending_bytes -= len(payload)
                if len(payload) > -ahead:
                    self._deliver(conn, direction, half, payload[-ahead:], t)
                progress = True

    def _gap_to(self, conn: _Conn, direction: Direction, half: _Half, seq: int, t: int) -> None:
        length = _diff(seq, half.next)
        if length > 0:
            self.gaps += 1
            self.receive(Gap(conn.id, t, direction, length))
            half.next = seq
            self._drain(conn, direction, half, t)

    def _flush_pending(self, conn: _Conn, direction: Direction, half: _Half, t: int) -> None:
        """Give up on every hole: each becomes a gap, the data after it is delivered."""
        while half.pending:
            first = min(half.pending, key=lambda q: _diff(q, half.next))
            self._gap_to(conn, direction, half, first, t)

    def _acked(self, conn: _Conn, direction: Direction, ack: int, t: int) -> None:
        """The other side acknowledged ``direction`` up to ``ack``: bytes before it
        that the capture has not shown are owed (``_settle`` decides their fate)."""
        half = conn.halves[direction]
        if not half.started:
            return
        limit = ack if half.fin is None else min(ack, half.fin, key=lambda q: _diff(q, half.next))
        if _diff(limit, half.next) > 0:
            self._owe(half, limit, t)

    @staticmethod
    def _owe(half: _Half, limit: int, t: int) -> None:
        if half.owed is None:
            half.owed, half.owed_since = limit, t
        elif _diff(limit, half.owed) > 0:
            half.owed = limit

    def _settle(self, conn: _Conn, direction: Direction, t: int, force: bool = False) -> None:
        """Owed bytes that have still not shown up ``ACK_GRACE_NS`` after they were
        owed (or at once, with ``force``) are gone for good: gaps."""
        half = conn.halves[direction]
        if half.owed is None:
            return
        if half.done:  # every byte up to its FIN came: an ACK beyond it owes nothing
            half.owed = None
            return
        if _diff(half.owed, half.next) <= 0:
            half.owed = None  # they came after all
            return
        if not force and t - half.owed_since < ACK_GRACE_NS:
            return
        limit, half.owed = half.owed, None
        while half.pending:
            first = min(half.pending, key=lambda q: _diff(q, half.next))
            if _diff(first, limit) >= 0:
                break
            self._gap_to(conn, direction, half, first, t)
        self._gap_to(conn, direction, half, limit, t)

    def _maybe_fin(self, key: frozenset, conn: _Conn, direction: Direction, t: int) -> None:
        half = conn.halves[direction]
        if half.fin is None or half.done:
            return
        if half.next != half.fin:
            self._owe(half, half.fin, t)  # what came before the FIN may still show up
            return
        half.done = True
        if conn.closed_by is None:
            conn.closed_by = direction.sender
        self.receive(HalfClosed(conn.id, t, direction))
        if all(h.done for h in conn.halves.values()):
            self._end(key)
            self.receive(Closed(conn.id, t, conn.closed_by, "closed"))

    def _reset(self, key: frozenset, conn: _Conn, direction: Direction, t: int) -> None:
        for d, half in conn.halves.items():
            self._settle(conn, d, t, force=True)
            self._flush_pending(conn, d, half, t)
        self._end(key)
        if direction is S2C and not conn.established:
            self.receive(UpstreamFailed(conn.id, t, "connection refused (RST)"))
        self.receive(Closed(conn.id, t, direction.sender, "reset"))
