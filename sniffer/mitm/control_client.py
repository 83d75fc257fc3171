"""A client of the control API that makes sure it talks to one before it
says anything that matters (``whiztap ctl``; docs/faults.md).

A control API's port is easily mixed up with the proxy's ``--listen`` port
or the robot's, and an HTTP request sent there is not harmless: through the
proxy it reaches the robot, which takes its first line for a password.  So,
before the first request:

1. On TCP, connect and listen for ``QUIET_S``: an HTTP server waits for its
   client, while a Winsock robot (and so a proxy in front of one) speaks
   first ('sendchkpass').  A peer that speaks, or hangs up, is not the API,
   and gets no byte.
2. Then a harmless ``GET /intercept``, whose answer must carry the Server
   header ``whiztap/VERSION`` that every answer of the API carries.

Answers are read by h11, at most ``MAX_ANSWER`` bytes of body and
``TIMEOUT_S`` in all: a peer that sends endlessly or slowly costs neither
memory nor forever.  Every failure is a ``ControlClientError`` whose message
is one line for the user.
"""

from __future__ import annotations

import json
import socket
import time
from typing import Any

import h11

from whiztap.analyzer import __version__
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.nettext import reason, show_address

QUIET_S = 0.3  # a control API says nothing first; a robot says 'sendchkpass' at once
TIMEOUT_S = 10.0  # to connect, send a request and read its whole answer
MAX_ANSWER = 16 << 20  # an answer's body: GET /state with a few thousand held frames fits many times over
MAX_HEAD = 64 << 10
SIGNATURE = b"whiztap/"
PROBE = ("GET", "/intercept")  # small, and it changes nothing
SHOWN = 40  # bytes of a stranger's words quoted in a message


class ControlClientError(WhiztapError):
    """The request could not be made, or was answered by something other than
    the control API; the message is one line for the user."""


class ApiRefusal(ControlClientError):
    """The control API answered with an error: ``status``, and its message."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class ControlClient:
    """Requests to the control API at ``endpoint``, the first one after the
    endpoint was recognised as one."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.where = str(endpoint)
        self._recognised = False

    def call(self, method: str, path: str, body: Any = None) -> Any:
        """The JSON answer to one request; ApiRefusal for the API's error
        answers, ControlClientError for everything else."""
        if not self._recognised:
            self._recognise()
        with self._connect() as sock:
            status, answer = self._exchange(sock, method, path, body)
        if status >= 400:
            raise ApiRefusal(status, _error_text(status, answer))
        return answer

    def _recognise(self) -> None:
        with self._connect() as sock:
            if not self.endpoint.unix:
                self._listen_first(sock)
            status, answer = self._exchange(sock, *PROBE, None)
        if status == 401:
            if self.endpoint.token is None:
                raise ControlClientError(f"the control API at {self.where} takes a token: give the one "
                                         f"'whiztap record' printed with --control-token or WHIZTAP_CONTROL_TOKEN")
            raise ControlClientError(f"the control API at {self.where} refused the token given; give the one "
                                     f"'whiztap record' printed at start")
        if status >= 400:
            raise ApiRefusal(status, _error_text(status, answer))
        self._recognised = True

    def _connect(self) -> socket.socket:
        e = self.endpoint
        try:
            if e.path is not None:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.settimeout(TIMEOUT_S)
                try:
                    sock.connect(e.path)
                except OSError:
                    sock.close()
                    raise
                return sock
            return socket.create_connection((e.host, e.port), timeout=TIMEOUT_S)
        except TimeoutError:
            raise self._unreachable(f"no answer within {TIMEOUT_S:g} s") from None
        except OSError as err:
            raise self._unreachable(reason(err)) from None

    def _unreachable(self, why: str) -> ControlClientError:
        return ControlClientError(f"cannot reach the control API at {self.where}: {why[:1].lower()}{why[1:]}; "
                                  f"is 'whiztap record --control' running there?")

    def _listen_first(self, sock: socket.socket) -> None:
        """Nothing is sent until the peer was quiet for ``QUIET_S``."""
        sock.settimeout(QUIET_S)
        try:
            said = sock.recv(SHOWN)
        except TimeoutError:
            return
        except OSError as err:
            raise self._unreachable(reason(err)) from None
        finally:
            sock.settimeout(TIMEOUT_S)
        if not said:
            raise self._stranger("it closed the connection before a word was said")
        raise self._stranger(f"it sent {escape(said)!r}; is that the proxy's --listen port?")

    def _stranger(self, what: str) -> ControlClientError:
        return ControlClientError(f"{self.where} is not a whiztap control API ({what})")

    def _exchange(self, sock: socket.socket, method: str, path: str, body: Any) -> tuple[int, Any]:
        """Send one request, read its answer: the status and the JSON body."""
        conn = h11.Connection(h11.CLIENT, max_incomplete_event_size=MAX_HEAD)
        data = b"" if body is None else json.dumps(body).encode()
        try:
            sock.sendall(conn.send(h11.Request(method=method, target=path, headers=self._headers(data)))
                         + conn.send(h11.Data(data=data)) + conn.send(h11.EndOfMessage()))
        except OSError as err:
            raise self._unreachable(reason(err)) from None
        return self._answer(conn, sock, time.monotonic() + TIMEOUT_S)

    def _headers(self, data: bytes) -> list[tuple[str, str]]:
        e = self.endpoint
        headers = [("Host", "localhost" if e.unix else show_address(e.host, e.port)),
                   ("User-Agent", f"whiztap-ctl/{__version__}"), ("Connection", "close"),
                   ("Content-Length", str(len(data)))]
        if data:
            headers.append(("Content-Type", "application/json"))
        if e.token is not None:
            headers.append(("Authorization", f"Bearer {e.token}"))
        return headers

    def _answer(self, conn: h11.Connection, sock: socket.socket, deadline: float) -> tuple[int, Any]:
        status, body, first = 0, bytearray(), b""
        while True:
            try:
                event = conn.next_event()
            except h11.RemoteProtocolError:
                if status:  # its head was HTTP, and whiztap's: the rest broke off
                    raise ControlClientError(f"the control API at {self.where} closed before its answer "
                                             f"ended") from None
                raise self._stranger(f"it answered {escape(first[:SHOWN])!r}, which is not HTTP") from None
            if event is h11.NEED_DATA:
                chunk = self._read(sock, deadline)
                first = first or chunk
                if not first:
                    raise self._stranger("it closed the connection without an answer")
                if first[:5] != b"HTTP/"[:len(first)]:
                    raise self._stranger(f"it answered {escape(first[:SHOWN])!r}, which is not HTTP")
                conn.receive_data(chunk)
            elif isinstance(event, h11.Response):
                status = event.status_code
                self._check_signature(event)
            elif isinstance(event, h11.Data):
                body += event.data
                if len(body) > MAX_ANSWER:
                    raise ControlClientError(f"the control API at {self.where} answered more than "
                                             f"{MAX_ANSWER >> 20} MiB; stopped reading")
            elif isinstance(event, h11.EndOfMessage):
                return status, self._json(bytes(body))
            elif isinstance(event, h11.ConnectionClosed):
                raise ControlClientError(f"the control API at {self.where} closed before its answer ended")

    def _read(self, sock: socket.socket, deadline: float) -> bytes:
        left = deadline - time.monotonic()
        if left <= 0:
            raise ControlClientError(f"the control API at {self.where} did not answer within {TIMEOUT_S:g} s")
        sock.settimeout(left)
        try:
            return sock.recv(1 << 16)
        except TimeoutError:
            raise ControlClientError(f"the control API at {self.where} did not answer within "
                                     f"{TIMEOUT_S:g} s") from None
        except OSError as err:
            raise ControlClientError(f"the control API at {self.where} broke off its answer: "
                                     f"{reason(err).lower()}") from None

    def _check_signature(self, response: h11.Response) -> None:
        server = dict(response.headers).get(b"server", b"")
        if not server.startswith(SIGNATURE):
            said = f"HTTP {response.status_code}" + (f" from {server.decode('latin-1')[:SHOWN]!r}" if server else "")
            raise self._stranger(f"it answered {said}, without whiztap's Server header")
        length = dict(response.headers).get(b"content-length", b"0")
        if len(length) > 12 or int(length) > MAX_ANSWER:
            raise ControlClientError(f"the control API at {self.where} would answer {length[:20].decode()} bytes, "
                                     f"more than {MAX_ANSWER >> 20} MiB; not read")

    def _json(self, body: bytes) -> Any:
        try:
            return json.loads(body)
        except (ValueError, RecursionError):
            raise ControlClientError(f"the control API at {self.where} answered something that is not JSON "
                                     f"({escape(body[:SHOWN])!r})") from None


def _error_text(status: int, answer: Any) -> str:
    if isinstance(answer, dict) and isinstance(answer.get("error"), str):
        return answer["error"]
    return f"the control API answered HTTP {status}"
