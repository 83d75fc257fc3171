"""The control API's server: HTTP/1.1 read by h11 on a Unix socket or TCP,
each request's head checked (``control_guard``) before its body is read, the
answer ``http_api``'s (docs/faults.md, "Reaching the control API").

One request per connection (``Connection: close``), so a client that stalls
(``CLIENT_TIMEOUT_S`` for the whole request), sends what is not HTTP, a head
over ``MAX_HEAD`` or a body over ``MAX_BODY`` costs only its own connection:
408, 400 (431 for the head), 413.  Every answer, errors included, carries
``Server: whiztap/VERSION``, by which ``whiztap ctl`` knows it reached a
control API and not some other server.

Requests are handled in the proxy's event loop, because the ``Controller``
is not thread-safe; its calls do no I/O, so they hold the traffic back no
longer than any other event would.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import secrets
import socket
from typing import Any
from urllib.parse import urlsplit

import h11

from whiztap.analyzer import __version__
from whiztap.sniffer.mitm.control_endpoint import Endpoint, EndpointError, default_socket_path, socket_state
from whiztap.sniffer.mitm.control_guard import MAX_BODY, check_head
from whiztap.sniffer.mitm.controller import Controller
from whiztap.sniffer.mitm.http_api import HttpError, Request, answer
from whiztap.sniffer.nettext import show_address

SIGNATURE = f"whiztap/{__version__}"
MAX_HEAD = 16 << 10  # the request line and headers
READ_SIZE = 16 << 10
CLIENT_TIMEOUT_S = 10.0  # to send a whole request, and to take the answer
LINGER_S = 2.0  # after the answer, how long the rest of a refused request is read and thrown away
LINGER_BYTES = 1 << 20
ONCE = frozenset({b"host", b"authorization", b"content-type", b"origin"})  # headers a request may carry once
REASONS = {200: "OK", 201: "Created", 400: "Bad Request", 401: "Unauthorized", 403: "Forbidden",
           404: "Not Found", 405: "Method Not Allowed", 408: "Request Timeout", 409: "Conflict",
           411: "Length Required", 413: "Content Too Large", 429: "Too Many Requests",
           431: "Request Header Fields Too Large", 500: "Internal Server Error"}


class ControlServer:
    """The control API at ``endpoint``; ``url`` and ``token`` say, once started,
    where it is and what a TCP client must send.

    A plain non-blocking listener whose readiness callback accepts, rather
    than an ``asyncio.Server`` (or a task awaiting ``sock_accept``): when those
    close or are cancelled, a connection they had just accepted is left open
    and unowned, and its client waits for ever.  Here each accepted socket is
    in ``_open`` at once, and stop() closes every one."""

    def __init__(self, controller: Controller, endpoint: Endpoint) -> None:
        self.controller = controller
        self.endpoint = endpoint
        self.token = None if endpoint.unix else endpoint.token or secrets.token_urlsafe(24)
        self._listener: socket.socket | None = None
        self._open: dict[asyncio.Task, socket.socket] = {}  # each connection's task and socket
        self._inode: int | None = None  # the socket file made, removed at stop if still the same

    @property
    def url(self) -> str:
        """The socket's path, or ``http://HOST:PORT`` (the bound port)."""
        e = self.endpoint
        if e.path is not None:
            return e.path
        return f"http://{show_address(e.host, e.port)}"

    async def start(self) -> None:
        """Listen.  OSError if the address cannot be bound; EndpointError for a
        socket path in use, or that is not a socket, or an unsafe runtime folder."""
        listener = self._bind_unix() if self.endpoint.unix else self._bind_tcp()
        listener.setblocking(False)
        listener.listen(64)
        self._listener = listener
        asyncio.get_running_loop().add_reader(listener.fileno(), self._accept)

    def _bind_tcp(self) -> socket.socket:
        e = self.endpoint
        family, _, _, _, address = socket.getaddrinfo(e.host or None, e.port, type=socket.SOCK_STREAM,
                                                      flags=socket.AI_PASSIVE)[0]
        listener = socket.create_server(address, family=family)
        self.endpoint = Endpoint(host=e.host, port=listener.getsockname()[1], token=self.token)
        return listener

    def _bind_unix(self) -> socket.socket:
        """The socket bound and made 0600 before it listens, so nobody else
        can connect in between; a socket a killed server left there is replaced."""
        path = self.endpoint.path or str(default_socket_path())
        state = socket_state(path)
        if state == "live":
            raise EndpointError(f"{path} is served already (another whiztap?); give another --control PATH")
        if state == "other":
            raise EndpointError(f"{path} exists and is not a socket; give another --control PATH")
        if state == "stale":
            os.unlink(path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(path)
            os.chmod(path, 0o600)
            self._inode = os.stat(path).st_ino
        except OSError:
            sock.close()
            raise
        self.endpoint = Endpoint(path=path)
        return sock

    async def stop(self) -> None:
        """Stop listening, end the connections still open, remove the socket file."""
        listener, self._listener = self._listener, None
        if listener is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(listener.fileno())
        self._end_waiting(listener)
        open_now = dict(self._open)
        for task in open_now:
            task.cancel()
        await asyncio.gather(*open_now, return_exceptions=True)
        for sock in open_now.values():  # a task cancelled before it began never closed its own
            sock.close()
        path = self.endpoint.path
        with contextlib.suppress(OSError):
            if path and os.stat(path).st_ino == self._inode:
                os.unlink(path)

    @staticmethod
    def _end_waiting(listener: socket.socket) -> None:
        """Close the connections still waiting to be accepted, then the listener.
        Each is accepted and closed, so its client reads an end: closing the
        listener over them would reset a Unix socket's clients without waking
        their poll, and they would wait for ever."""
        while True:
            try:
                sock, _ = listener.accept()
            except OSError:  # BlockingIOError: none left
                break
            sock.close()
        listener.close()

    def _accept(self) -> None:
        """The listener is readable: every connection waiting, each to a task of its own."""
        loop = asyncio.get_running_loop()
        while self._listener is not None:
            try:
                sock, _ = self._listener.accept()
            except BlockingIOError:
                return
            except OSError:  # out of descriptors, say: rest a moment rather than spin on a readable listener
                fd = self._listener.fileno()
                loop.remove_reader(fd)
                loop.call_later(0.1, self._resume, fd)
                return
            sock.setblocking(False)
            task = loop.create_task(self._serve(sock))
            self._open[task] = sock
            task.add_done_callback(lambda done: self._open.pop(done, None))

    def _resume(self, fd: int) -> None:
        if self._listener is not None and self._listener.fileno() == fd:
            asyncio.get_running_loop().add_reader(fd, self._accept)

    async def _serve(self, sock: socket.socket) -> None:
        try:
            await self._one(sock)
        except (ConnectionError, OSError, TimeoutError):
            pass  # that client's loss only
        finally:
            sock.close()

    async def _one(self, sock: socket.socket) -> None:
        """Read one request, answer it, close."""
        loop = asyncio.get_running_loop()
        allow: tuple[str, ...] = ()
        try:
            request = await asyncio.wait_for(self._receive(sock), CLIENT_TIMEOUT_S)
            if request is None:
                return
            status, payload, allow = answer(self.controller, request)
        except TimeoutError:
            status, payload = 408, {"error": f"no complete request within {CLIENT_TIMEOUT_S:g} s"}
        except HttpError as e:
            status, payload, allow = e.status, {"error": str(e)}, e.allow
        await asyncio.wait_for(loop.sock_sendall(sock, response(status, payload, allow)), CLIENT_TIMEOUT_S)
        sock.shutdown(socket.SHUT_WR)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(_discard(sock), LINGER_S)


    async def _receive(self, sock: socket.socket) -> Request | None:
        """One request, its head checked before its body is read; None if the
        client closed before sending one.  HttpError for anything refused."""
        loop = asyncio.get_running_loop()
        conn = h11.Connection(h11.SERVER, max_incomplete_event_size=MAX_HEAD)
        head: h11.Request | None = None
        body = bytearray()
        while True:
            try:
                event = conn.next_event()
            except h11.RemoteProtocolError as e:  # h11's 501 is a Transfer-Encoding it does not know: no length
                raise HttpError(411 if e.error_status_hint == 501 else e.error_status_hint,
                                f"not a request the control API takes: {e}") from None
            if event is h11.NEED_DATA:
                conn.receive_data(await loop.sock_recv(sock, READ_SIZE))
            elif isinstance(event, h11.Request):
                check_head(_headers(event.headers), self.endpoint, self.token)
                head = event
            elif isinstance(event, h11.Data):
                body += event.data
                if len(body) > MAX_BODY:  # check_head saw its Content-Length; this is a second lock
                    raise HttpError(413, f"the body is over {MAX_BODY} bytes")
            elif isinstance(event, h11.EndOfMessage) and head is not None:
                target = urlsplit(head.target.decode("latin-1")).path
                return Request(head.method.decode("ascii").upper(), target, bytes(body))
            elif isinstance(event, h11.ConnectionClosed):
                return None


async def _discard(sock: socket.socket) -> None:
    """Read what the client still sends (a body refused unread), up to
    ``LINGER_BYTES``, until it closes: closing on unread bytes resets the
    connection, and a reset can reach the client before it read the answer."""
    loop = asyncio.get_running_loop()
    left = LINGER_BYTES
    while left > 0:
        data = await loop.sock_recv(sock, READ_SIZE)
        if not data:
            return
        left -= len(data)


def _headers(pairs: Any) -> dict[bytes, bytes]:
    """h11's header list as a dict; 400 for a header that must come once and came twice."""
    headers: dict[bytes, bytes] = {}
    for name, value in pairs:
        if name in headers and name in ONCE:
            raise HttpError(400, f"more than one {name.decode()} header")
        headers[name] = value
    return headers


def response(status: int, payload: Any, allow: tuple[str, ...] = ()) -> bytes:
    """An answer whole: a JSON body, whiztap's Server header, Connection: close."""
    body = json.dumps(payload).encode() + b"\n"
    head = [f"HTTP/1.1 {status} {REASONS.get(status, 'Error')}", "Content-Type: application/json",
            f"Content-Length: {len(body)}", "Connection: close", f"Server: {SIGNATURE}"]
    if allow:
        head.append(f"Allow: {', '.join(allow)}")
    if status == 401:
        head.append('WWW-Authenticate: Bearer realm="whiztap"')
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body
