"""Which client bytes may hold the Winsock password, decided from the bytes alone.

The rule (docs/recording-format.md, *Passwords*), per connection:

* The password can only be the client's first line: from the start of its
  stream (line breaks aside) to its first line break, or to the header
  (``rr1-``, ``cr1-``, ``sr1-``) of a frame that completes (a header whose
  frame never completes is part of the line).  A first line that begins with
  a frame header, or that is longer than ``MAX_PASSWORD`` bytes, is no
  password.  Nothing after the first line is ever masked.
* It is masked if the server begins (line breaks aside) with ``sendchkpass``;
  if the server begins with anything else, nothing is masked.  A verdict
  (``readytogo``, ``Failed Validation``) that comes before the line has ended
  masks what came of it at once: the server judged that much as the password
  (the session hands it over as one there).  The rest of the line follows the
  rule.
* A server that ends (or is never reached, or loses bytes to a gap) before it
  has said which may have asked: the first line is masked.

Masking replaces each byte by ``*`` except CR and LF; lengths never change.
The decisions depend on the two byte streams and the order in which reads
arrived, never on how the bytes were cut into reads (the line is found by the
session's own ``Framer``, whose items do not depend on it).  What only a clock
or a bound decides (held too long, too many undecided bytes, the connection
closed undecided) is to mask, never to show, and it can only ever reach the
bytes of the first line.

Sans-IO: ``LoginMask`` is one connection's decision; ``Redactor`` keeps the
traffic of every connection in arrival order and lets it out as it is decided.
The recorder writes what it lets out, and the live TUI shows it, so both show
the same bytes.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterator
from enum import Enum
from typing import TYPE_CHECKING, Generic, NamedTuple, TypeVar

from whiztap.analyzer.protocol.framing import MAX_PASSWORD, Framer, ItemKind
from whiztap.analyzer.protocol.handshake import SENDCHKPASS, VERDICTS
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import MASK_BYTE
from whiztap.analyzer.traffic import Closed, Gap, HalfClosed, Opened, TrafficEvent, UpstreamFailed

if TYPE_CHECKING:
    from whiztap.analyzer.recording.notice import Notice

HOLD_LIMIT_S = 2.0  # undecided bytes are masked rather than held longer than this
UNDECIDED_CAP = 16 * 1024  # ... or once a connection has this many
QUEUE_CAP = 8 << 20  # ... or once this much traffic waits behind them
_VERDICT = re.compile(b"|".join(re.escape(verdict) for verdict in VERDICTS))
_VERDICT_CARRY = max(len(verdict) for verdict in VERDICTS) - 1
_MASKABLE = re.compile(rb"[^\r\n]+")
_ALL = 1 << 62  # an offset past any stream's end
_NONE = -1  # the first line is no password
C2S, S2C = Direction.C2S, Direction.S2C
__all__ = ["HOLD_LIMIT_S", "MAX_PASSWORD", "QUEUE_CAP", "UNDECIDED_CAP", "LoginMask", "Phase",
           "Redactor", "Released"]


class Phase(Enum):
    GREETING = "greeting"  # the server has not said whether it asks for a password
    LOGIN = "login"  # it asked (or may have: it ended first), and the first line has not ended yet
    OPEN = "open"  # decided: nothing more is masked


class LoginMask:
    """One connection: which of its client's bytes are masked.

    The masked bytes are always within the client's first line: offsets below
    ``masked_end`` are masked (line breaks aside), from there up to
    ``decided`` they are shown, and from ``decided`` on nothing is known yet."""

    __slots__ = ("phase", "received", "masked_end", "decided", "_server", "_greeted", "_carry", "_line",
                 "_line_at", "_start", "_said", "_end")

    def __init__(self) -> None:
        self.phase = Phase.GREETING
        self.received = 0  # client bytes so far
        self.masked_end = 0
        self.decided = 0
        self._server: bool | None = None  # whether the server asks for a password (None: not said yet)
        self._greeted = 0  # bytes of 'sendchkpass' the server has sent so far
        self._carry = b""  # the server's last bytes, which a verdict may straddle
        self._line: Framer | None = Framer()  # finds the client's first line, as the session does
        self._line.expect_password()
        self._line_at = 0  # client bytes the line's framer has taken as items
        self._start = 0  # where the first line begins (line breaks before it aside)
        self._said: int | None = None  # where the password items so far end (None: none yet)
        self._end: int | None = None  # where it ends if it is a password, _NONE if it is none; None: not known

    @property
    def undecided(self) -> int:
        """Client bytes that may still be masked or shown."""
        if self.phase is Phase.OPEN:
            return 0
        end = self.received if self._end is None else self._end
        return max(end - self.decided, 0)

    # -- input -----------------------------------------------------------------------------

    def client(self, data: bytes) -> None:
        """Bytes from the client, in order."""
        self.received += len(data)
        if self.phase is Phase.OPEN:
            return
        if self._line is not None:
            self._scan_line(self._line.feed(data, 0))
        self._settle()
        if self.undecided > UNDECIDED_CAP:
            self.force()

    def client_gap(self, length: int) -> None:
        """``length`` client bytes were never seen (a capture that missed them):
        what came of the first line is masked, and the hole counts as bytes of it."""
        if self.phase is not Phase.OPEN and self._line is not None:
            self.force()
            self.client(b"\0" * min(length, MAX_PASSWORD + 4))
            self.received += length - min(length, MAX_PASSWORD + 4)
        else:
            self.received += length

    def client_ended(self) -> None:
        """The client will send nothing more: its first line ends here if it has not."""
        if self._line is not None and self.phase is not Phase.OPEN:
            self._scan_line(self._line.end(0))
            self._settle()

    def server(self, data: bytes) -> None:
        """Bytes from the server, in order."""
        if self.phase is Phase.OPEN:
            return
        if self._server is None:
            data = self._greeting(data)
        if self._server and self._line is not None and data:
            self._verdict(self._line, data)
        self._settle()

    def server_gap(self) -> None:
        """Server bytes were never seen: the greeting may be among them."""
        self._carry = b""  # a verdict may not straddle the hole
        if self._server is None:
            self._server = True
            self._settle()

    def server_ended(self) -> None:
        """The server will send nothing more (it shut down, or was never reached)."""
        self.server_gap()  # it may have asked: the first line is masked

    def end(self) -> None:
        """The connection is over: decide, as if both sides ended, and mask what is left."""
        self.client_ended()
        self.server_ended()
        self.force()

    def force(self) -> None:
        """Mask what is undecided now (held too long, too much of it, or the end)."""
        if self.phase is Phase.OPEN or not self.undecided:
            return
        self.masked_end = max(self.masked_end, self.received if self._end is None else self._end)
        self.decided = max(self.decided, self.masked_end)
        self._settle()

    # -- output ----------------------------------------------------------------------------

    def apply(self, offset: int, data: bytes) -> tuple[bytes, list[tuple[int, int]]]:
        """A client read at stream ``offset`` as it may be shown, and its masked
        [start, length] spans (CR and LF are never masked)."""
        end = min(len(data), self.masked_end - offset)
        if end <= 0:
            return data, []
        out = bytearray(data)
        spans = []
        for m in _MASKABLE.finditer(data, 0, end):
            start, stop = m.span()
            out[start:stop] = MASK_BYTE * (stop - start)
            spans.append((start, stop - start))
        return bytes(out), spans

    # -- internals ---------------------------------------------------------------------------

    def _greeting(self, data: bytes) -> bytes:
        """Follow 'sendchkpass' in the server's first bytes; what comes after it."""
        if not self._greeted:
            data = data.lstrip(b"\r\n")
        wanted = SENDCHKPASS[self._greeted:]
        n = min(len(wanted), len(data))
        if data[:n] != wanted[:n]:
            self._server = False  # the server spoke first with something else: no login
            return b""
        self._greeted += n
        if self._greeted < len(SENDCHKPASS):
            return b""
        self._server = True
        return data[n:]

    def _verdict(self, line: Framer, data: bytes) -> None:
        """A verdict while the first line is still coming: what came of it is
        the password the server judged, and it is masked now."""
        seen = self._carry + data
        if _VERDICT.search(seen) is None:
            self._carry = seen[-_VERDICT_CARRY:]
            return
        self._carry = b""
        self._scan_line(line.close_password(0), judged=True)

    def _scan_line(self, items: list, judged: bool = False) -> None:
        """The line's framer said something: line breaks before it, the
        password (or, ``judged``, what came of it by the verdict), or none."""
        line = self._line
        for item in items:
            if item.kind is ItemKind.PASSWORD:
                self._line_at += len(item.raw)
                self._said = self._line_at
                if judged:
                    self.masked_end = max(self.masked_end, self._said)
                    self.decided = max(self.decided, self._said)
            elif item.kind is ItemKind.EOL and self._said is None:
                self._line_at += len(item.raw)
                self._start = self._line_at
            else:
                break
        if line is not None and not line.in_password:
            # over: at its end, or it began with a frame header, or ran past MAX_PASSWORD
            self._end = self._said if self._said is not None else _NONE
            self._line = None

    def _settle(self) -> None:
        """What the line and the server have said so far, as the phase and the offsets."""
        end, server = self._end, self._server
        if end == _NONE or server is False or (end is not None and (server or self.masked_end >= end)):
            if end is not None and end != _NONE and server:
                self.masked_end = max(self.masked_end, end)
            self.phase = Phase.OPEN
            self.decided = _ALL
            self._line = None
            return
        if end is not None:
            self.decided = max(self.decided, self._start)  # the line breaks before the password are shown
        self.phase = Phase.LOGIN if server else Phase.GREETING


R = TypeVar("R")


class _Entry(NamedTuple, Generic[R]):
    conn: int
    direction: Direction | None  # None: not a read (a connection event)
    mask: LoginMask | None  # for a client read that may need masking
    offset: int
    data: bytes
    record: R


class Released(NamedTuple, Generic[R]):
    conn: int
    direction: Direction | None  # None: a connection event
    data: bytes  # a read's bytes as they may be shown (b"" for an event)
    spans: list[tuple[int, int]]  # [start, length] of the masked bytes in ``data``
    record: R  # what the caller queued with it


class Redactor(Generic[R]):
    """Every connection's reads and events in arrival order, out again in the
    same order once decided: a client read waits while any of its bytes is
    undecided, and everything after it waits behind it, so whoever takes them
    (the file, the TUI) keeps each stream in order.  ``record`` is the caller's
    own note about each read or event, handed back with it."""

    def __init__(self, hold_s: float = HOLD_LIMIT_S, queue_cap: int = QUEUE_CAP) -> None:
        self.hold_s = hold_s
        self.queue_cap = queue_cap
        self._masks: dict[int, LoginMask] = {}  # connections that may still mask something
        self._queue: deque[_Entry[R]] = deque()
        self._queued = 0  # bytes in the queue
        self._since: dict[int, float] = {}  # connection -> when its oldest undecided byte came

    def passing(self, conn: int) -> bool:
        """Nothing waits and nothing of ``conn`` can be masked: its traffic may skip the queue."""
        return not self._queue and conn not in self._masks

    @property
    def idle(self) -> bool:
        """Nothing waits: a connection event may be taken at once."""
        return not self._queue

    def tell(self, event: TrafficEvent | Notice) -> None:
        """What a connection event means for the decisions (call before queuing
        it with ``event``): a new connection may log in; a server that ended or
        was never reached will give no verdict; a gap; the end."""
        if type(event) is Opened:
            self.opened(event.conn)
        elif type(event) is HalfClosed:
            self.ended(event.conn, event.direction)
        elif type(event) is UpstreamFailed:
            self.ended(event.conn, S2C)
        elif type(event) is Gap:
            self.gap(event.conn, event.direction, event.length or 0)
        elif type(event) is Closed:
            self.closed(event.conn)

    def opened(self, conn: int) -> None:
        self._masks[conn] = LoginMask()

    def read(self, conn: int, direction: Direction, data: bytes, record: R, now: float) -> None:
        mask = self._masks.get(conn)
        offset = 0
        if mask is not None:
            if direction is C2S:
                offset = mask.received
                mask.client(data)
            else:
                mask.server(data)
            self._settle(conn, mask, now)
        self._queue.append(_Entry(conn, direction, mask if direction is C2S else None, offset, data, record))
        self._queued += len(data)
        while self._queued > self.queue_cap and self._queue and self._held(self._queue[0]):
            self.force(self._queue[0].conn)  # too much waits behind it: mask rather than hold

    def event(self, conn: int, record: R) -> None:
        """A connection event, to come out after what arrived before it."""
        self._queue.append(_Entry(conn, None, None, 0, b"", record))

    def ended(self, conn: int, direction: Direction) -> None:
        """One side shut down (call before queuing its event)."""
        mask = self._masks.get(conn)
        if mask is not None:
            if direction is S2C:
                mask.server_ended()
            else:
                mask.client_ended()
            self._settle(conn, mask)

    def gap(self, conn: int, direction: Direction, length: int) -> None:
        mask = self._masks.get(conn)
        if mask is None:
            return
        if direction is C2S:
            mask.client_gap(length)
        else:
            mask.server_gap()
        self._settle(conn, mask)

    def closed(self, conn: int) -> None:
        """The connection is over (call before queuing its event): what is undecided is masked."""
        mask = self._masks.pop(conn, None)
        if mask is not None:
            mask.end()
        self._since.pop(conn, None)

    def force(self, conn: int) -> None:
        mask = self._masks.get(conn)
        if mask is not None:
            mask.force()
            self._settle(conn, mask)

    def tick(self, now: float) -> None:
        """Mask what has been undecided for longer than ``hold_s``."""
        for conn, since in list(self._since.items()):
            if now - since >= self.hold_s:
                self.force(conn)

    def finish(self) -> None:
        """Nothing more will come: mask everything undecided."""
        for conn in list(self._masks):
            self.closed(conn)

    def released(self) -> Iterator[Released[R]]:
        """What may be taken now, in arrival order."""
        queue = self._queue
        while queue and not self._held(queue[0]):
            e = queue.popleft()
            self._queued -= len(e.data)
            if e.mask is not None:
                data, spans = e.mask.apply(e.offset, e.data)
                yield Released(e.conn, e.direction, data, spans, e.record)
            else:
                yield Released(e.conn, e.direction, e.data, [], e.record)

    # -- internals ---------------------------------------------------------------------------

    @staticmethod
    def _held(e: _Entry[R]) -> bool:
        return e.mask is not None and e.offset + len(e.data) > e.mask.decided

    def _settle(self, conn: int, mask: LoginMask, now: float | None = None) -> None:
        """Note when undecided bytes began to wait (``now``: a read just came);
        forget a connection with nothing left to mask."""
        if mask.phase is Phase.OPEN:
            del self._masks[conn]
        if not mask.undecided:
            self._since.pop(conn, None)
        elif now is not None:
            self._since.setdefault(conn, now)
