"""The TUI's model of a connection the proxy stands in the middle of.

In the middle, what the client sent is not what the server got.  The list
shows the conversation as the server had it (the bytes delivered to it, and
what it sent: so an injected request pairs with its answer, and an edited
frame shows what the server will make of it), plus what the proxy did: each
frame carries the marks of its interventions, a frame the client sent that
the server never got (dropped) and one the proxy sent to the client on its own
(injected) are rows no session saw.

Marks find their frame by its bytes: an answer's (s2c) row is what the server
sent, so a mark there matches the ``before`` bytes of one of the connection's
latest answers; a request's (c2s) row is what the server received, which
comes after the proxy's decision, so its marks wait until a delivered frame
with their ``after`` bytes is stored.
"""

from __future__ import annotations

from collections.abc import Callable

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction, Event
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.traffic import Data, Delivered, Intervention, TrafficEvent
from whiztap.sniffer.mitm.frame import observe_bytes
from whiztap.tui.marks import Mark
from whiztap.tui.store import FrameStore

C2S, S2C = Direction.C2S, Direction.S2C
PENDING_MAX = 256  # marks of one connection waiting for their frame; the oldest go past this
_HELD = "(held #"


def kind_of(raw: bytes, direction: Direction) -> ItemKind:
    """The kind of bytes dropped or injected on their own, framed as the proxy
    frames typed bytes (``observe_bytes``); UNFRAMED unless they are one item.
    (Not the Intervention's recorded ``kind``: that is the sender's frame's,
    and an earlier stage may have changed the bytes since.)"""
    item = observe_bytes(raw, direction).item
    return item.kind if len(item.raw) == len(raw) else ItemKind.UNFRAMED


class MiddleView:
    """Feeds the analyzer and the store for a recording made in the middle."""

    def __init__(self, analyze: Callable[[TrafficEvent], list[Event]], store: FrameStore, redact: bool) -> None:
        self.analyze = analyze
        self.store = store
        self.redact = redact
        self.pending: dict[int, list[Mark]] = {}

    def receive(self, event: TrafficEvent) -> None:
        kind = type(event)
        if kind is Data:
            if event.direction is S2C:  # what the client sent is told by the delivered bytes and the marks
                self._add(event.conn, self.analyze(event))
        elif kind is Delivered:
            if event.direction is C2S:  # what the client got differs from what the server sent by the marks
                data = b"*" * len(event.data) if event.secret and self.redact else event.data
                self._add(event.conn, self.analyze(Data(event.conn, C2S, event.t_ns, data)))
        elif kind is Intervention:
            self._intervention(event)  # type: ignore[arg-type]
        else:
            self._add(event.conn, self.analyze(event))

    def _add(self, conn: int, events: list[Event]) -> None:
        store = self.store
        first = store.count
        store.add(conn, events)
        pending = self.pending.get(conn)
        if pending:
            for n in range(first, store.count):
                if store.direction(n) is C2S:
                    self._attach(n, pending)

    def _attach(self, n: int, pending: list[Mark]) -> None:
        """A request the server received: the waiting marks that made it."""
        raw = self.store.raw(n)
        mine: list[Mark] = []
        causes: set[str] = set()
        for m in pending:  # one mark per cause: the oldest, as frames with the same bytes go out in order
            if m.action != "hold" and m.cause not in causes and \
                    (m.after == raw or (m.action == "dup" and m.before == raw)):
                mine.append(m)
                causes.add(m.cause)
        # a hold goes with the frame its release (or edit) went out as, by its number: held frames
        # with the same bytes are let go in any order
        held = {m.cause[m.cause.index(_HELD):] for m in mine if _HELD in m.cause}
        mine += [m for m in pending if m.action == "hold" and f"(held #{m.detail.rsplit('#', 1)[-1]})" in held]
        mine.sort(key=lambda m: m.t_ns)
        for mark in mine:
            self.store.mark(n, mark)
            pending.remove(mark)

    def _unanswered_for_the_client(self, n: int, mark: Mark) -> None:
        """An answer the proxy dropped: its request was answered as the server
        sees it, never as the client does (reported on the client's side only,
        as ``whiztap analyze`` does)."""
        request = self.store.pair[n]
        if mark.kind == "dropped" and 0 <= request < n:
            self.store.add_violation(request, Violation(
                "PW-PAIR-UNANSWERED", f"client side: the answer never reached the client ({mark.cause})"))

    def _intervention(self, event: Intervention) -> None:
        mark, store, conn = Mark.of(event), self.store, event.conn
        if not event.before and not event.after:  # the connection's end on a timer: its last frame shows it
            last = next(iter(store.last_frames(conn, S2C)), None) or next(iter(store.last_frames(conn, C2S)), None)
            if last is not None:
                store.mark(last, mark)
        elif event.direction is S2C:
            if not event.before:  # injected toward the client: the server never sent it
                store.add_unseen(conn, S2C, kind_of(event.after, S2C), event.after, event.t_ns, mark)
                return
            for n in store.last_frames(conn, S2C):
                if event.before.startswith(store.raw(n)):  # (a large item's row keeps its head)
                    store.mark(n, mark)
                    self._unanswered_for_the_client(n, mark)
                    return
        elif not event.after and event.action in ("drop", "blackhole"):  # the server never got it
            raw = b"*" * len(event.before) if self.redact and event.kind == ItemKind.PASSWORD.value else event.before
            store.add_unseen(conn, C2S, kind_of(event.before, C2S), raw, event.t_ns, mark)
        else:
            pending = self.pending.setdefault(conn, [])
            pending.append(mark)
            del pending[:-PENDING_MAX]
