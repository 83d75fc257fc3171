"""Which client bytes may hold the Winsock password, decided from the bytes alone.

The rule (docs/recording-format.md, *Passwords*), per connection:

* Until the server's first bytes (line breaks aside) say which, a session may
  be Winsock: the client's bytes are *undecided* and held back.
* If the server begins with ``sendchkpass`` the session is Winsock: every
  client byte received before the server's verdict (``readytogo`` or
  ``Failed Validation``, wherever it comes in the server's bytes) is masked,
  and so are the client's bytes after the verdict up to its first line break
  or frame header (``rr1-``, ``cr1-``, ``sr1-``): a server may judge a
  password before its end (at its first wrong byte), and the rest follows.
  From there on, nothing is masked.
* If the server begins with anything else, there is no login (VPN mode, or
  not the Progwhiz protocol): nothing the client sends is masked, held bytes
  included.
* A server that ends (or is never reached, or the connection closes) before
  its first bytes leaves the session undecided for good: the client's bytes
  are masked, unless the client began with a frame header (line breaks
  aside), which no Winsock client does (it begins with its password).

Masking replaces each byte by ``*`` except CR and LF, which end a password
and keep the items around it in shape; lengths never change.  The decisions
depend on the byte streams and the order in which reads arrived, never on how
the bytes were cut into reads.  What only a clock or a bound decides (held too
long, too many undecided bytes, the connection closed undecided) is to mask,
never to show.

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
from typing import Generic, NamedTuple, TypeVar

from whiztap.analyzer.recording.format import MASK_BYTE
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, ConnectionEvent, Gap, HalfClosed, Opened, UpstreamFailed

HOLD_LIMIT_S = 2.0  # undecided bytes are masked rather than held longer than this
UNDECIDED_CAP = 16 * 1024  # ... or once a connection has this many
QUEUE_CAP = 8 << 20  # ... or once this much traffic waits behind them
GREETING = b"sendchkpass"
_VERDICT = re.compile(rb"readytogo|Failed Validation")
_VERDICT_CARRY = len(b"Failed Validation") - 1
_LINE_END = re.compile(rb"[\r\n]|[rcs]r1-")
_HEADERS = (b"rr1-", b"cr1-", b"sr1-")
_HEADER_SIZE = 4
_MASKABLE = re.compile(rb"[^\r\n]+")
_ALL = 1 << 62  # an offset past any stream's end
C2S, S2C = Direction.C2S, Direction.S2C


class Phase(Enum):
    GREETING = "greeting"  # the server has not said whether it asks for a password
    LOGIN = "login"  # Winsock, before the verdict: every client byte is masked
    TAIL = "tail"  # after the verdict, up to the client's next line break or frame header
    OPEN = "open"  # nothing more is masked


class LoginMask:
    """One connection: which of its client's bytes are masked.

    The masked bytes are always a prefix of the client's stream: offsets below
    ``masked_end`` are masked, from there up to ``decided`` they are shown, and
    from ``decided`` on nothing is known yet."""

    __slots__ = ("phase", "received", "masked_end", "decided", "_greeted", "_carry", "_head")

    def __init__(self) -> None:
        self.phase = Phase.GREETING
        self.received = 0  # client bytes so far
        self.masked_end = 0
        self.decided = 0
        self._greeted = 0  # bytes of 'sendchkpass' the server has sent so far
        self._carry = b""  # bytes a token may straddle: the server's (LOGIN) or the client's (TAIL)
        self._head = b""  # the client's first bytes, line breaks aside (up to a frame header's length)

    @property
    def undecided(self) -> int:
        return max(self.received - self.decided, 0)

    # -- input -----------------------------------------------------------------------------

    def client(self, data: bytes) -> None:
        """Bytes from the client, in order."""
        self.received += len(data)
        if len(self._head) < _HEADER_SIZE:
            self._head = (self._head + data).lstrip(b"\r\n")[:_HEADER_SIZE]
        if self.phase is Phase.LOGIN:
            self.masked_end = self.decided = self.received
        elif self.phase is Phase.TAIL:
            self._scan_tail(data)
        elif self.phase is Phase.GREETING and self.undecided > UNDECIDED_CAP:
            self.force()

    def client_gap(self, length: int) -> None:
        """``length`` client bytes were never seen (a capture that missed them)."""
        self.received += length
        if self.phase in (Phase.LOGIN, Phase.TAIL):
            self.force()

    def server(self, data: bytes) -> None:
        """Bytes from the server, in order."""
        if self.phase is Phase.GREETING:
            self._scan_greeting(data)
        elif self.phase is Phase.LOGIN:
            self._scan_verdict(data)

    def server_gap(self) -> None:
        """Server bytes were never seen: the greeting or the verdict may be among them."""
        if self.phase is Phase.GREETING:
            self._login()
        elif self.phase is Phase.LOGIN:
            self._carry = b""  # a verdict may not straddle the hole

    def server_ended(self) -> None:
        """The server will send nothing more (it shut down, or was never reached)."""
        if self.phase is not Phase.GREETING:
            return
        if not self._greeted and self._head in _HEADERS:
            self._open()  # a client that begins with a frame: no password first
        else:
            self._login()  # never decided: mask

    def end(self) -> None:
        """The connection is over: decide, as if the server ended, and mask what is left."""
        self.server_ended()
        self.force()

    def force(self) -> None:
        """Mask what is undecided now (held too long, too much of it, or the end)."""
        if self.phase is not Phase.OPEN and self.received > self.decided:
            self.masked_end = self.decided = self.received
            if self.phase is Phase.TAIL:
                self._carry = b""  # a header may not begin in masked bytes

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

    def _login(self) -> None:
        self.phase = Phase.LOGIN
        self.masked_end = self.decided = self.received
        self._carry = b""

    def _open(self) -> None:
        self.phase = Phase.OPEN
        self.decided = _ALL
        self._carry = b""

    def _scan_greeting(self, data: bytes) -> None:
        if not self._greeted:
            data = data.lstrip(b"\r\n")
        wanted = GREETING[self._greeted:]
        n = min(len(wanted), len(data))
        if data[:n] != wanted[:n]:
            self._open()  # the server spoke first with something else: no login
            return
        self._greeted += n
        if self._greeted == len(GREETING):
            self._login()
            self._scan_verdict(data[n:])

    def _scan_verdict(self, data: bytes) -> None:
        seen = self._carry + data
        if _VERDICT.search(seen):
            self.phase = Phase.TAIL
            self._carry = b""
        else:
            self._carry = seen[-_VERDICT_CARRY:]

    def _scan_tail(self, data: bytes) -> None:
        """Mask up to the first line break or frame header; hold only the last
        bytes that may still begin a header."""
        base = self.decided
        seen = self._carry + data
        m = _LINE_END.search(seen)
        if m is not None:
            self.masked_end = base + m.start()
            self._open()
            return
        keep = next((k for k in (3, 2, 1) if len(seen) >= k and any(h.startswith(seen[-k:]) for h in _HEADERS)), 0)
        self.masked_end = self.decided = base + len(seen) - keep
        self._carry = seen[len(seen) - keep:]


R = TypeVar("R")


class _Entry(NamedTuple):
    conn: int
    direction: Direction | None  # None: not a read (a connection event)
    mask: LoginMask | None  # for a client read that may need masking
    offset: int
    data: bytes
    record: object


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
        self._queue: deque[_Entry] = deque()
        self._queued = 0  # bytes in the queue
        self._since: dict[int, float] = {}  # connection -> when its oldest undecided byte came

    def passing(self, conn: int) -> bool:
        """Nothing waits and nothing of ``conn`` can be masked: its traffic may skip the queue."""
        return not self._queue and conn not in self._masks

    @property
    def idle(self) -> bool:
        """Nothing waits: a connection event may be taken at once."""
        return not self._queue

    def tell(self, event: ConnectionEvent) -> None:
        """What a connection event means for the decisions (call before queuing
        it with ``event``): a new connection may log in; a server that ended or
        was never reached will give no verdict; a gap; the end."""
        kind = type(event)
        if kind is Opened:
            self.opened(event.conn)
        elif kind is HalfClosed:
            self.ended(event.conn, event.direction)  # type: ignore[union-attr]
        elif kind is UpstreamFailed:
            self.ended(event.conn, S2C)
        elif kind is Gap:
            self.gap(event.conn, event.direction, event.length or 0)  # type: ignore[union-attr]
        elif kind is Closed:
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
        if mask is not None and direction is S2C:
            mask.server_ended()
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
                yield Released(e.conn, e.direction, data, spans, e.record)  # type: ignore[arg-type]
            else:
                yield Released(e.conn, e.direction, e.data, [], e.record)  # type: ignore[arg-type]

    # -- internals ---------------------------------------------------------------------------

    @staticmethod
    def _held(e: _Entry) -> bool:
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
