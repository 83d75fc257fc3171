"""One direction of one connection with the proxy in the middle, sans-IO.

Bytes from the sender are framed (the analyzer's framer) and each frame goes
through the stages (faults, scripts, interception) before anything of it is
written; the decision is carried out in order: a frame never overtakes the one
before it, so a delayed or held frame holds back everything behind it in its
direction.  Bytes that no frame owns yet wait until their item is complete,
with three exceptions that keep a session from waiting on itself: a password
(the server's verdict may be what ends it), bytes that stay incomplete for
``STALL_NS`` and an item that grows past ``HIGH_WATER`` (a camera picture)
pass on as they come, untouched; the framer's items for them are then only
observed.

Memory is bounded after the faults act, not before: frames are decided only
while what the lane has queued for delivery (after replace, dup and
injection) is at most ``HIGH_WATER``; the rest wait as the sender sent them,
and ``may_read`` tells the shell to stop reading the sender.  The queue
drains only as fast as the receiver takes it: a lane writes at most
``WRITE_BURST`` bytes until the shell says the receiver takes more
(``writable``: its transport's buffer is under its mark), so what a fault
makes of a read never piles up in the transport either.  One decision
adds at most one frame's worth times its copies, both bounded
(``MAX_REPLACEMENT``, ``MAX_DUP_FAULTS``).  An injection that would make the
queue longer than ``INJECT_ROOM`` is refused (``Full``).

The lane never looks at a clock: every call brings the time, and
``deadline`` says when it next has something to do.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

from whiztap.analyzer.mitm.commands import Full
from whiztap.analyzer.protocol.framing import Framer, Item
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action, Cause, Intervention

if TYPE_CHECKING:
    from whiztap.analyzer.mitm.frame import Frame
    from whiztap.analyzer.mitm.intercept import Held

HIGH_WATER = 256 << 10
WRITE_BURST = 256 << 10  # bytes a lane writes before its receiver must say it takes more (``writable``)
INJECT_ROOM = 1 << 20
STALL_NS = 200_000_000
Notes = tuple[Intervention, ...]
Segments = Sequence[tuple[int, int, int, bool]]  # in a write: (at, length, the sender's offset or -1, secret)


class LaneOwner(Protocol):
    """What a lane asks of its connection's core (``core.py``)."""

    gone: bool

    def saw(self, direction: Direction, item: Item, t_ns: int) -> None: ...
    def secret(self, direction: Direction, offset: int, length: int) -> bool: ...
    def idle(self) -> bool: ...
    def tell(self, event: Intervention) -> None: ...
    def decide(self, lane: Lane, item: Item, index: int, offset: int, t_ns: int) -> Frame: ...
    def hold(self, lane: Lane, frame: Frame, out: Out, t_ns: int) -> Held: ...
    def inject_from_stage(self, direction: Direction, data: bytes, cause: Cause, t_ns: int) -> None: ...
    def deliver(self, direction: Direction, data: bytes, t_ns: int, notes: list[tuple[int, Notes]],
                segments: Segments = ...) -> None: ...
    def end(self, how: Action, t_ns: int) -> None: ...
    def pass_eof(self, direction: Direction) -> None: ...
    def expired(self, direction: Direction, out: Out, t_ns: int) -> None: ...
    def slice_size(self, low: int, high: int) -> int: ...


@dataclass(slots=True)
class Out:
    """Something to write, in turn: bytes (in slices, if set) no earlier than
    ``at_ns``, or a connection's end; ``held`` until a person lets it go.
    ``index``/``offset``/``kind``/``secret``: the frame it comes from (-1: an
    injection or bytes passed on raw); ``source``: where ``data`` begins in the
    sender's stream when it is the sender's own bytes, unchanged (-1: an
    injection, an edit); ``notes``: the interventions on it, told when it is
    delivered (then it is known where it went)."""

    data: bytes
    at_ns: int
    slices: tuple[int, int] | None = None
    pause_ns: int = 0
    end: Action | None = None
    held: Held | None = None
    index: int = -1
    offset: int = -1
    kind: str = ""
    secret: bool = False
    notes: Notes = ()
    source: int = -1


class _Entry(NamedTuple):
    """Framed (or passed raw: ``item`` None), not yet decided."""

    item: Item | None
    raw: bytes
    number: int  # the frame's index in its direction (-1: bytes no frame holds)
    offset: int
    t_ns: int


def _joinable(out: Out, now: int) -> bool:
    """``out`` can go in the same write as the one before it: due, whole, not
    held, no connection's end."""
    return out.at_ns <= now and out.held is None and out.end is None and (out.slices is None or len(out.data) <= 1)


class Lane:
    def __init__(self, owner: LaneOwner, direction: Direction, framer: Framer) -> None:
        self.owner = owner
        self.direction = direction
        self.framer = framer
        self.ready = False  # the receiver is there to write to
        self.index = 0  # frames framed in this direction
        self.offset = 0  # sender's stream offset of the next item
        self.eof_passed = False
        self._pending = bytearray()  # fed, not yet in an item
        self._pending_since: int | None = None
        self._skip = 0  # bytes passed on raw ahead of the items that will cover them
        self._entries: deque[_Entry] = deque()
        self._entry_bytes = 0
        self._queue: deque[Out] = deque()
        self._queued = 0
        self._last_at = 0
        self._eof = False  # pass a FIN on once everything is delivered
        self.credit = WRITE_BURST  # bytes it may still write before the receiver says it takes more

    @property
    def queued(self) -> int:
        """Bytes waiting here, decided or not: what the memory tests bound."""
        return self._queued + self._entry_bytes + len(self._pending)

    @property
    def busy(self) -> bool:
        """Something waits here (to be framed, decided or written)."""
        return bool(self._queue or self._entries or self._pending or (self._eof and not self.eof_passed))

    @property
    def blocked(self) -> bool:
        """It wrote its burst: nothing more goes until the receiver takes more (``writable``)."""
        return self.credit <= 0

    def writable(self, now: int) -> None:
        """The receiver takes more (its transport's buffer is under its mark)."""
        self.credit = WRITE_BURST
        self.pump(now)

    def may_read(self) -> bool:
        """Whether the shell may read the sender: flow control's rule (``queued`` spelled out: once per read)."""
        return self._queued + self._entry_bytes + len(self._pending) <= HIGH_WATER

    def deadline(self) -> int | None:
        """When this lane next has something to do on its own (None: only on an event)."""
        times = []
        if self._pending and self._pending_since is not None:
            times.append(self._pending_since + STALL_NS)
        if self._queue and self.ready and self.credit > 0:
            head = self._queue[0]
            if head.held is None:
                times.append(head.at_ns)
        return min(times) if times else None

    # -- input ------------------------------------------------------------------------------

    def feed(self, data: bytes, t_ns: int) -> None:
        framer = self.framer
        if framer.password_pending:  # a password cannot wait for its end
            self._raw(bytes(self._pending) + data, t_ns)
            self._frame(framer.feed(data, t_ns), t_ns)
        else:
            items = framer.feed(data, t_ns)
            if (not framer.buffered and not self._pending and not self._queue and not self._entries and self.ready
                    and not self._skip and not self._eof and self.credit > 0 and self.owner.idle()):
                self._pass(items, data, t_ns)  # whole frames, nothing before them, no stage to ask: now, as they are
                return
            self._pending += data
            self._frame(items, t_ns)
            if len(self._pending) >= HIGH_WATER:  # a large item (a picture): it flows on as it comes
                self._raw(bytes(self._pending), t_ns)
        self._pending_since = t_ns if self._pending else None
        self.pump(t_ns)

    def _pass(self, items: list[Item], data: bytes, t_ns: int) -> None:
        """The fast way of a read that is whole frames through an idle middle
        (what ``_frame``, ``_advance`` and ``pump`` would do with it, at once)."""
        owner = self.owner
        for item in items:
            owner.saw(self.direction, item, t_ns)
        self.index += len(items)
        self.offset += len(data)
        if not owner.gone:
            self.credit -= len(data)
            owner.deliver(self.direction, data, t_ns, [], [(0, len(data), self.offset - len(data), False)])

    def end(self, t_ns: int) -> None:
        """The sender sent its FIN: everything pending becomes items; the FIN follows them."""
        self._frame(self.framer.end(t_ns), t_ns)
        if self._pending:
            self._raw(bytes(self._pending), t_ns)
        self._pending_since = None
        self._eof = True
        self.pump(t_ns)

    def password_closed(self, t_ns: int) -> None:
        """The server judged a password: the framer hands over its item now."""
        self._frame(self.framer.close_password(t_ns), t_ns)
        self.pump(t_ns)

    def inject(self, data: bytes, t_ns: int, note: Intervention) -> None:
        """Write ``data`` to the receiver after what is already decided (Full past ``INJECT_ROOM``)."""
        if self.queued + len(data) > INJECT_ROOM:
            raise Full(f"{self.queued:,} bytes already wait to go {self.direction} on this connection "
                       f"(the receiver is not reading); try again once they are delivered")
        self._append(Out(data, max(self._last_at, t_ns), notes=(note,)))

    def wake(self, t_ns: int) -> None:
        if self._pending and self._pending_since is not None and t_ns >= self._pending_since + STALL_NS:
            self._raw(bytes(self._pending), t_ns)
            self._pending_since = None
        self.pump(t_ns)

    # -- framing and deciding -------------------------------------------------------------------

    def _frame(self, items: list[Item], t_ns: int) -> None:
        """Queue each item for its decision, in order; the pending bytes they
        took go at the end (once per read: a read of thousands of frames stays
        linear).  While no stage can act (``owner.idle``), a read's items need
        no decision and go on as one run of bytes."""
        if not items:
            return
        owner = self.owner
        if owner.idle() and not self._skip:
            run = b"".join([item.raw for item in items])
            start = self.index
            for item in items:
                owner.saw(self.direction, item, t_ns)
            self.index += len(items)
            self.offset += len(run)
            self._enter(_Entry(None, run, start, self.offset - len(run), t_ns))
            del self._pending[:len(run)]
            return
        used = 0
        for item in items:
            n = len(item.raw)
            index, offset = self.index, self.offset
            self.index += 1
            self.offset += n
            owner.saw(self.direction, item, t_ns)
            if self._skip:
                taken = min(self._skip, n)
                self._skip -= taken
                if taken < n:  # the rest of an item begun raw: it passes as it is
                    used += n - taken
                    self._enter(_Entry(None, item.raw[taken:], index, offset + taken, t_ns))
                continue
            used += n
            self._enter(_Entry(item, item.raw, index, offset, t_ns))
        if used:
            del self._pending[:used]

    def _raw(self, data: bytes, t_ns: int) -> None:
        """Bytes no item owns yet, on their way untouched (see the module docstring)."""
        self._pending.clear()
        if data:
            offset = self.offset + self._skip  # where they begin in the sender's stream: after the items and skips
            self._skip += len(data)
            self._enter(_Entry(None, data, -1, offset, t_ns))

    def _enter(self, entry: _Entry) -> None:
        self._entries.append(entry)
        self._entry_bytes += len(entry.raw)

    def _advance(self) -> None:
        """Decide waiting frames while there is room for what they become."""
        entries = self._entries
        while entries and self._queued <= HIGH_WATER:
            entry = entries.popleft()
            self._entry_bytes -= len(entry.raw)
            if entry.item is None:  # secret: judged as a frame is, should it never be delivered (expire)
                self._append(Out(entry.raw, max(self._last_at, entry.t_ns),
                                 secret=self.owner.secret(self.direction, entry.offset, len(entry.raw)),
                                 source=entry.offset))
            else:
                self._decide(entry, entry.item)

    def _decide(self, entry: _Entry, item: Item) -> None:
        owner = self.owner
        t_ns = entry.t_ns
        frame = owner.decide(self, item, entry.number, entry.offset, t_ns)
        at = max(self._last_at, t_ns + frame.delay_ns)
        kind = frame.kind.value
        notes = tuple(frame.interventions)
        if frame.data is None:
            for note in notes:  # nothing of it is delivered: told now
                owner.tell(note)
            notes = ()
        else:
            for _ in range(frame.copies):
                out = Out(frame.data, at, frame.slices, frame.pause_ns, index=frame.index, offset=frame.offset,
                          kind=kind, secret=frame.secret, notes=notes,
                          source=frame.offset if frame.data == frame.raw else -1)
                notes = ()  # the first copy tells them
                if frame.hold is not None:
                    out.held = owner.hold(self, frame, out, t_ns)
                self._append(out)
        for direction, data, cause in frame.injections:
            owner.inject_from_stage(direction, data, cause, t_ns)
        if frame.end is not None:  # after what comes before it, and the frame if it is delivered
            self._append(Out(b"", at, end=frame.end, index=frame.index, kind=kind, notes=notes))

    def _append(self, out: Out) -> None:
        self._queue.append(out)
        self._queued += len(out.data)
        self._last_at = max(self._last_at, out.at_ns)

    # -- writing --------------------------------------------------------------------------------

    def pump(self, now: int) -> None:
        """Decide what there is room for and write what is due, in order."""
        while True:
            self._advance()
            if not self._write_due(now) or not self._entries:
                break
        if (self._eof and not self._queue and not self._entries and not self._pending and self.ready
                and not self.owner.gone and not self.eof_passed):
            self.eof_passed = True
            self.owner.pass_eof(self.direction)

    def _write_due(self, now: int) -> bool:
        """Write what is due; whether anything left the queue."""
        queue, owner = self._queue, self.owner
        wrote = False
        notes: list[tuple[int, Notes]] = []
        segments: list[tuple[int, int, int, bool]] = []
        while queue and self.ready and not owner.gone and self.credit > 0:
            out = queue[0]
            if out.held is not None or out.at_ns > now:
                break  # a release, or the deadline, pumps again
            if out.end is not None:
                queue.popleft()
                for note in out.notes:
                    owner.tell(note)
                owner.end(out.end, now)
                return True
            if out.notes:
                notes.append((0, out.notes))
                out.notes = ()
            data = out.data
            if out.slices is not None and len(data) > 1:
                low, high = out.slices
                size = owner.slice_size(low, high)
                chunk, out.data = data[:size], data[size:]
                segments.append((0, len(chunk), out.source, out.secret))
                if out.source >= 0:
                    out.source += len(chunk)
                if out.data:
                    out.at_ns = now + out.pause_ns
                else:
                    queue.popleft()
            else:
                queue.popleft()
                chunk = data
                segments.append((0, len(data), out.source, out.secret))
                if queue and _joinable(queue[0], now):  # one write for a run of due frames
                    parts = [data]
                    at = len(data)
                    while queue and _joinable(queue[0], now):
                        out = queue.popleft()
                        if out.notes:
                            notes.append((at, out.notes))
                        segments.append((at, len(out.data), out.source, out.secret))
                        parts.append(out.data)
                        at += len(out.data)
                    chunk = b"".join(parts)
            self._queued -= len(chunk)
            self.credit -= len(chunk)
            wrote = True
            if chunk or notes:  # a frame replaced by nothing is no delivery, but what was done to it is told
                owner.deliver(self.direction, chunk, now, notes, segments)
                notes = []
            segments = []
        return wrote

    # -- holds and the end ------------------------------------------------------------------------

    def let_go(self, out: Out, data: bytes, notes: Notes, now: int) -> None:
        """A held frame may go, as ``data`` (empty: dropped), ``notes`` told once it is delivered."""
        self._queued += len(data) - len(out.data)
        if data != out.data:
            out.source = -1  # edited: the bytes are the person's, not the sender's
        out.data = data
        out.held = None
        out.notes += notes
        self.pump(now)

    def flush(self, now: int) -> None:
        """The connection is ending: what is decided goes now, held frames as
        they are (the core records their release); frames not yet decided pass
        as the sender sent them (deciding them now could take more memory
        than a lane may hold)."""
        while self._entries:
            entry = self._entries.popleft()
            self._append(Out(entry.raw, 0, index=entry.number, kind=entry.item.kind.value if entry.item is not None
                             else "", source=entry.offset))
        self._entry_bytes = 0
        if self._pending:
            self._append(Out(bytes(self._pending), 0, source=self.offset + self._skip))
            self._pending.clear()
        for out in self._queue:
            out.held = None
            out.at_ns = 0
            out.slices = None
        self._queue = deque(o for o in self._queue if o.end is None)
        self.pump(now)

    def drop_all(self, now: int) -> None:
        """The receiver is gone: nothing here can be delivered.  A frame the
        middle was holding back (held, or due later) is recorded as expired;
        bytes that were simply not written yet go as a plain proxy's would."""
        owner = self.owner
        for out in self._queue:
            if out.end is None and (out.held is not None or out.at_ns > now):
                owner.expired(self.direction, out, now)
        self._queue.clear()
        self._entries.clear()
        self._queued = self._entry_bytes = 0
        self._pending.clear()
        self._pending_since = None
