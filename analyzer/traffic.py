"""Traffic events: what happened on the wire, in one typed shape for every part of whiztap.

Every producer of traffic (the proxy, a pcap import or live capture, the scan of
a recording, a replay) says what happened as these events, and every consumer
(the recorder, the analyzer, the TUI, replay and stub) takes them, so "a
connection opened", "bytes arrived", "one side shut down its sending half", "bytes
are missing" and "the connection ended" mean one thing everywhere.

``Data`` is a ``NamedTuple`` because there is one per TCP read and it is built
on the proxy's forwarding path: a tuple is the cheapest object Python makes.
The others are rare and are frozen dataclasses.

``to_json``/``from_json`` turn the connection events into the messages of a
recording's ``/tcp/events`` topic and back; this module is the only place their
names appear.  ``Data`` has its own message (``/tcp/reads``), encoded by
``whiztap.analyzer.recording.encode`` for speed.

``Traffic`` keeps one ``Session`` per connection and turns events into the
session's events (observations and late violations): the one table of sessions
that the analyzer, the recorder's model, replay and the TUI share.
"""

from __future__ import annotations

import base64
import re
from collections.abc import Callable
from dataclasses import dataclass, fields
from enum import StrEnum
from typing import Any, NamedTuple

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction, Event
from whiztap.analyzer.protocol.session import Session

GAP_DETAIL = "bytes missing from the capture; the session model restarts after them"


class Data(NamedTuple):
    """One read of ``data`` from one direction of connection ``conn``, at ``t_ns``.

    A read scanned from a recording also says where it was: ``offset``, its
    first byte's place in its direction's stream (a jump in it is bytes
    missing), and ``masked``, whether the recorder replaced a password in it
    by mask bytes.  Reads from the wire leave them at -1 and False: the
    recorder counts offsets and masks passwords itself."""

    conn: int
    direction: Direction
    t_ns: int
    data: bytes
    offset: int = -1
    masked: bool = False


class Delivered(NamedTuple):
    """Bytes the proxy wrote toward the receiver of ``direction`` when it stands
    in the middle (faults, interception, injection or scripts): what that side
    actually got, beside the ``Data`` its sender sent.  ``secret``: the bytes
    are (part of) a password."""

    conn: int
    direction: Direction
    t_ns: int
    data: bytes
    secret: bool = False


class Action(StrEnum):
    """What the proxy in the middle did to a frame (or a connection).  A
    ``StrEnum``: its value is the word recordings, the API and reports use."""

    DROP = "drop"
    DUP = "dup"
    DELAY = "delay"
    CORRUPT = "corrupt"
    REPLACE = "replace"
    SLICE = "slice"
    BANDWIDTH = "bandwidth"
    BLACKHOLE = "blackhole"
    RESET = "reset"
    CLOSE = "close"
    HOLD = "hold"
    RELEASE = "release"
    EDIT = "edit"
    INJECT = "inject"
    EXPIRE = "expire"  # due after its connection closed: never delivered


class Source(StrEnum):
    """Who or what made the proxy intervene."""

    FAULT = "fault"  # a fault SPEC (--fault, the API, the TUI's faults pane)
    SCRIPT = "script"  # a --script's hook
    HAND = "hand"  # a person: release, edit or drop of a held frame
    INTERCEPT = "intercept"  # the intercept filter held the frame for a person
    INJECTION = "injection"  # a frame typed into a connection
    TIMEOUT = "timeout"  # a held frame nobody let go within --hold-timeout
    CLOSING = "closing"  # the connection ended while the frame waited
    PROXY = "proxy"  # anything else (only read from old recordings)


@dataclass(frozen=True, slots=True)
class Cause:
    """Why the proxy intervened, as data: the ``source``, the fault's or
    script's ``name`` (for a hand: what it did) and the fault's SPEC ``text``
    (for a timeout: how long).  ``str()`` is the one line people read."""

    source: Source
    name: str = ""
    text: str = ""

    def __str__(self) -> str:
        source, name, text = self.source, self.name, self.text
        if source is Source.FAULT:
            return f"fault {name}: {text}"
        if source is Source.SCRIPT:
            return f"script {name}"
        if source is Source.HAND:
            return f"hand {name}" if name else "hand"
        if source is Source.INTERCEPT:
            return f"intercept {text}"
        if source is Source.TIMEOUT:
            return f"hold timeout after {text}"
        if source is Source.CLOSING:
            return "connection ending"
        return text or str(source)

    @classmethod
    def parse(cls, text: str) -> Cause:
        """The cause a format-3 recording wrote only as text (newer ones write its fields)."""
        text = _HELD_SUFFIX.sub("", text)
        if text.startswith("fault ") and ": " in text:
            name, spec = text[6:].split(": ", 1)
            return cls(Source.FAULT, name, spec)
        if text.startswith("script "):
            return cls(Source.SCRIPT, text[7:])
        if text == "hand" or text.startswith("hand "):
            return cls(Source.HAND, text[5:])
        if text == "injection":
            return cls(Source.INJECTION)
        if text.startswith("intercept "):
            return cls(Source.INTERCEPT, text=text[10:])
        if text.startswith("hold timeout after "):
            return cls(Source.TIMEOUT, text=text[19:])
        if text == "connection ending":
            return cls(Source.CLOSING)
        return cls(Source.PROXY, text=text)


_HELD_SUFFIX = re.compile(r" \(held #\d+\)$")


@dataclass(frozen=True, slots=True)
class Intervention:
    """The proxy changed the traffic: ``action`` on a frame of ``direction``,
    because of ``cause``, turning ``before`` into ``after`` (each ``b""``
    where there is none).  ``kind`` is the frame's framer kind; ``index`` the
    frame's number among the frames its sender sent in that direction (-1: no
    sent frame, an injection or a timer) and ``offset`` where it begins in
    the sender's stream; ``delivered`` where it begins in the stream the
    receiver got (-1: not delivered: dropped, expired, or the intervention
    is not about one frame); ``held`` the held frame's id (0: none).  An
    intervention on a frame that is delivered is told when it is delivered,
    so ``delivered`` is known; one on a frame that is not, when decided.
    ``secret``: the frame is (part of) a password; its bytes here are
    already masked unless the run keeps secrets, and every output that shows
    them says ``<redacted>`` unless it keeps secrets."""

    conn: int
    t_ns: int
    direction: Direction
    action: Action
    cause: Cause
    before: bytes = b""
    after: bytes = b""
    kind: str = ""
    detail: str = ""
    index: int = -1
    held: int = 0
    secret: bool = False
    offset: int = -1
    delivered: int = -1


@dataclass(frozen=True, slots=True)
class RecordingStarted:
    """A recording began (connection 0); ``detail`` says where its traffic comes from."""

    t_ns: int
    detail: str = ""
    conn: int = 0


@dataclass(frozen=True, slots=True)
class Opened:
    """A client connected (to the proxy, or as a capture first saw it)."""

    conn: int
    t_ns: int
    client: str = ""
    upstream: str = ""


@dataclass(frozen=True, slots=True)
class Continued:
    """A connection already open when this part of a split recording began;
    its streams continue at the offsets given."""

    conn: int
    t_ns: int
    client: str = ""
    upstream: str = ""
    c2s_offset: int = 0
    s2c_offset: int = 0
    detail: str = ""


@dataclass(frozen=True, slots=True)
class UpstreamConnected:
    """The proxy reached the server for this connection."""

    conn: int
    t_ns: int
    detail: str = ""


@dataclass(frozen=True, slots=True)
class UpstreamFailed:
    """The proxy could not reach the server: the server side will never speak."""

    conn: int
    t_ns: int
    detail: str = ""


@dataclass(frozen=True, slots=True)
class HalfClosed:
    """The sender of ``direction`` shut down its sending half (TCP FIN)."""

    conn: int
    t_ns: int
    direction: Direction


@dataclass(frozen=True, slots=True)
class Gap:
    """``length`` bytes of ``direction`` (from ``offset`` when known) are not in
    the traffic: a capture missed them, the proxy left them out, or a part of a
    split recording is missing."""

    conn: int
    t_ns: int
    direction: Direction
    length: int | None = None
    offset: int | None = None
    detail: str = GAP_DETAIL


@dataclass(frozen=True, slots=True)
class Closed:
    """The connection ended; ``by`` is "client", "server" or "recorder".  A
    recording adds what its model made of it (bytes, mode, handshake)."""

    conn: int
    t_ns: int
    by: str = ""
    detail: str = ""
    c2s_bytes: int | None = None
    s2c_bytes: int | None = None
    mode: str | None = None
    handshake: str | None = None


@dataclass(frozen=True, slots=True)
class RecordingStopped:
    """The recording ended (connection 0)."""

    t_ns: int
    by: str = ""
    detail: str = ""
    conn: int = 0


ConnectionEvent = (RecordingStarted | Opened | Continued | UpstreamConnected | UpstreamFailed | HalfClosed
                   | Gap | Closed | RecordingStopped)
TrafficEvent = Data | Delivered | Intervention | ConnectionEvent

NAMES: dict[type[ConnectionEvent], str] = {
    RecordingStarted: "recording_started",
    Opened: "opened",
    UpstreamConnected: "upstream_connected",
    UpstreamFailed: "upstream_failed",
    HalfClosed: "half_closed",
    Closed: "closed",
    Gap: "gap",
    Continued: "continued",
    RecordingStopped: "recording_stopped",
}
"""The ``event`` field of each connection event on ``/tcp/events`` (the recording
format's enum takes its values from here, in this order)."""

_BY_NAME = {name: cls for cls, name in NAMES.items()}
_FIELDS = {cls: tuple(f.name for f in fields(cls)) for cls in NAMES}
_FIELDS[Gap] = ("conn", "t_ns", "direction", "offset", "length", "detail")  # a gap's offset comes first in a recording


class TrafficError(WhiztapError, ValueError):
    """A ``/tcp/events`` message that is not a traffic event whiztap knows."""


def to_json(event: ConnectionEvent) -> dict[str, Any]:
    """The ``/tcp/events`` message of ``event``: ``conn``, ``event``, ``t_ns``,
    then the fields it has, in the order recordings have always had them (a
    direction as ``dir``; empty optional ones left out).  A half-close and an
    upstream that failed also say who closed (``by``), for people reading the file."""
    kind = type(event)
    message: dict[str, Any] = {"conn": event.conn, "event": NAMES[kind], "t_ns": event.t_ns}
    if isinstance(event, HalfClosed):
        message["by"] = event.direction.sender
    elif kind is UpstreamFailed:
        message["by"] = "server"
    for key in _FIELDS[kind]:
        value = getattr(event, key)
        if key in ("conn", "t_ns") or value is None:
            continue
        if key == "direction":
            message["dir"] = value.value
        else:
            message[key] = value
    return message


def from_json(message: dict[str, Any]) -> ConnectionEvent:
    """The event of a ``/tcp/events`` message; fields it does not know are left
    out (a newer writer may add some).  Raises ``TrafficError``."""
    name = message.get("event")
    cls = _BY_NAME.get(name) if isinstance(name, str) else None
    if cls is None:
        raise TrafficError(f"unknown connection event {message.get('event')!r}")
    values: dict[str, Any] = {}
    for key in _FIELDS[cls]:
        if key == "direction":
            try:
                values[key] = Direction(message["dir"])
            except (KeyError, ValueError):
                raise TrafficError(f"a {NAMES[cls]} event without a direction") from None
        elif key in message:
            values[key] = message[key]
    try:
        return cls(**values)
    except TypeError:
        raise TrafficError(f"a {NAMES[cls]} event without its connection or time") from None


def intervention_to_json(event: Intervention) -> dict[str, Any]:
    """An intervention's fields besides its connection, direction and time,
    bytes as base64: how the proxy hands it to the writer process.  (The
    recording's /interventions message, text for people, is ``encode``'s.)"""
    cause = event.cause
    return {"action": event.action.value, "source": cause.source.value, "name": cause.name, "text": cause.text,
            "kind": event.kind, "detail": event.detail, "index": event.index, "held": event.held,
            "secret": event.secret, "offset": event.offset, "delivered": event.delivered,
            "before": base64.b64encode(event.before).decode(), "after": base64.b64encode(event.after).decode()}


def intervention_from_json(conn: int, direction: Direction, t_ns: int, f: dict[str, Any]) -> Intervention:
    return Intervention(conn, t_ns, direction, Action(f["action"]), Cause(Source(f["source"]), f["name"], f["text"]),
                        base64.b64decode(f["before"]), base64.b64decode(f["after"]), f["kind"], f["detail"],
                        f["index"], f["held"], f["secret"], f["offset"], f["delivered"])


SessionEnded = Callable[[int, Session], None]


class Traffic:
    """One ``Session`` per connection, fed by traffic events.

    ``receive(event)`` returns what the session made of it.  A session begins
    with the first bytes of its connection and ends when the connection closes,
    when a gap cuts its streams (what follows cannot be framed with what came
    before: each side of a gap is judged on its own), or at ``finish()``;
    ``on_end(conn, session)`` is told each time, after the session's last events
    are returned, so a consumer can add up what the session counted."""

    def __init__(self, new_session: Callable[[], Session], on_end: SessionEnded | None = None) -> None:
        self.sessions: dict[int, Session] = {}
        self._new_session = new_session
        self._on_end = on_end

    def session(self, conn: int) -> Session:
        """The connection's session, begun now if it has none."""
        session = self.sessions.get(conn)
        if session is None:
            session = self.sessions[conn] = self._new_session()
        return session

    def receive(self, event: TrafficEvent) -> list[Event]:
        if type(event) is Data:
            session = self.sessions.get(event.conn) or self.session(event.conn)
            return session.receive(event.direction, event.data, event.t_ns)
        kind = type(event)
        known = self.sessions.get(event.conn)
        if known is None:
            return []
        if type(event) is HalfClosed:
            return known.end(event.direction, event.t_ns)
        if type(event) is UpstreamFailed:
            known.server_unreachable(event.detail)
            return []
        if kind is Closed or kind is Gap:
            return self.end(event.conn, event.t_ns)
        return []

    def end(self, conn: int, t_ns: int) -> list[Event]:
        """End the connection's session now (if it has one); its last events."""
        session = self.sessions.pop(conn, None)
        if session is None:
            return []
        events = session.close(t_ns)
        if self._on_end is not None:
            self._on_end(conn, session)
        return events

    def finish(self) -> list[tuple[int, list[Event]]]:
        """End every session still open (traffic cut short), each at its last
        time; the last events per connection."""
        return [(conn, self.end(conn, self.sessions[conn].last_t_ns or 0)) for conn in list(self.sessions)]
