"""Each answer's latency for the server and for the client, one answer at a time.

Reports give latencies as statistics (``sides.py`` times both views); a view
that shows answers one by one (``whiztap cat``) needs them per answer.  When
the proxy stood in the middle the two differ: the server's is from the
request as it received it (delivered ``c2s``) to the answer it sent (read
``s2c``), the client's from the request as it sent it (read ``c2s``) to the
answer as it received it (delivered ``s2c``).  ``AnswerLatencies`` runs the
two views of ``sides.py`` over the traffic events and tells, for an answer of
the one session over what each side sent (the session ``cat`` shows):

- ``server_ns(conn, answer)``: the server's latency, known as soon as the
  event that completed the answer was received (the server's view sees that
  same item: its answers are what the server sent);
- ``client_ns(conn, request)``: the client's latency for the request the
  answer answers, once the client's view has paired that request with an
  answer it received (``Known``), or once it gave up on it (``Known(None)``):
  possibly later, when the proxy held the answer back.

Requests and answers are found across sessions by their item (the same bytes
at the same times: the views frame the same streams as the one session).
What a view found and nobody asked for is forgotten past ``kept`` entries.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable
from typing import NamedTuple

from whiztap.analyzer.protocol.framing import Item
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.traffic import (
    Closed,
    Data,
    Delivered,
    Gap,
    HalfClosed,
    Traffic,
    TrafficEvent,
    UpstreamFailed,
)

_Key = tuple[int, Item]  # a connection and an item of it
_ENDS = (HalfClosed, Closed, Gap, UpstreamFailed)


class Known(NamedTuple):
    """A latency known (``ns`` None: there is none: the request was given up)."""

    ns: int | None


class AnswerLatencies:
    """The server's and the client's view of a recording made in the middle,
    kept for each answer's latencies (see the module docstring)."""

    def __init__(self, new_session: Callable[[], Session], kept: int = 100_000) -> None:
        self._server = Traffic(new_session)
        self._client = Traffic(new_session)
        self._kept = kept
        self._served: OrderedDict[_Key, deque[int | None]] = OrderedDict()
        self._waited: OrderedDict[_Key, deque[int | None]] = OrderedDict()

    def receive(self, event: TrafficEvent) -> None:
        """One traffic event, into the views it belongs to (before the one
        session takes it, so that what it completes is known here first)."""
        if type(event) is Data:
            if event.direction is Direction.S2C:
                self._server_events(event.conn, self._server.receive(event))
            else:
                self._client_events(event.conn, self._client.receive(event))
        elif type(event) is Delivered:
            conn, direction, t_ns, data, _secret = event
            data_event = Data(conn, direction, t_ns, data)
            if direction is Direction.C2S:
                self._server_events(conn, self._server.receive(data_event))
            else:
                self._client_events(conn, self._client.receive(data_event))
        elif type(event) in _ENDS:
            self._server_events(event.conn, self._server.receive(event))
            self._client_events(event.conn, self._client.receive(event))

    def finish(self) -> None:
        """The traffic is over: requests the client's view still awaits are given up."""
        self._server.finish()
        for conn, events in self._client.finish():
            self._client_events(conn, events)

    def server_ns(self, conn: int, answer: Observation) -> int | None:
        """The server's latency for this answer (None: it answers nothing the server received)."""
        return _take(self._served, (conn, answer.item))

    def client_ns(self, conn: int, request: Observation) -> Known | None:
        """The client's latency for this request, once known (None: not yet)."""
        found = self._waited.get((conn, request.item))
        if not found:
            return None
        return Known(_take(self._waited, (conn, request.item)))

    # -- internals ---------------------------------------------------------------------

    def _server_events(self, conn: int, events: list[Event]) -> None:
        for e in events:
            if type(e) is Observation and e.answers is not None:
                self._put(self._served, (conn, e.item), e.latency_ns)

    def _client_events(self, conn: int, events: list[Event]) -> None:
        for e in events:
            if type(e) is LateViolation:
                if e.violation.rule_id == "PW-PAIR-UNANSWERED":
                    self._put(self._waited, (conn, e.about.item), None)
            elif type(e) is Observation and e.answers is not None:
                self._put(self._waited, (conn, e.answers.item), e.latency_ns)

    def _put(self, book: OrderedDict[_Key, deque[int | None]], key: _Key, value: int | None) -> None:
        found = book.get(key)
        if found is None:
            found = book[key] = deque()
        found.append(value)
        while len(book) > self._kept:
            book.popitem(last=False)


def _take(book: OrderedDict[_Key, deque[int | None]], key: _Key) -> int | None:
    found = book.get(key)
    if not found:
        return None
    value = found.popleft()
    if not found:
        del book[key]
    return value
