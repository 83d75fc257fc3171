"""Progwhiz conversations found by their content, for ``whiztap capture``
without ``--port``: a user who does not know the server's port still gets a
recording.

Every TCP conversation's segments are held (a few at most) until the first
bytes one side sends say what it is.  A Progwhiz conversation opens with a
frame header or a handshake word from one side, and which side sends it
(``sender_of`` in analyzer/protocol/observations.py: the protocol's rule, not
the capture's) tells which is the server, and its port; the held segments and
everything after them then go to a ``Reassembler`` for that port, exactly as
with ``--port``.  A conversation whose first bytes from both sides are
something else is not followed.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass, field

from whiztap.analyzer.protocol.observations import LONGEST_OPENING, Direction, may_tell, sender_of
from whiztap.analyzer.traffic import TrafficEvent
from whiztap.sniffer.record.consumers import Consumer
from whiztap.sniffer.record.tcpreasm import ACK, SYN, Reassembler, Segment

LOOKED_AT = LONGEST_OPENING  # first bytes per side that decide
MAX_HELD = 64  # segments held for one undecided conversation; past that it is not followed
MAX_UNDECIDED = 10_000  # conversations undecided at once (a SYN flood): the oldest is given up
MAX_DECIDED = 100_000  # conversations remembered, followed or not


@dataclass
class _Undecided:
    held: list[Segment] = field(default_factory=list)
    first: dict[tuple[str, int], bytes] = field(default_factory=dict)  # each sender's first bytes
    refused: set[tuple[str, int]] = field(default_factory=set)  # senders whose first bytes are not Progwhiz


class _Renumber:
    """One id sequence for the connections of several reassemblers, in the order they open."""

    def __init__(self, consumer: Consumer) -> None:
        self.receive_next = consumer.receive
        self.ids: dict[tuple[int, int], int] = {}

    def for_port(self, index: int) -> Consumer:
        return _PortConsumer(self, index)

    def forward(self, index: int, event: TrafficEvent) -> None:
        key = (index, event.conn)
        conn = self.ids.get(key)
        if conn is None:
            conn = self.ids[key] = len(self.ids) + 1
        if isinstance(event, tuple):  # Data, a NamedTuple
            self.receive_next(event._replace(conn=conn))
        else:
            self.receive_next(dataclasses.replace(event, conn=conn))


class _PortConsumer:
    """What the reassembler of one server port feeds: its connections renumbered."""

    def __init__(self, renumber: _Renumber, index: int) -> None:
        self.renumber = renumber
        self.index = index

    def receive(self, event: TrafficEvent) -> None:
        self.renumber.forward(self.index, event)


class ContentDetector:
    """Like a ``Reassembler`` (``segment``, ``finish``, ``gaps``), for the
    Progwhiz conversations on any port."""

    def __init__(self, consumer: Consumer) -> None:
        self._renumber = _Renumber(consumer)
        self._by_port: dict[int, Reassembler] = {}
        self._undecided: OrderedDict[frozenset, _Undecided] = OrderedDict()
        self._decided: OrderedDict[frozenset, int | None] = OrderedDict()  # the server port, None: not Progwhiz

    @property
    def gaps(self) -> int:
        return sum(r.gaps for r in self._by_port.values())

    def segment(self, s: Segment) -> None:
        key = frozenset((s.src, s.dst))
        if s.flags & (SYN | ACK) == SYN:
            self._decided.pop(key, None)  # a new connection on these addresses: look again
        elif key in self._decided:
            port = self._decided[key]
            if port is not None:
                self._by_port[port].segment(s)
            return
        pending = self._undecided.get(key)
        if pending is None:
            pending = self._undecided[key] = _Undecided()
            if len(self._undecided) > MAX_UNDECIDED:
                self._decide(next(iter(self._undecided)), None)
        pending.held.append(s)
        if s.payload and s.src not in pending.refused:
            self._look(key, pending, s)
        elif len(pending.held) > MAX_HELD:
            self._decide(key, None)

    def finish(self, t_ns: int) -> None:
        for reassembler in self._by_port.values():
            reassembler.finish(t_ns)

    def _look(self, key: frozenset, pending: _Undecided, s: Segment) -> None:
        """The sender's first bytes so far: Progwhiz, not, or not yet known."""
        first = pending.first.get(s.src, b"") + s.payload
        head = pending.first[s.src] = first[:LOOKED_AT]
        sender = sender_of(head)
        if sender is not None:
            self._decide(key, s.src[1] if sender is Direction.S2C else s.dst[1])
        elif not may_tell(head) or len(first) >= LOOKED_AT:
            pending.refused.add(s.src)
            if len(pending.refused) == 2:
                self._decide(key, None)
        if key in self._undecided and len(pending.held) > MAX_HELD:
            self._decide(key, None)

    def _decide(self, key: frozenset, port: int | None) -> None:
        pending = self._undecided.pop(key)
        self._decided[key] = port
        if len(self._decided) > MAX_DECIDED:
            self._decided.popitem(last=False)
        if port is None:
            return
        reassembler = self._by_port.get(port)
        if reassembler is None:
            reassembler = self._by_port[port] = Reassembler(port, self._renumber.for_port(len(self._by_port)))
        for held in pending.held:
            reassembler.segment(held)
