"""The TUI's model of a connection the proxy stands in the middle of.

In the middle, what the client sent is not what the server got.  The list
shows the conversation as the server had it (the bytes delivered to it, and
what it sent: so an injected request pairs with its answer, and an edited
frame shows what the server will make of it), plus what the proxy did: each
frame carries its interventions (the ``Intervention`` events themselves, see
``marks.py``); a frame the client sent that the server never got (dropped) and
one the proxy sent to the client on its own (injected) are rows no session saw.

An intervention finds its row by the facts it carries, never by bytes:

- toward the client (s2c) the rows are what the server sent, so a mark goes
  to the row that begins at its ``offset`` in the server's stream (by its
  ``index`` among the server's frames when it has no offset: a frame that
  expired);
- toward the server (c2s) the rows are what the server received, so a mark
  goes to the row that begins at its ``delivered`` offset in that stream (an
  intervention on a delivered frame is told before the bytes that carry it,
  so it waits for its row); every copy of a duplicated frame gets the mark;
- a hold (told when the frame is held, before anyone knows where it will go)
  goes with its release, edit or drop, by the ``held`` id;
- a c2s frame that was never delivered (dropped, blackholed, expired, or
  taken away by a reset or close of its connection), and
  an injection that never was (either way), is a row of its own, with the
  marks told on it before (by its ``index``);
- what is about the connection (a reset or close on a timer) shows on its
  last frame.

Each row's offset is counted here: the rows of one direction of a connection
are the framer's items of one stream, in order, so a row begins where the one
before it ended.

A row's time is the server's (when it received a request, when it sent an
answer).  Where the proxy changed a frame's timing (a delay, a hold, a slice,
a bandwidth limit) the client's time differs, and the store keeps it
(``client_t``): a request's is when the client sent it (the time the proxy
noted it at, on arrival), an answer's when the client got it (the time of the
delivery that carried its ``delivered`` offset).  The detail pane shows both
latencies from them.
"""

from __future__ import annotations

from bisect import bisect_right, insort
from collections.abc import Callable
from itertools import count

from whiztap.analyzer.protocol.frame_text import frame_alone
from whiztap.analyzer.protocol.items import ItemKind
from whiztap.analyzer.protocol.observations import Direction, Event
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.traffic import (
    Action,
    Continued,
    Data,
    Delivered,
    Gap,
    Intervention,
    TrafficEvent,
)
from whiztap.tui.data.marks import TIMING
from whiztap.tui.data.store import FrameStore

C2S, S2C = Direction.C2S, Direction.S2C
RECENT = 1024  # rows of one direction of a connection whose offsets are kept: marks find their row among them
PENDING_MAX = 256  # marks of one direction of a connection waiting for their row; the oldest go past this
NOT_DELIVERED = frozenset({Action.DROP, Action.BLACKHOLE, Action.EXPIRE})
DROPPED_ANSWER = frozenset({Action.DROP, Action.BLACKHOLE})  # the client never got it, and was there to


def kind_of(raw: bytes, direction: Direction) -> ItemKind:
    """The kind of bytes dropped or injected on their own, framed as the proxy
    frames typed bytes (``frame_alone``); UNFRAMED unless they are one item.
    (Not the Intervention's recorded ``kind``: that is the sender's frame's,
    and an earlier stage may have changed the bytes since.)"""
    observations, _ = frame_alone(raw, direction)
    return observations[0].item.kind if len(observations) == 1 else ItemKind.UNFRAMED


class _Track:
    """One direction of one connection as its rows show it (what the server
    sent, s2c; what it received, c2s): where the next row begins in that
    stream, where the recent rows begin, and the marks told before their row."""

    __slots__ = ("offset", "items", "starts", "rows", "first", "waiting")

    def __init__(self) -> None:
        self.offset = 0  # where the next row begins
        self.items = 0  # rows so far (the framer's items of the stream)
        self.starts: list[int] = []  # recent rows: where each begins, and its id
        self.rows: list[int] = []
        self.first = 0  # the item number of starts[0]
        self.waiting: list[tuple[int, int, Intervention]] = []  # (offset, order, mark), by offset

    def added(self, n: int, size: int) -> int:
        """Row ``n`` of ``size`` bytes is the next item; where it begins."""
        start = self.offset
        self.offset = start + size
        self.items += 1
        self.starts.append(start)
        self.rows.append(n)
        if len(self.rows) > 2 * RECENT:
            del self.starts[:RECENT], self.rows[:RECENT]
            self.first += RECENT
        return start

    def row_at(self, offset: int) -> int | None:
        """The recent row holding the stream's byte ``offset`` (None: not stored yet, or long gone)."""
        if offset >= self.offset:
            return None
        at = bisect_right(self.starts, offset) - 1
        return self.rows[at] if at >= 0 else None

    def row_numbered(self, index: int) -> int | None:
        at = index - self.first
        return self.rows[at] if 0 <= at < len(self.rows) else None


class MiddleView:
    """Feeds the analyzer and the store for a recording made in the middle."""

    def __init__(self, analyze: Callable[[TrafficEvent], list[Event]], store: FrameStore, redact: bool) -> None:
        self.analyze = analyze
        self.store = store
        self.redact = redact
        self.tracks: dict[tuple[int, Direction], _Track] = {}
        self.holds: dict[int, Intervention] = {}  # c2s holds by held id, until let go
        # (conn, direction, index) -> marks told on a frame not delivered, before what decided that
        self.undelivered: dict[tuple[int, Direction, int], list[Intervention]] = {}
        self._dups: dict[tuple[int, int], int] = {}  # (conn, request index) -> copies marked so far
        self.unseen: dict[tuple[int, Direction], tuple[int, int]] = {}  # (index, row) of the last frame never delivered
        self.to_client: dict[int, int] = {}  # conn -> bytes delivered to its client so far
        self.arriving: dict[int, list[tuple[int, int]]] = {}  # conn -> (delivered offset, row): when did it arrive?
        self._order = count()

    def receive(self, event: TrafficEvent) -> None:
        if type(event) is Data:
            if event.direction is S2C:  # what the client sent is told by the delivered bytes and the marks
                self._add(event.conn, self.analyze(event))
        elif type(event) is Delivered:
            if event.direction is C2S:  # what the client got differs from what the server sent by the marks
                data = b"*" * len(event.data) if event.secret and self.redact else event.data
                self._add(event.conn, self.analyze(Data(event.conn, C2S, event.t_ns, data)))
            else:
                self._to_client(event)
        elif type(event) is Intervention:
            self._intervention(event)
        else:
            if type(event) is Continued:  # a later part of a split recording: the server's stream goes on from here
                self._track(event.conn, S2C).offset = event.s2c_offset
            elif type(event) is Gap and event.direction is S2C and event.length:
                track = self._track(event.conn, S2C)
                track.offset = (event.offset if event.offset is not None else track.offset) + event.length
            self._add(event.conn, self.analyze(event))

    def _track(self, conn: int, direction: Direction) -> _Track:
        track = self.tracks.get((conn, direction))
        if track is None:
            track = self.tracks[conn, direction] = _Track()
        return track

    def _add(self, conn: int, events: list[Event]) -> None:
        store = self.store
        first = store.count
        store.add(conn, events)
        for n in range(first, store.count):
            track = self._track(conn, store.direction(n))
            size = store.size(n)
            start = track.added(n, size)
            waiting = track.waiting
            while waiting and waiting[0][0] < start + size:
                self._attach(n, waiting.pop(0)[2])

    # -- interventions -----------------------------------------------------------------------------

    def _intervention(self, e: Intervention) -> None:
        if e.index < 0 and e.offset < 0 and not e.before and not e.after:
            self._on_the_connection(e)  # a reset or close on a timer: no frame
        elif e.direction is S2C and (e.index >= 0 or e.offset >= 0):
            self._on_what_the_server_sent(e)
        elif e.delivered >= 0:
            if e.direction is C2S:
                self._delivered(e)
            else:  # injected toward the client: the server never sent it
                raw = e.after or e.before
                self.store.add_unseen(e.conn, S2C, kind_of(raw, S2C), raw, e.t_ns, [e])
        elif e.action is Action.HOLD:
            self.holds[e.held] = e
        elif (last := self.unseen.get((e.conn, e.direction))) is not None and e.index >= 0 and last[0] == e.index:
            self._attach(last[1], e)  # more about a frame already shown as never delivered
        elif e.action in NOT_DELIVERED or (e.before and not e.after):  # dropped (by a reset or close too)
            self._never_delivered(e)
        else:  # told on a frame that is not delivered, before what decided that
            self.undelivered.setdefault((e.conn, e.direction, e.index), []).append(e)
            if len(self.undelivered) > PENDING_MAX:
                del self.undelivered[next(iter(self.undelivered))]

    def _on_what_the_server_sent(self, e: Intervention) -> None:
        """A mark on a frame the server sent: the row at its offset in the
        server's stream (by its number when it has no offset)."""
        track = self._track(e.conn, S2C)
        if e.offset >= 0:
            row = track.row_at(e.offset)
            if row is None and e.offset >= track.offset:
                self._wait(track, e.offset, e)
                return
        else:
            row = track.row_numbered(e.index)
        if row is not None:  # (else a row long gone)
            self._attach(row, e)

    def _delivered(self, e: Intervention) -> None:
        """A mark on a frame the server received: the row at its delivered
        offset, each copy's for a duplicate."""
        track = self._track(e.conn, C2S)
        step = len(e.before)
        copies = 1
        if e.action is Action.DUP:  # each dup on a frame is one more copy, right behind the others
            key = (e.conn, e.index)
            copies = self._dups[key] = self._dups.get(key, 1) + 1
            if len(self._dups) > PENDING_MAX:
                del self._dups[next(iter(self._dups))]
        for k in range(copies):
            offset = e.delivered + k * step
            row = track.row_at(offset)
            if row is not None:
                self._attach(row, e)
            elif offset >= track.offset:
                self._wait(track, offset, e)

    def _never_delivered(self, e: Intervention) -> None:
        """A frame its receiver never got (a client's frame, or an injection):
        a row of its own, with what was done to it before."""
        raw = e.before or e.after
        shown = b"*" * len(raw) if self.redact and e.secret else raw
        marks = self.undelivered.pop((e.conn, e.direction, e.index), [])
        hold = self.holds.pop(e.held, None) if e.held else None
        marks = ([hold] if hold is not None else []) + marks + [e]
        n = self.store.add_unseen(e.conn, e.direction, kind_of(raw, e.direction), shown, e.t_ns,
                                  sorted(marks, key=_told))
        if e.index >= 0:
            self.unseen[e.conn, e.direction] = (e.index, n)

    def _on_the_connection(self, e: Intervention) -> None:
        """What is about the connection rather than a frame shows on its last frame."""
        store = self.store
        last = next(iter(store.last_frames(e.conn, S2C)), None) or next(iter(store.last_frames(e.conn, C2S)), None)
        if last is not None:
            self._attach(last, e)

    def _wait(self, track: _Track, offset: int, e: Intervention) -> None:
        insort(track.waiting, (offset, next(self._order), e))
        if len(track.waiting) > PENDING_MAX:
            del track.waiting[0]

    def _attach(self, n: int, e: Intervention) -> None:
        """Row ``n`` gets the mark (and, for a c2s release, edit or drop, the hold it ends)."""
        store = self.store
        if e in store.marks.get(n, ()):
            return  # told twice: one mark
        if e.held and e.direction is C2S and e.action is not Action.HOLD:
            hold = self.holds.pop(e.held, None)
            if hold is not None:
                store.mark(n, hold)
        store.mark(n, e)
        marks = store.marks[n]
        marks.sort(key=_told)
        if e.action in TIMING:
            if e.direction is C2S:  # the client sent it when the proxy first noted it
                store.client_t[n] = min(m.t_ns for m in marks if m.action is not Action.INJECT)
            elif e.delivered >= 0:
                self.arriving.setdefault(e.conn, []).append((e.delivered, n))
        if e.direction is S2C and e.action in DROPPED_ANSWER:
            self._unanswered_for_the_client(n, e)

    def _to_client(self, event: Delivered) -> None:
        """Bytes delivered to the client: the answers whose timing the proxy
        changed and that begin in them arrived now."""
        conn = event.conn
        start = self.to_client.get(conn, 0)
        end = self.to_client[conn] = start + len(event.data)
        arriving = self.arriving.get(conn)
        if arriving:
            for _delivered, n in [a for a in arriving if a[0] < end]:
                self.store.client_t[n] = event.t_ns
            self.arriving[conn] = [a for a in arriving if a[0] >= end][-PENDING_MAX:]

    def _unanswered_for_the_client(self, n: int, e: Intervention) -> None:
        """An answer the proxy dropped: its request was answered as the server
        sees it, never as the client does (reported on the client's side only,
        as ``whiztap analyze`` does)."""
        request = self.store.pair[n]
        if 0 <= request < n:
            self.store.add_violation(request, Violation(
                "PW-PAIR-UNANSWERED", f"client side: the answer never reached the client ({e.cause})"))


def _told(e: Intervention) -> int:
    """Marks in the order things happened to the frame (stable: ties keep the order told)."""
    return e.t_ns
