"""Interception: frames that match a filter wait for a person.

``Intercept`` is the last stage: it marks the frames its filter (the filter
bar's words) selects.  ``HeldFrames`` keeps each held frame under an id until
it is released as it is, released edited, or dropped; one forgotten for
``timeout_s`` is released as it is, so a hold never wedges a session.  While a
frame waits, everything behind it in its direction waits too (the lane keeps
order).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

from whiztap.analyzer.analysis.item_filter import ItemFilter, parse_filter
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import Intervention
from whiztap.sniffer.mitm.frame import Frame, observe_bytes


class Intercept:
    """The stage that marks frames to hold."""

    name = "intercept"

    def __init__(self) -> None:
        self.text = ""
        self.filter: ItemFilter | None = None

    def set(self, text: str | None) -> None:
        """Hold what ``text`` selects from now on (FilterSyntaxError if it does not parse); None or "": nothing."""
        self.filter = parse_filter(text) if text else None
        self.text = text or ""

    def frame(self, frame: Frame) -> None:
        """Mark ``frame`` to hold if the filter takes it; its ``since:``/``until:``
        count from the opening of the frame's connection, as a fault's clock does."""
        if self.filter is not None and frame.data is not None and \
                self.filter.accepts(frame.conn, frame.observation, frame.opened_ns):
            frame.hold = f"intercept {self.text}"


@dataclass
class Held:
    """A frame waiting for a person."""

    id: int
    conn: int
    direction: Direction
    observation: Observation
    since_ns: int
    cause: str
    out: object  # the lane's _Out
    lane: object  # the Lane that waits on it

    @property
    def data(self) -> bytes:
        return self.out.data  # type: ignore[attr-defined]

    def as_dict(self, now_ns: int) -> dict:
        """Its state, its meaning that of the bytes it holds now (an edit's, once edited)."""
        observation = self.observation
        if self.data != observation.item.raw:
            observation = observe_bytes(self.data, self.direction, observation.index)
        return {"id": self.id, "conn": self.conn, "dir": self.direction.value, "kind": observation.item.kind.value,
                "text": escape(self.data), "meaning": meaning(observation),
                "waited_s": round((now_ns - self.since_ns) / 1e9, 3), "cause": self.cause}


class HeldFrames:
    """The frames held now, by id."""

    def __init__(self, timeout_s: float, clock: Callable[[], int], emit: Callable[[Intervention], None]) -> None:
        self.timeout_ns = int(timeout_s * 1e9)
        self.clock = clock
        self.emit = emit
        self.frames: dict[int, Held] = {}
        self._ids = itertools.count(1)

    def hold(self, lane: object, out: object, frame: Frame) -> Held:
        held = Held(next(self._ids), frame.conn, frame.direction, frame.observation, self.clock(), frame.hold or "",
                    out, lane)
        self.frames[held.id] = held
        self.emit(Intervention(frame.conn, held.since_ns, frame.direction, "hold", held.cause, frame.data or b"",
                               frame.data or b"", frame.kind.value, f"held as #{held.id}"))
        return held

    def release(self, held_id: int, data: bytes | None = None, drop: bool = False, cause: str = "hand") -> Held:
        """Let a held frame go: as it is, as ``data``, or not at all.  KeyError if there is no such frame."""
        held = self.frames.pop(held_id)
        out = held.out
        before = out.data  # type: ignore[attr-defined]
        kind = held.observation.item.kind.value
        now = self.clock()
        if drop:
            action, after = "drop", b""
        elif data is not None and data != before:
            action, after = "edit", data
        else:
            action, after = "release", before
        self.emit(Intervention(held.conn, now, held.direction, action, f"{cause} (held #{held.id})", before, after,
                               kind, ""))
        held.lane.let_go(out, after)  # type: ignore[attr-defined]
        return held

    def expire(self) -> None:
        """Release, as they are, the frames held longer than the timeout."""
        now = self.clock()
        for held in [h for h in self.frames.values() if now - h.since_ns >= self.timeout_ns]:
            self.release(held.id, cause=f"hold timeout after {self.timeout_ns / 1e9:g} s")

    def forget_conn(self, conn: int) -> None:
        """The connection is ending: its held frames go out as they are (the
        lane delivers what it holds before closing), and the recording says so."""
        for held_id in [i for i, h in self.frames.items() if h.conn == conn]:
            held = self.frames.pop(held_id)
            self.emit(Intervention(conn, self.clock(), held.direction, "release",
                                   f"connection ending (held #{held_id})", held.data, held.data,
                                   held.observation.item.kind.value, ""))
