"""One direction of one connection with the proxy in the middle.

Bytes from the sender are framed (the analyzer's sans-IO framer) and each
frame goes through the stages (faults, scripts, interception) before anything
of it is written; the decision is carried out in order: a frame never
overtakes the one before it, so a delayed or held frame holds back everything
behind it in its direction.  Bytes that no frame owns yet are held until their
item is complete, with two exceptions that keep a session from waiting on
itself: a password (the server's verdict is what ends it, so it cannot wait
for the verdict), bytes that stay incomplete for ``STALL_S`` and an item that
grows past ``HIGH_WATER`` (a camera picture) are passed on as they come,
untouched; the framer's items for them are then only observed.

What is written is told to the consumers as ``Delivered`` events (by the
``Middle``, which decides which client bytes are secret), each change as an
``Intervention``.  The lane holds at most what its sender sent
beyond ``HIGH_WATER`` plus one read: past it the sender is not read
(``Middle.sync``), so a delay fault under a client that keeps sending keeps
memory bounded.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass
from typing import Any

from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.traffic import Intervention
from whiztap.sniffer.mitm.frame import observation_of

HIGH_WATER = 256 << 10
STALL_S = 0.2
NS = 1_000_000_000


@dataclass
class _Out:
    """Something to write, in turn: bytes (in slices, if set) no earlier than
    ``at_ns``, or a connection's end; ``held`` until a person lets it go."""

    data: bytes
    at_ns: int
    slices: tuple[int, int] | None = None
    pause_ns: int = 0
    end: str | None = None
    held: object | None = None  # a Held (intercept.py) while it waits


def _joinable(out: _Out, now: int) -> bool:
    """``out`` can go in the same write as the one before it: due, whole, not
    held, no connection's end."""
    return out.at_ns <= now and out.held is None and out.end is None and (out.slices is None or len(out.data) <= 1)


class Lane:
    def __init__(self, middle: Any, direction: Direction, framer: Framer) -> None:
        self.middle = middle
        self.direction = direction
        self.framer = framer
        self.target: asyncio.Transport | None = None
        self.index = 0  # frames seen in this direction
        self._pending = bytearray()  # fed, not yet in an item
        self._skip = 0  # bytes passed on raw ahead of the items that will cover them
        self._queue: deque[_Out] = deque()
        self._queued = 0
        self._last_at = 0
        self._timer: asyncio.TimerHandle | None = None
        self._stall: asyncio.TimerHandle | None = None
        self._eof = False  # pass a FIN on once the queue is empty
        self.eof_passed = False

    @property
    def queued(self) -> int:
        """Bytes waiting here (pending and queued): flow control's measure."""
        return self._queued + len(self._pending)

    # -- input ------------------------------------------------------------------------------

    def feed(self, data: bytes, t_ns: int) -> None:
        if self.framer._password_mode:  # noqa: SLF001 - the framer's own flag: a password cannot wait
            self._pass_raw(bytes(self._pending) + data, t_ns)
            self._consume(self.framer.feed(data, t_ns), t_ns)
        else:
            self._pending += data
            self._consume(self.framer.feed(data, t_ns), t_ns)
            if len(self._pending) >= HIGH_WATER:  # a large item (a picture): it flows on as it comes
                self._pass_raw(bytes(self._pending), t_ns)
            self._watch_stall()
        self.pump()

    def end(self, t_ns: int) -> None:
        """The sender sent its FIN: everything pending becomes items; the FIN follows them."""
        if self.direction is Direction.S2C:
            self.middle.server_ended()
        self._consume(self.framer.end(t_ns), t_ns)
        if self._pending:
            self._pass_raw(bytes(self._pending), t_ns)
        self._eof = True
        self.pump()

    def inject(self, data: bytes, cause: str, t_ns: int, action: str = "inject") -> None:
        """Write ``data`` to the receiver after what is already queued."""
        self.middle.emit(Intervention(self.middle.conn_id, t_ns, self.direction, action, cause, b"", data, "", ""))
        self._append(_Out(data, max(self._last_at, t_ns)))
        self.pump()

    def password_closed(self, t_ns: int) -> None:
        """The server judged a password: the framer hands over its item now."""
        self._consume(self.framer.close_password(t_ns), t_ns)

    # -- deciding ------------------------------------------------------------------------------

    def _consume(self, items: list[Item], t_ns: int) -> None:
        """Decide each item, in order; the pending bytes they took go at the end
        (once per read: a read of thousands of frames stays linear)."""
        used = 0
        for item in items:
            n = len(item.raw)
            if self._skip:
                taken = min(self._skip, n)
                self._skip -= taken
                self._observe(item)
                if taken < n:  # the rest of an item begun raw: it passes as it is
                    used += n - taken
                    self._append(_Out(item.raw[taken:], max(self._last_at, t_ns)))
                continue
            used += n
            self._decide(item, t_ns)
        if used:
            del self._pending[:used]

    def _observe(self, item: Item) -> Observation:
        observation = observation_of(item, self.direction, self.index)
        self.index += 1
        self.middle.saw(self, item)
        return observation

    def _decide(self, item: Item, t_ns: int) -> None:
        observation = self._observe(item)
        middle = self.middle
        frame = middle.new_frame(self, item, observation, t_ns)
        if item.kind is not ItemKind.PASSWORD:
            middle.stages.frame(frame)
        for intervention in frame.interventions:
            middle.emit(intervention)
        at = max(self._last_at, t_ns + frame.delay_ns)
        if frame.data is not None:
            for _ in range(frame.copies):
                out = _Out(frame.data, at, frame.slices, frame.pause_ns)
                middle.hold(self, out, frame)
                self._append(out)
        for direction, data, cause in frame.injections:
            middle.inject(direction, data, cause)
        if frame.end is not None:  # after what comes before it, and the frame if it is delivered
            self._append(_Out(b"", at, end=frame.end))

    def _append(self, out: _Out) -> None:
        self._queue.append(out)
        self._queued += len(out.data)
        self._last_at = max(self._last_at, out.at_ns)

    def _pass_raw(self, data: bytes, t_ns: int) -> None:
        """Bytes no item owns yet, on their way untouched (see the module docstring)."""
        self._pending.clear()
        if data:
            self._skip += len(data)
            self._append(_Out(data, max(self._last_at, t_ns)))

    def _watch_stall(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None
        if self._pending:
            self._stall = asyncio.get_running_loop().call_later(STALL_S, self._stalled)

    def _stalled(self) -> None:
        self._stall = None
        if self._pending:
            self._pass_raw(bytes(self._pending), self.middle.clock())
            self.pump()

    # -- writing --------------------------------------------------------------------------------

    def pump(self) -> None:
        """Write what is due, in order; come back when the next thing is."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        queue, middle = self._queue, self.middle
        while queue and self.target is not None and not middle.gone:
            out = queue[0]
            if out.held is not None:
                return  # its release pumps again
            now = middle.clock()
            if out.at_ns > now:
                self._timer = asyncio.get_running_loop().call_later((out.at_ns - now) / NS, self.pump)
                return
            if out.end is not None:
                queue.popleft()
                middle.end(out.end)
                return
            data = out.data
            if out.slices is not None and len(data) > 1:
                low, high = out.slices
                size = middle.rng.randint(low, high) if high > low else low
                chunk, out.data = data[:size], data[size:]
                if out.data:
                    out.at_ns = now + out.pause_ns
                else:
                    queue.popleft()
            else:
                queue.popleft()
                chunk = data
                if queue and _joinable(queue[0], now):  # one write for a run of due frames
                    parts = [data]
                    while queue and _joinable(queue[0], now):
                        parts.append(queue.popleft().data)
                    chunk = b"".join(parts)
            self._queued -= len(chunk)
            if chunk:  # a frame replaced by nothing is no delivery
                self._write(chunk, now)
        if not queue and self._eof and self.target is not None and not middle.gone:
            self._eof = False
            self.eof_passed = True
            middle.pass_eof(self)
        middle.sync()

    def _write(self, chunk: bytes, now: int) -> None:
        self.target.write(chunk)  # type: ignore[union-attr]
        self.middle.delivered(self.direction, chunk, now)

    def flush(self) -> None:
        """The connection is ending: write everything queued now (held frames as they are)."""
        for out in self._queue:
            out.held = None
            out.at_ns = 0
            out.slices = None
        self._queue = deque(o for o in self._queue if o.end is None)
        self.pump()

    def let_go(self, out: _Out, data: bytes) -> None:
        """A held frame may go, as ``data`` (empty: dropped); flow control
        counts what it holds now."""
        self._queued += len(data) - len(out.data)
        out.data = data
        out.held = None
        self.pump()

    def stop_timers(self) -> None:
        for timer in (self._timer, self._stall):
            if timer is not None:
                timer.cancel()
        self._timer = self._stall = None
