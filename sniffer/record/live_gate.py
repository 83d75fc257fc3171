"""The gate in front of the live Foxglove server: web pages you did not choose
cannot read the traffic.

Why a gate: a browser lets any page open a WebSocket to ``127.0.0.1``; the
only thing that tells whiztap which site opened it is the handshake's
``Origin`` header.  The ``foxglove-sdk`` server (0.30) checks only the
subprotocol: no origin check, no token, no hook on the handshake (its
``handshake.rs`` and its Python stubs, read for this).  So the SDK's server
listens on a loopback address no page can guess (``127.R.R.R``, random, port
chosen by the system; ``127.0.0.1`` where the system has no other loopback
address), and this gate listens where the user asked.  For each connection it
reads the HTTP upgrade request (at most ``HEAD_LIMIT`` bytes, within
``HEAD_TIMEOUT_S``), refuses with 403 an ``Origin`` that is not allowed (one
warning per origin), refuses with 400 what is no WebSocket upgrade, and
otherwise connects to the SDK's server, hands it the request as read and
splices bytes both ways untouched until either side ends.

Allowed: no ``Origin`` at all (not a browser page: Foxglove's desktop app, a
script), ``https://app.foxglove.dev``, ``http(s)://localhost``,
``127.0.0.1`` and ``[::1]`` with any port, and each ``--foxglove-origin``.

Bounded: at most ``MAX_CLIENTS`` connections at once (more are closed at
once), and per connection the request head plus, each way, a transport's
high-water mark and one read: a viewer that stops reading stops the gate
reading the SDK, whose own bounded queue then drops the oldest messages
(``live.py``).  The gate runs on its own event loop in a thread of the writer
process; the recording never waits on it.
"""

from __future__ import annotations

import asyncio
import re
import socket
import threading
from collections.abc import Callable
from typing import NamedTuple, cast

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.text import printable, shorten
from whiztap.sniffer.nettext import show_address

HEAD_LIMIT = 16 << 10
HEAD_TIMEOUT_S = 10.0
MAX_CLIENTS = 64
HIGH_WATER = 256 << 10
FOXGLOVE_APP = "https://app.foxglove.dev"
MAX_ORIGINS_SAID = 8  # refused origins warned about by name; later ones are counted in one line
_LOCAL_ORIGIN = re.compile(r"https?://(localhost|127\.0\.0\.1|\[::1\])(:\d{1,5})?")
_ORIGIN = re.compile(r"null|[a-z][a-z0-9+.-]*://[^/\s?#]*")
_END = b"\r\n\r\n"
_TOKEN = re.compile(r"[!#$%&'*+.^_`|~0-9A-Za-z-]+")


class LiveAddress(NamedTuple):
    """Where ``--foxglove`` serves, and the web origins also allowed to read it
    (``--foxglove-origin``); a tuple, so it travels to the writer as JSON."""

    host: str
    port: int
    origins: tuple[str, ...] = ()


def origin_text(text: str) -> str:
    """An origin as a browser sends it (``scheme://host[:port]``, lower case,
    no path), or ``null``; ValueError naming what is wrong."""
    origin = text.strip().lower()
    if origin.endswith("/") and not origin.endswith("://"):  # as copied from the address bar
        origin = origin[:-1]
    if not _ORIGIN.fullmatch(origin):
        raise ValueError(f"{text!r} is not an origin: give SCHEME://HOST[:PORT] as the browser sends it "
                         f"(e.g. https://studio.example.com), or null")
    return origin


def origin_allowed(origin: str | None, extra: frozenset[str]) -> bool:
    """Whether a handshake with this ``Origin`` (None: none) may be served."""
    if origin is None:
        return True
    origin = origin.strip().lower()
    return origin == FOXGLOVE_APP or origin in extra or _LOCAL_ORIGIN.fullmatch(origin) is not None


class BadRequest(WhiztapError, ValueError):
    """A request head that is not one HTTP/1.1 request line and header fields."""


def parse_head(head: bytes) -> tuple[str, dict[str, list[str]]]:
    """(method, header fields by lower-case name) of an HTTP request head (the
    bytes before the blank line).  Strict: a browser never sends anything
    else, and what the gate cannot read it does not pass on."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not _TOKEN.fullmatch(parts[0]) or not parts[2].startswith("HTTP/1."):
        raise BadRequest("not an HTTP/1.1 request line")
    fields: dict[str, list[str]] = {}
    for line in lines[1:]:
        name, colon, value = line.partition(":")
        if not colon or not _TOKEN.fullmatch(name):
            raise BadRequest("a header line that is not NAME: VALUE")
        fields.setdefault(name.lower(), []).append(value.strip(" \t"))
    return parts[0], fields


def verdict(head: bytes, extra: frozenset[str]) -> tuple[int, str | None]:
    """(status, origin): 0 to serve the request, else the HTTP status to
    refuse it with; the origin it names (None: none, or unreadable)."""
    try:
        method, fields = parse_head(head)
    except BadRequest:
        return 400, None
    origins = fields.get("origin", [])
    origin = origins[0] if len(origins) == 1 else None
    if len(origins) > 1 or not origin_allowed(origin, extra):
        return 403, origin if len(origins) == 1 else ", ".join(origins)
    upgrade = ",".join(fields.get("upgrade", [])).lower()
    if method != "GET" or "websocket" not in upgrade:
        return 400, origin
    return 0, origin


_REASONS = {400: "Bad Request", 403: "Forbidden", 431: "Request Header Fields Too Large"}


def refusal(status: int, text: str) -> bytes:
    """A complete HTTP answer that ends the connection."""
    body = f"whiztap: {text}\n".encode()
    return (f"HTTP/1.1 {status} {_REASONS[status]}\r\nContent-Type: text/plain; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode() + body


class _Refusals:
    """Warnings about refused origins: once per origin, by name for the first
    ``MAX_ORIGINS_SAID`` (a page that retries in a loop says nothing more),
    then one line that more were refused.  Memory: at most that many names."""

    def __init__(self, warn: Callable[[str], None]) -> None:
        self.warn = warn
        self.said: set[str] = set()
        self.more = False

    def refused(self, origin: str, peer: str) -> None:
        if origin in self.said:
            return
        if len(self.said) >= MAX_ORIGINS_SAID:
            if not self.more:
                self.more = True
                self.warn("warning: foxglove: more web origins were refused; they are not named again")
            return
        self.said.add(origin)
        shown = shorten(printable(origin), 200)
        self.warn(f"warning: foxglove: refused a connection from {peer} sent by the web page at {shown} "
                  f"(if that is yours, allow it with --foxglove-origin {shown})")


class _Side(asyncio.Protocol):
    """One socket of a spliced connection: what it reads is written to the
    other side, and it stops reading while the other side's buffer is full."""

    def __init__(self, conn: _Conn) -> None:
        self.conn = conn
        self.transport: asyncio.Transport | None = None
        self.other: _Side | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # a TCP connection's
        self.transport.set_write_buffer_limits(high=HIGH_WATER)

    def _spliced(self) -> asyncio.Transport | None:
        """The other side's transport, once the two are spliced."""
        return self.other.transport if self.other is not None else None

    def data_received(self, data: bytes) -> None:
        other = self._spliced()
        if other is not None:
            other.write(data)

    def eof_received(self) -> bool:
        other = self._spliced()
        if other is not None and other.can_write_eof():
            other.write_eof()
        return True

    def pause_writing(self) -> None:
        other = self._spliced()
        if other is not None:
            other.pause_reading()

    def resume_writing(self) -> None:
        other = self._spliced()
        if other is not None:
            other.resume_reading()

    def connection_lost(self, exc: Exception | None) -> None:
        self.conn.lost()


class _Client(_Side):
    """The viewer's socket: first its request head, judged, then spliced."""

    def __init__(self, conn: _Conn) -> None:
        super().__init__(conn)
        self.head = bytearray()  # from the start: the gate lists the connection before it is made

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        tcp = cast(asyncio.Transport, transport)
        peer = tcp.get_extra_info("peername")
        self.conn.peer = show_address(*peer[:2]) if peer else "?"
        self.timer = asyncio.get_running_loop().call_later(HEAD_TIMEOUT_S, tcp.abort)
        if len(self.conn.gate.conns) > MAX_CLIENTS:
            tcp.abort()

    def data_received(self, data: bytes) -> None:
        if self.other is not None:
            super().data_received(data)
            return
        self.head += data
        end = self.head.find(_END)
        if end < 0:
            if len(self.head) > HEAD_LIMIT:
                self._refuse(431, "the request head is too large")
            return
        self.timer.cancel()
        head, self.head = bytes(self.head), bytearray()  # judged once; not kept for the connection's life
        status, origin = verdict(head[:end], self.conn.gate.origins)
        if status == 403:
            self.conn.gate.refusals.refused(origin or "", self.conn.peer)
            self._refuse(403, f"the web page at {origin} may not read this recording live; "
                                      "whiztap record --foxglove-origin ORIGIN allows one")
        elif status:
            self._refuse(status, "this port serves the recording to the Foxglove app "
                                         "(a Foxglove WebSocket connection) and nothing else")
        elif self.transport is not None:  # it has one: it read the head
            self.transport.pause_reading()  # until the SDK's side is there
            self.conn.open_upstream(head)

    def eof_received(self) -> bool:
        if self.other is None:  # it ended before its request did: nothing to pass on
            return False
        return super().eof_received()

    def _refuse(self, status: int, text: str) -> None:
        self.timer.cancel()
        if self.transport is not None:  # it has one: it read the head
            self.transport.write(refusal(status, shorten(printable(text), 400)))
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.timer.cancel()
        super().connection_lost(exc)


class _Conn:
    """A viewer's connection through the gate to the SDK's server."""

    def __init__(self, gate: LiveGate) -> None:
        self.gate = gate
        self.client = _Client(self)
        self.upstream: _Side | None = None
        self.peer = "?"
        self.closed = False
        gate.conns.add(self)

    def open_upstream(self, head: bytes) -> None:
        asyncio.get_running_loop().create_task(self._connect(head))

    async def _connect(self, head: bytes) -> None:
        loop = asyncio.get_running_loop()
        upstream = _Side(self)
        client = self.client.transport  # the head was read from it
        try:
            transport, _ = await loop.create_connection(lambda: upstream, *self.gate.inner)
        except OSError:
            if client is not None:
                client.abort()
            return
        if self.closed or client is None:
            transport.close()
            return
        self.upstream = upstream
        upstream.other, self.client.other = self.client, upstream
        transport.write(head)  # the request as read, and what came after it
        client.resume_reading()

    def lost(self) -> None:
        """Either side ended: the other closes once it has sent what it holds."""
        self.closed = True
        self.gate.conns.discard(self)
        for side in (self.client, self.upstream):
            if side is not None and side.transport is not None:
                side.transport.close()


class LiveGate:
    """Listens on ``sock`` (bound by the caller, so that a port in use is its
    error) and lets allowed viewers through to ``inner`` (host, port)."""

    def __init__(self, sock: socket.socket, inner: tuple[str, int], origins: tuple[str, ...],
                 warn: Callable[[str], None]) -> None:
        self.sock = sock
        self.inner = inner
        self.origins = frozenset(origins)
        self.refusals = _Refusals(warn)
        self.conns: set[_Conn] = set()
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="whiztap-foxglove-gate", daemon=True)

    def start(self) -> None:
        """Serve from now on (connections made before wait in the backlog)."""
        self._thread.start()

    def _run(self) -> None:
        loop = self.loop
        asyncio.set_event_loop(loop)
        loop.run_until_complete(loop.create_server(self._accept, sock=self.sock, backlog=MAX_CLIENTS))
        loop.run_forever()

    def _accept(self) -> _Client:
        conn = _Conn(self)
        return conn.client
