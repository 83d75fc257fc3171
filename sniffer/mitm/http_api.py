"""The control API of the proxy in the middle: a small JSON HTTP server, in
the manner of toxiproxy's, that ``whiztap ctl`` (and curl) drive.

No authentication: whoever can connect to it can drop, edit and inject the
traffic.  ``whiztap record --control PORT`` binds 127.0.0.1; binding another
address hands control of the traffic to everyone who can reach it.

========  ===============================  =====================================================
GET       /state                           everything below at once (``Controller.state``)
GET       /connections                     {"connections": [...]}
GET       /faults                          {"faults": [...]}
POST      /faults                          {"spec": SPEC, "name": optional} -> 201 and the fault
DELETE    /faults/{id-or-name}             the fault removed
POST      /faults/{id-or-name}/enable      {"enabled": true|false} -> the fault
GET, PUT  /intercept                       {"filter": "dir:c2s kind:command"} ("" clears)
GET       /held                            {"held": [...]}
POST      /held/{id}/release               {"edit": optional frame text, "force": false}
POST      /held/{id}/drop                  the frame dropped
POST      /held/release-all                {"released": N}
POST      /inject                          {"conn": 1, "dir": "c2s"|"s2c", "frame": TEXT, "force": false}
========  ===============================  =====================================================

Errors are ``{"error": "one line"}``: 400 for a request the controller
refuses, bad JSON or a missing field; 404 for an unknown path or no such
fault, held frame or connection; 409 when the connection is closing (an
injection, release or edit racing its FIN or reset); 429 when an injection
would queue more than the lane may hold toward a side that is not reading; 405 for a
method the path does not take; 413 for a body over 64 KiB.  One request per
connection (``Connection: close``), so a client that stalls (10 s), sends
a malformed request line or too much costs only its own connection.

Requests are handled in the proxy's event loop, because the ``Controller``
is not thread-safe; its calls do no I/O, so they hold the traffic back no
longer than any other event would.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote, urlsplit

from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.mitm.controller import ControlError, Controller
from whiztap.sniffer.nettext import show_address

MAX_BODY = 64 << 10
MAX_LINE = 8 << 10  # the request line and each header line
MAX_HEADERS = 100
CLIENT_TIMEOUT_S = 10.0  # to send a whole request, and to take the answer
REASONS = {200: "OK", 201: "Created", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed",
           408: "Request Timeout", 409: "Conflict", 411: "Length Required", 413: "Content Too Large",
           429: "Too Many Requests", 500: "Internal Server Error"}


class HttpError(Exception):
    """A request answered with an error ``status`` and ``{"error": message}``
    (``allow``: the methods the path takes, for a 405's Allow header)."""

    def __init__(self, status: int, message: str, allow: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.status = status
        self.allow = allow


class _Malformed(Exception):
    """Not HTTP at all: the connection is answered 400 and closed."""


@dataclass
class Request:
    """One request as the handlers see it: the path without its query, the body read whole."""

    method: str
    path: str
    body: bytes

    def json(self) -> dict[str, Any]:
        """The body as a JSON object; an empty body is ``{}``."""
        if not self.body.strip():
            return {}
        try:
            value = json.loads(self.body)
        except (ValueError, UnicodeDecodeError) as e:
            raise HttpError(400, f"the body is not JSON: {e}") from None
        if not isinstance(value, dict):
            raise HttpError(400, "the body must be a JSON object")
        return value


_TYPES: dict[type, str] = {str: "a string", bool: "true or false", int: "a whole number"}


def field(body: dict[str, Any], name: str, kind: type, default: Any = ...) -> Any:
    """``body[name]`` if it is of ``kind`` (400 naming the field if not, or
    if it is missing and has no ``default``; JSON null counts as missing)."""
    value = body.get(name)
    if value is None:
        if default is ...:
            raise HttpError(400, f"missing field {name!r}")
        return default
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise HttpError(400, f"field {name!r} must be {_TYPES[kind]}, got {json.dumps(value)[:40]}")
    return value


def _held_id(text: str) -> int:
    if not text.isascii() or not text.isdigit() or len(text) > 18:
        raise HttpError(400, f"a held frame's id is a number, got {text[:20]!r}")
    return int(text)


Handler = Callable[[Controller, Request, tuple[str, ...]], tuple[int, Any]]


def _state(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, c.state()


def _connections(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, {"connections": c.connections()}


def _faults(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, {"faults": [f.as_dict() for f in c.faults]}


def _add_fault(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    body = r.json()
    return 201, c.add_fault(field(body, "spec", str), field(body, "name", str, "")).as_dict()


def _remove_fault(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, c.remove_fault(a[0]).as_dict()


def _enable_fault(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, c.enable_fault(a[0], field(r.json(), "enabled", bool)).as_dict()


def _intercept(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, {"filter": c.intercept.text}


def _set_intercept(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    c.set_intercept(field(r.json(), "filter", str))
    return 200, {"filter": c.intercept.text}


def _held(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, {"held": c.held_frames()}


def _release(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    body = r.json()
    return 200, c.release(_held_id(a[0]), field(body, "edit", str, None), field(body, "force", bool, False))


def _drop(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, c.drop(_held_id(a[0]))


def _release_all(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    return 200, {"released": c.release_all()}


def _inject(c: Controller, r: Request, a: tuple[str, ...]) -> tuple[int, Any]:
    body = r.json()
    conn, direction = field(body, "conn", int), field(body, "dir", str)
    data = c.inject(conn, direction, field(body, "frame", str), field(body, "force", bool, False))
    return 200, {"conn": conn, "dir": direction, "frame": escape(data)}


# (method, path pattern, handler); a {name} part is one path segment, percent-decoded.
ROUTES: list[tuple[str, re.Pattern[str], Handler]] = [
    (method, re.compile("^" + re.sub(r"\{\w+\}", "([^/]+)", path) + "$"), handler)
    for method, path, handler in [
        ("GET", "/state", _state),
        ("GET", "/connections", _connections),
        ("GET", "/faults", _faults),
        ("POST", "/faults", _add_fault),
        ("DELETE", "/faults/{key}", _remove_fault),
        ("POST", "/faults/{key}/enable", _enable_fault),
        ("GET", "/intercept", _intercept),
        ("PUT", "/intercept", _set_intercept),
        ("GET", "/held", _held),
        ("POST", "/held/release-all", _release_all),
        ("POST", "/held/{id}/release", _release),
        ("POST", "/held/{id}/drop", _drop),
        ("POST", "/inject", _inject),
    ]
]


def route(method: str, path: str) -> tuple[Handler, tuple[str, ...]]:
    """The handler for ``method path`` and its path arguments; 404 or 405 if none."""
    allowed: list[str] = []
    for want, pattern, handler in ROUTES:
        m = pattern.match(path)
        if m is None:
            continue
        if want == method:
            return handler, tuple(unquote(g) for g in m.groups())
        allowed.append(want)
    if allowed:
        raise HttpError(405, f"{path} takes {', '.join(allowed)}, not {method}", tuple(allowed))
    raise HttpError(404, f"no such endpoint: {path}")


def answer(controller: Controller, request: Request) -> tuple[int, Any, tuple[str, ...]]:
    """Status, JSON body and Allow header for one request; never raises (a
    bug in a handler is a 500 and a report, the proxy goes on)."""
    try:
        handler, args = route(request.method, request.path)
        status, payload = handler(controller, request, args)
        return status, payload, ()
    except HttpError as e:
        return e.status, {"error": str(e)}, e.allow
    except ControlError as e:  # the controller's one-line refusals, with their status
        return e.status, {"error": str(e)}, ()
    except ValueError as e:  # FaultSpecError and the like: a request that does not parse
        return 400, {"error": str(e)}, ()
    except Exception as e:  # noqa: BLE001 - a bug here must not reach the proxy's loop
        controller.report(f"control API: {request.method} {request.path}: {type(e).__name__}: {e}")
        return 500, {"error": f"internal error: {type(e).__name__}: {e}"}, ()


async def read_request(reader: asyncio.StreamReader) -> Request | None:
    """One request: its line, headers and Content-Length body; None if the
    client closed before sending anything.  _Malformed if it is not HTTP;
    HttpError for a body that is too big or not sized."""
    line = await _line(reader)
    if not line:
        return None
    parts = line.split(" ")
    if len(parts) != 3 or not parts[0].isalpha() or not parts[1].startswith("/") or \
            not parts[2].startswith("HTTP/1."):
        raise _Malformed(f"malformed request line {line[:60]!r}")
    headers = await _headers(reader)
    if "transfer-encoding" in headers:
        raise HttpError(411, "send the body with a Content-Length (chunked bodies are not taken)")
    length_text = headers.get("content-length", "0")
    if not length_text.isdigit():
        raise HttpError(400, f"Content-Length is not a number: {length_text[:20]!r}")
    length = int(length_text)
    if length > MAX_BODY:
        raise HttpError(413, f"the body is {length} bytes; at most {MAX_BODY} are taken")
    try:
        body = await reader.readexactly(length)
    except asyncio.IncompleteReadError as e:
        raise _Malformed(f"the body ended after {len(e.partial)} of its {length} bytes") from None
    return Request(parts[0].upper(), urlsplit(parts[1]).path, body)


async def _line(reader: asyncio.StreamReader) -> str:
    try:
        raw = await reader.readuntil(b"\n")
    except asyncio.IncompleteReadError as e:
        if e.partial:
            raise _Malformed("the request ended mid-line") from None
        return ""
    except asyncio.LimitOverrunError:
        raise _Malformed(f"a line over {MAX_LINE} bytes") from None
    return raw.decode("latin-1").rstrip("\r\n")


async def _headers(reader: asyncio.StreamReader) -> dict[str, str]:
    headers: dict[str, str] = {}
    for _ in range(MAX_HEADERS):
        line = await _line(reader)
        if not line:
            return headers
        name, sep, value = line.partition(":")
        if not sep or not name.strip():
            raise _Malformed(f"malformed header line {line[:60]!r}")
        headers[name.strip().lower()] = value.strip()
    raise _Malformed(f"more than {MAX_HEADERS} header lines")


def response(status: int, payload: Any, allow: tuple[str, ...] = ()) -> bytes:
    body = json.dumps(payload).encode() + b"\n"
    head = [f"HTTP/1.1 {status} {REASONS.get(status, 'Error')}", "Content-Type: application/json",
            f"Content-Length: {len(body)}", "Connection: close"]
    if allow:
        head.append(f"Allow: {', '.join(allow)}")
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body


class ControlServer:
    """The control API on ``host:port`` (port 0 picks one; ``url`` says which)."""

    def __init__(self, controller: Controller, host: str = "127.0.0.1", port: int = 0) -> None:
        self.controller = controller
        self.host = host
        self.port = port
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task] = set()

    @property
    def url(self) -> str:
        return f"http://{show_address(self.host, self.port)}"

    async def start(self) -> None:
        """Listen (OSError if the address cannot be bound)."""
        self._server = await asyncio.start_server(self._serve, self.host, self.port, limit=MAX_LINE)
        self.port = self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        """Stop listening and end the connections still open."""
        if self._server is None:
            return
        self._server.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._server.wait_closed()
        self._server = None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        try:
            await self._one(reader, writer)
        except (ConnectionError, OSError, asyncio.IncompleteReadError, TimeoutError):
            pass  # that client's loss only
        finally:
            if task is not None:
                self._tasks.discard(task)
            writer.close()

    async def _one(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read one request, answer it, close."""
        allow: tuple[str, ...] = ()
        try:
            request = await asyncio.wait_for(read_request(reader), CLIENT_TIMEOUT_S)
            if request is None:
                return
            status, payload, allow = answer(self.controller, request)
        except TimeoutError:
            status, payload = 408, {"error": f"no complete request within {CLIENT_TIMEOUT_S:g} s"}
        except _Malformed as e:
            status, payload = 400, {"error": str(e)}
        except HttpError as e:
            status, payload = e.status, {"error": str(e)}
        writer.write(response(status, payload, allow))
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(writer.drain(), CLIENT_TIMEOUT_S)
