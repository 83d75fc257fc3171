"""The primary server's answers against a mirror's, paired live as ``whiztap diff`` pairs two recordings.

``record --mirror`` feeds each client's bytes to a second server too; this
module judges what the two servers made of the same requests, while the
traffic flows, without a socket: the writer process feeds it the primary's
traffic as the file has it (a password already masked) and the mirror's
answers, and takes the differences it returns.

Each connection is two conversations over the one client stream: the client
with the primary, and the client with the mirror, each in a ``Session`` of its
own.  Both sessions frame the same client bytes, so their requests come in
the same order: the n-th request of one side meets the n-th of the other,
named as ``diff`` names it (kind, channel, position among its kind and
channel), and the pair is judged by ``diff``'s own judging (``_pair``: the
request's bytes, the answer's fields, latency beyond the tolerance, the rules
each side broke) once both answers are in, or given up on (the session's
answer timeout), so a difference shows while the connection is still open.
The handshakes are compared when the connection ends (``_handshake``).

A mirror that ends early (dropped, refused, closed on its own) cuts its
connection's comparison where it ended: requests the client sent after that
are counted as not compared, never reported as missing.  Memory is bounded
whatever either server does: at most ``MAX_WAITING`` requests wait per side
(past that the oldest are judged as they stand) and ``MAX_HANDSHAKE``
handshake items are kept.
"""

from __future__ import annotations

from collections import defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from whiztap.analyzer.analysis.compare import LATENCY_TOLERANCE_MS, answer_key
from whiztap.analyzer.analysis.diff import DiffResult, Difference, _handshake, _pair, exchange_key
from whiztap.analyzer.analysis.exchanges import ClientItem, RecordedConnection
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.session import Session

C2S, S2C = Direction.C2S, Direction.S2C
MAX_WAITING = 4096  # requests waiting for their answer, per side of a connection
MAX_HANDSHAKE = 16  # handshake items kept per side (a Winsock handshake has three)


@dataclass(slots=True)
class _Request:
    item: ClientItem
    done: bool  # answered, given up on, or asking nothing


class _Side:
    """One conversation of a connection: the client's bytes with one server's answers."""

    def __init__(self, session: Session, timeout_ns: int) -> None:
        self.session = session
        self.timeout_ns = timeout_ns
        self.framed = 0  # client bytes framed so far
        self.fed = 0  # client bytes fed so far
        self.now = 0  # the latest time this side has seen
        self.waiting: deque[_Request] = deque()
        self.asked: dict[int, _Request] = {}  # the session's request index -> its request, until answered
        self.handshake: list[Observation] = []
        self.password: ClientItem | None = None

    def feed(self, direction: Direction, data: bytes, t_ns: int) -> None:
        self.now = max(self.now, t_ns)
        if direction is C2S:
            self.fed += len(data)
        self.take(self.session.receive(direction, data, t_ns))

    def take(self, events: list[Event]) -> None:
        for event in events:
            if isinstance(event, LateViolation):  # the session gave up on a request
                given_up = self.asked.pop(event.about.index, None)
                if given_up is not None:
                    given_up.done = True
                continue
            obs = event
            kind = obs.item.kind
            if obs.direction is C2S:
                offset = self.framed
                self.framed += len(obs.item.raw)
                if kind is ItemKind.PASSWORD:
                    self.password = ClientItem(obs, offset, obs.item.t_end_ns)
                elif kind is ItemKind.COMMAND:
                    request = _Request(ClientItem(obs, offset, obs.item.t_end_ns), answer_key(obs) is None)
                    self.waiting.append(request)
                    if not request.done:
                        self.asked[obs.index] = request
            elif kind is ItemKind.HANDSHAKE:
                if len(self.handshake) < MAX_HANDSHAKE:
                    self.handshake.append(obs)
            elif obs.answers is not None:
                answered = self.asked.pop(obs.answers.index, None)
                if answered is not None:
                    answered.item = ClientItem(answered.item.obs, answered.item.offset, answered.item.t_ns, obs)
                    answered.done = True

    def ready(self) -> bool:
        """Whether the oldest waiting request can be judged: answered, or waited for past the timeout."""
        front = self.waiting[0]
        return front.done or self.now - front.item.t_ns > self.timeout_ns

    def pop(self) -> ClientItem:
        """The oldest request, out of the comparison's waiting."""
        request = self.waiting.popleft()
        self.asked.pop(request.item.obs.index, request)
        return request.item

    def close(self, t_ns: int) -> None:
        self.take(self.session.close(max(t_ns, self.now)))
        for request in self.waiting:
            request.done = True

    def as_connection(self, conn: int) -> RecordedConnection:
        """What ``diff``'s handshake comparison reads."""
        return RecordedConnection(conn, 0, mode=self.session.mode, handshake=self.handshake,
                                  items=[self.password] if self.password is not None else [])


@dataclass(slots=True)
class _Pair:
    primary: _Side
    mirror: _Side
    # (title, channel) -> requests so far: the positions diff names them by
    seen: dict[tuple[str, int | None], int] = field(default_factory=lambda: defaultdict(int))
    cut: int | None = None  # the mirror ended: client bytes past this offset are not compared
    mirror_started: bool = False  # the mirror's connection was made
    primary_closed: bool = False
    mirror_ended: bool = False


@dataclass(slots=True)
class MirrorTally:
    """What the pairing found so far: ``result`` counts the exchanges compared and the
    differences by kind (it keeps none: each is handed back as it is found)."""

    result: DiffResult = field(default_factory=lambda: DiffResult("primary", "mirror", LATENCY_TOLERANCE_MS, 0))
    connections: int = 0  # connections whose comparison is over
    not_compared: int = 0  # requests the mirror never got (it ended first)


class MirrorPairing:
    """Each connection's primary and mirror conversations, judged as they go.

    ``opened``, ``client`` (the client's bytes as recorded), ``primary`` (the
    primary's), ``client_ended`` and ``primary_closed`` follow the primary's
    connection; ``mirror_started``, ``mirror`` (its answers) and
    ``mirror_ended`` follow the mirror's.  Each returns the differences it
    completed (also counted in ``tally``)."""

    def __init__(self, new_session: Callable[[], Session], answer_timeout_ns: int,
                 latency_tolerance_ms: float = LATENCY_TOLERANCE_MS) -> None:
        self.new_session = new_session
        self.timeout_ns = answer_timeout_ns
        self.tolerance_ns = int(latency_tolerance_ms * 1e6)
        self.tally = MirrorTally(DiffResult("primary", "mirror", latency_tolerance_ms, 0))  # the primary is A
        self.pairs: dict[int, _Pair] = {}

    def opened(self, conn: int) -> None:
        self.pairs[conn] = _Pair(_Side(self.new_session(), self.timeout_ns), _Side(self.new_session(), self.timeout_ns))

    def client(self, conn: int, data: bytes, t_ns: int) -> list[Difference]:
        pair = self.pairs.get(conn)
        if pair is None:
            return []
        pair.primary.feed(C2S, data, t_ns)
        if not pair.mirror_ended:
            pair.mirror.feed(C2S, data, t_ns)
        return self._judge(conn, pair)

    def primary(self, conn: int, data: bytes, t_ns: int) -> list[Difference]:
        pair = self.pairs.get(conn)
        if pair is None:
            return []
        pair.primary.feed(S2C, data, t_ns)
        return self._judge(conn, pair)

    def client_ended(self, conn: int, t_ns: int) -> list[Difference]:
        """The client's FIN: both conversations know no more requests come."""
        pair = self.pairs.get(conn)
        if pair is None:
            return []
        for side in (pair.primary, pair.mirror) if not pair.mirror_ended else (pair.primary,):
            side.take(side.session.end(C2S, t_ns))
        return self._judge(conn, pair)

    def primary_closed(self, conn: int, t_ns: int) -> list[Difference]:
        pair = self.pairs.get(conn)
        if pair is None:
            return []
        pair.primary_closed = True
        pair.primary.close(t_ns)
        return self._judge(conn, pair)

    def mirror_started(self, conn: int) -> None:
        pair = self.pairs.get(conn)
        if pair is not None:
            pair.mirror_started = True

    def mirror(self, conn: int, data: bytes, t_ns: int) -> list[Difference]:
        pair = self.pairs.get(conn)
        if pair is None or pair.mirror_ended:
            return []
        pair.mirror.feed(S2C, data, t_ns)
        return self._judge(conn, pair)

    def mirror_ended(self, conn: int, t_ns: int, sent: int | None = None) -> list[Difference]:
        """The mirror's connection is over (it closed, or was dropped or never made), having
        been sent ``sent`` bytes of the client's (None: all so far): requests past them are
        not compared."""
        pair = self.pairs.get(conn)
        if pair is None or pair.mirror_ended:
            return []
        pair.mirror_ended = True
        pair.cut = pair.mirror.fed if sent is None else min(sent, pair.mirror.fed)
        pair.mirror.close(t_ns)
        return self._judge(conn, pair)

    def finish(self, t_ns: int) -> list[Difference]:
        """The recording ends: every connection's comparison ends with it."""
        out: list[Difference] = []
        for conn in list(self.pairs):
            out += self.primary_closed(conn, t_ns) + self.mirror_ended(conn, t_ns)
        return out

    # -- judging ----------------------------------------------------------------------------

    def _judge(self, conn: int, pair: _Pair) -> list[Difference]:
        out: list[Difference] = []
        a, b = pair.primary, pair.mirror
        self._past_cut(pair)
        while a.waiting and b.waiting:
            over = len(a.waiting) > MAX_WAITING or len(b.waiting) > MAX_WAITING  # judged as they stand
            if not (over or (a.ready() and b.ready())):
                break
            out += self._compare(conn, pair, a.pop(), b.pop())
        for side in (a, b):  # one side far ahead of an empty other: its oldest go uncompared
            while len(side.waiting) > MAX_WAITING:
                side.pop()
                self.tally.not_compared += 1
        if pair.primary_closed and pair.mirror_ended:
            out += self._end(conn, pair)
        return self._count(out)

    def _compare(self, conn: int, pair: _Pair, item_a: ClientItem, item_b: ClientItem) -> list[Difference]:
        """The same request (the same bytes, at the same place in the client's stream) and each
        server's answer, named as the primary's session reads it: the mirror's may read it
        otherwise until its configuration answer has come, which says nothing of the request."""
        self.tally.result.exchanges += 1
        key = exchange_key(item_a)
        if key in pair.seen or len(pair.seen) < MAX_WAITING:  # a client's endless channel numbers: past the
            pair.seen[key] += 1  # bound, named without a position
        return _pair(conn, (*key, pair.seen.get(key, 0)), item_a, item_b, self.tolerance_ns)

    def _past_cut(self, pair: _Pair) -> None:
        """Requests the mirror never got (sent after it ended) leave the comparison, counted."""
        if pair.cut is None:
            return
        for side in (pair.primary, pair.mirror):
            waiting = side.waiting
            while waiting and waiting[-1].item.end > pair.cut:
                request = waiting.pop()
                side.asked.pop(request.item.obs.index, request)
                self.tally.not_compared += side is pair.primary  # counted once, as the client's request

    def _end(self, conn: int, pair: _Pair) -> list[Difference]:
        del self.pairs[conn]
        self.tally.connections += 1
        leftover = len(pair.primary.waiting) + len(pair.mirror.waiting)
        self.tally.not_compared += leftover
        if not pair.mirror_started:  # never connected: nothing of the mirror to compare
            return []
        return _handshake(conn, pair.primary.as_connection(conn), pair.mirror.as_connection(conn))

    def _count(self, differences: list[Difference]) -> list[Difference]:
        if differences:
            self.tally.result.add(differences)
        return differences

