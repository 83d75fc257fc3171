"""The control API of the proxy in the middle: what each request does, in
the manner of toxiproxy's JSON API, which ``whiztap ctl`` (and curl) drive.
The transport, and who may send a request at all, are ``control_server``'s
and ``control_guard``'s (docs/faults.md, "Reaching the control API").

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
would queue more than the lane may hold toward a side that is not reading;
405 for a method the path does not take.

A body is parsed by orjson (never Python's recursive parser, which a body
nested a few thousand deep turns into a RecursionError) and may nest at most
``MAX_DEPTH`` levels: the API's bodies are flat objects, and a deeper value
could not even be quoted back in an error message.  A number past 64 bits
comes out as a float, which no field takes.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote

import orjson

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.mitm.controller import ControlError, Controller

MAX_DEPTH = 8  # levels of arrays and objects in a body
MAX_ID_DIGITS = 18  # a held frame's id in a path: more is no id, and int() of thousands of digits raises


class HttpError(WhiztapError):
    """A request answered with an error ``status`` and ``{"error": message}``
    (``allow``: the methods the path takes, for a 405's Allow header)."""

    def __init__(self, status: int, message: str, allow: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.status = status
        self.allow = allow


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
            value = orjson.loads(self.body)
        except orjson.JSONDecodeError as e:
            raise HttpError(400, f"the body is not JSON: {e}") from None
        if not isinstance(value, dict):
            raise HttpError(400, "the body must be a JSON object")
        if depth(value) > MAX_DEPTH:
            raise HttpError(400, f"the body nests deeper than {MAX_DEPTH} levels of arrays and objects")
        return value


def depth(value: Any) -> int:
    """How deep arrays and objects nest in ``value`` (a scalar is 0), walked
    without recursion: orjson lets 1,024 levels through."""
    deepest = 0
    stack = [(value, 1)]
    while stack:
        item, level = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is None:
            continue
        deepest = max(deepest, level)
        stack.extend((child, level + 1) for child in children)
    return deepest


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
    if not text.isascii() or not text.isdigit() or len(text) > MAX_ID_DIGITS:
        raise HttpError(400, f"a held frame's id is a number of at most {MAX_ID_DIGITS} digits, got {text[:20]!r}")
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
    except Exception as e:  # a bug here must not reach the proxy's loop
        controller.report(f"control API: {request.method} {request.path}: {type(e).__name__}: {e}")
        return 500, {"error": f"internal error: {type(e).__name__}: {e}"}, ()
