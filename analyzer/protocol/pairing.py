"""Requests waiting for their answers, found by what answers them, and given up.

The session pairs each answer with the oldest waiting request it fits: the
same item kind, the same channel (an answer without a channel fits any), and a
request that certainly expects an answer before one that only may (a frame that
may be a Sensor Request before the channel map says).  Scanning every waiting
request for each answer made a client that is never answered, or a server that
answers what nobody asked, cost quadratic time (20,000 unmatched pairs took
15 s); a ``Book`` finds the oldest fit in amortized constant time.

Each entry is queued once in arrival order and once under each key it can be
found by.  Taking one from the middle of a queue only marks it taken; a queue
drops taken entries when they reach its front, and when taken entries outnumber
the live ones every queue is rebuilt, so memory stays proportional to the
entries still waiting.  Entries join the keyed queues only when an answer
first has to look past the oldest: established traffic, answered in order,
never pays for them.

``Awaited`` keeps one session's two books, the requests awaited and those
given up, and their deadlines: the bookkeeping of pairing, apart from the
session that decides what pairs.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Iterator
from typing import NamedTuple

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import (
    FetchCameraImage,
    FetchConfiguration,
    Message,
    SensorRequest,
    ServoPositionRequest,
)
from whiztap.analyzer.protocol.observations import Event, LateViolation, Observation
from whiztap.analyzer.protocol.rules import Violation

REBUILD_SLACK = 1024  # taken entries tolerated in the queues beyond the live ones
PENDING_KEPT = 250_000  # requests awaited at once per connection; the oldest is given up beyond
EXPIRED_KEPT = 1024  # requests given up (deadline or cap) that a late answer may still pair with
# The item kind that answers each request.
_ANSWER_KIND = {
    FetchConfiguration: ItemKind.CONFIG,
    FetchCameraImage: ItemKind.IMAGE,
    SensorRequest: ItemKind.RESPONSE,
    ServoPositionRequest: ItemKind.RESPONSE,
}


def answer_spec(message: Message | None,
                candidates: tuple[Message, ...]) -> tuple[ItemKind | None, int | None, bool]:
    """What answer a command waits for: (item kind, channel, certain)."""
    if message is not None:
        return _ANSWER_KIND.get(type(message)), getattr(message, "channel", None), True
    for candidate in candidates:
        if isinstance(candidate, SensorRequest):
            # may be a Sensor Request: pair an answer if one comes, forgive it if none does
            return ItemKind.RESPONSE, candidate.channel, False
    return None, None, False


class Pending(NamedTuple):
    """A request waiting for its answer."""

    request: Observation
    answer_kind: ItemKind
    channel: int | None
    certain: bool  # False for an ambiguous frame that may be a Sensor Request
    t_ns: int


_Key = tuple[ItemKind, int | None, bool]


class Book:
    """Waiting requests: the oldest overall, and the oldest by what answers them.

    ``order`` is every entry still waiting, oldest first, and its first entry is
    always one still waiting (the session's fast paths read it directly).
    """

    def __init__(self) -> None:
        self.order: deque[Pending] = deque()
        self.live = 0  # entries still waiting
        # (kind, channel, certain): channel None queues every entry of the kind
        self._queues: dict[_Key, deque[Pending]] = {}
        self._unqueued = 0  # the last entries of ``order``, not in ``_queues`` yet
        self._taken: set[int] = set()  # request indexes taken out but maybe still queued

    def __len__(self) -> int:
        return self.live

    def __iter__(self) -> Iterator[Pending]:
        """The entries still waiting, oldest first."""
        taken = self._taken
        return (p for p in self.order if p.request.index not in taken)

    def add(self, pending: Pending) -> None:
        self.order.append(pending)
        self.live += 1
        self._unqueued += 1

    def pop_oldest(self) -> Pending:
        order = self.order
        pending = order.popleft()
        self.live -= 1
        if self._unqueued > len(order):
            self._unqueued -= 1  # it was in no keyed queue
        else:
            self._taken.add(pending.request.index)
            self._settle()
        return pending

    def take(self, kind: ItemKind, channel: int | None, certain_first: bool) -> Pending | None:
        """The oldest entry an answer of ``kind`` on ``channel`` (None: any) fits,
        taken out.  ``certain_first``: one that certainly expects an answer, if
        any does, before the oldest."""
        if self._unqueued:
            self._queue_new()
        sure = self._head((kind, channel, True))
        if sure is None or not certain_first:
            maybe = self._head((kind, channel, False))
            if sure is None or (maybe is not None and maybe.request.index < sure.request.index):
                sure = maybe
        if sure is not None:
            self._take(sure)
        return sure

    def __deepcopy__(self, memo: dict[int, object]) -> Book:
        """A copy with containers of its own; the entries, immutable tuples, are
        shared (a copied session awaits the same requests without copying them)."""
        book = Book()
        book.order.extend(self.order)
        book.live, book._unqueued = self.live, self._unqueued
        book._queues = {key: deque(queue) for key, queue in self._queues.items()}
        book._taken = set(self._taken)
        return book

    def clear(self) -> None:
        self.order.clear()
        self._queues.clear()
        self._taken.clear()
        self.live = self._unqueued = 0

    # -- internals ----------------------------------------------------------------------

    def _queue_new(self) -> None:
        """Put the entries not yet in keyed queues in them, in arrival order."""
        queues = self._queues
        tail = reversed(self.order)
        new = [next(tail) for _ in range(self._unqueued)]
        self._unqueued = 0
        for pending in reversed(new):
            kind, channel, certain = pending.answer_kind, pending.channel, pending.certain
            keys = ((kind, None, certain),) if channel is None else ((kind, None, certain), (kind, channel, certain))
            for key in keys:
                queue = queues.get(key)
                if queue is None:
                    queue = queues[key] = deque()
                queue.append(pending)

    def _head(self, key: _Key) -> Pending | None:
        queue = self._queues.get(key)
        if queue is None:
            return None
        taken = self._taken
        while queue and queue[0].request.index in taken:
            queue.popleft()
        if not queue:
            del self._queues[key]
            return None
        return queue[0]

    def _take(self, pending: Pending) -> None:
        self._taken.add(pending.request.index)
        self.live -= 1
        self._settle()

    def _settle(self) -> None:
        """Keep ``order``'s first entry a waiting one, and the taken ones few."""
        order, taken = self.order, self._taken
        while order and order[0].request.index in taken:
            order.popleft()
        if len(taken) > self.live + REBUILD_SLACK:
            self._rebuild()

    def _rebuild(self) -> None:
        """Drop every taken entry from every queue (in place: the session's
        fast paths hold ``order``)."""
        taken = self._taken
        waiting = [p for p in self.order if p.request.index not in taken]
        self.order.clear()
        self.order.extend(waiting)
        for key, queue in list(self._queues.items()):
            kept = [p for p in queue if p.request.index not in taken]
            if kept:
                self._queues[key] = deque(kept)
            else:
                del self._queues[key]
        taken.clear()


class Awaited:
    """One session's requests and their answers' deadlines: the only code
    that touches its books (tests put plain lists in their place).

    ``pending`` holds the requests awaited, at most ``pending_kept``: past
    that the oldest is given up, as at its deadline (``timeout_ns`` after it
    was sent).  ``expired`` holds the latest ``expired_kept`` given up: an
    answer that comes late still answers one of them, and is not
    unsolicited.  A request that certainly asked and is given up, or still
    awaited when the session closes, is reported unanswered
    (PW-PAIR-UNANSWERED, counted in the session's ``violation_counts``)."""

    def __init__(self, timeout_ns: int, violation_counts: Counter[str]) -> None:
        self.timeout_ns = timeout_ns
        self.violation_counts = violation_counts
        self.pending = Book()
        self.expired = Book()
        self.pending_kept = PENDING_KEPT
        self.expired_kept = EXPIRED_KEPT
        self.ended_why = "the session ended first"  # of requests still awaited at close

    def add(self, pending: Pending, events: list[Event]) -> None:
        """Await the answer to ``pending`` (the oldest request is given up if
        ``pending_kept`` are awaited already)."""
        if self.pending.live >= self.pending_kept:
            self.give_up_oldest(pending.t_ns, events)
        self.pending.add(pending)

    def take(self, kind: ItemKind, channel: int | None) -> Pending | None:
        """The request an answer of ``kind`` on ``channel`` (None: any) answers,
        taken out: the oldest awaited one it fits, one that certainly asked
        before a frame that only may be a Sensor Request (no channel map yet);
        else the oldest given up (already reported unanswered), so a late
        answer is not unsolicited."""
        return (self.pending.take(kind, channel, certain_first=True)
                or self.expired.take(kind, channel, certain_first=False))

    def expire(self, t: int, events: list[Event]) -> None:
        """Give up the requests whose deadline passed by ``t``, oldest first."""
        pending = self.pending.order
        while pending and t - pending[0].t_ns > self.timeout_ns:
            self._give_up(self.pending.pop_oldest(), t, events, f"no answer within {self.timeout_ns / 1e9:g} s")

    def give_up_oldest(self, t: int, events: list[Event]) -> None:
        """A request arrives while ``pending_kept`` are awaited: give up the oldest."""
        cap = self.pending_kept
        self._give_up(self.pending.pop_oldest(), t, events,
                      f"not answered while {cap} later requests were waiting (whiztap awaits at most {cap} at once)")

    def close(self, t: int, events: list[Event]) -> None:
        """The session is over: every request still awaited that certainly asked is unanswered."""
        for pending in self.pending:
            if pending.certain:
                events.append(self._unanswered(pending, t, self.ended_why))
        self.pending.clear()

    def _give_up(self, pending: Pending, t: int, events: list[Event], why: str) -> None:
        self.expired.add(pending)
        if self.expired.live > self.expired_kept:
            self.expired.pop_oldest()
        if pending.certain:
            events.append(self._unanswered(pending, t, why))

    def _unanswered(self, pending: Pending, t: int, why: str) -> LateViolation:
        self.violation_counts["PW-PAIR-UNANSWERED"] += 1
        title = pending.request.message.title if pending.request.message else "request"
        return LateViolation(Violation("PW-PAIR-UNANSWERED", f"{title}: {why}"), pending.request, t)
