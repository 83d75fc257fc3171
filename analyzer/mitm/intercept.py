"""Interception: frames that match a filter wait for a person.

``Intercept`` is the last stage: it marks the frames its filter (the filter
bar's words) selects.  ``HeldFrames`` is the one table of held frames of every
connection, by id, that the control layer lists and lets go; each connection's
core (``core.py``) keeps the frame itself in its queue, so while a frame waits
everything behind it in its direction waits too.  A password is shown masked
here as everywhere (``Held.shown``) unless the run keeps secrets.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

from whiztap.analyzer.analysis.item_filter import ItemFilter, parse_filter
from whiztap.analyzer.mitm.frame import Frame, masked
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.frame_text import frame_alone
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.text import escape

REDACTED_MEANING = "a password (redacted)"


class Intercept:
    """The stage that marks frames to hold."""

    name = "intercept"

    def __init__(self) -> None:
        self.text = ""
        self.filter: ItemFilter | None = None

    @property
    def active(self) -> bool:
        return self.filter is not None

    def set(self, text: str | None) -> None:
        """Hold what ``text`` selects from now on (FilterSyntaxError if it does not parse); None or "": nothing."""
        self.filter = parse_filter(text) if text else None
        self.text = text or ""

    def frame(self, frame: Frame) -> None:
        """Mark ``frame`` to hold if the filter takes it; its ``since:``/``until:``
        count from the opening of the frame's connection, as a fault's clock does."""
        if self.filter is not None and frame.data is not None and \
                self.filter.accepts(frame.conn, frame.observation, frame.opened_ns):
            frame.hold = self.text


@dataclass
class Held:
    """A frame waiting for a person: ``data`` is what would go now (the frame
    as the stages left it); ``hidden``: it may be a password and the run hides them;
    ``cause``: why it is held, as people read it."""

    id: int
    conn: int
    direction: Direction
    index: int
    offset: int
    observation: Observation
    since_ns: int
    cause: str
    data: bytes
    secret: bool  # it may be a password
    redact: bool  # the run hides passwords

    @property
    def hidden(self) -> bool:
        return self.secret and self.redact

    @property
    def shown(self) -> bytes:
        """Its bytes as any output may show them."""
        return masked(self.data) if self.hidden else self.data

    def as_dict(self, now_ns: int) -> dict[str, Any]:
        """Its state, its meaning that of the bytes it holds now (an edit's, once edited)."""
        observation = self.observation
        if self.data != observation.item.raw and not self.hidden:
            edited, _ = frame_alone(self.data, self.direction)
            observation = edited[0] if edited else observation
        return {"id": self.id, "conn": self.conn, "dir": self.direction.value, "index": self.index,
                "kind": observation.item.kind.value, "text": escape(self.shown),
                "meaning": REDACTED_MEANING if self.hidden else meaning(observation),
                "waited_s": round((now_ns - self.since_ns) / 1e9, 3), "cause": self.cause, "redacted": self.hidden}


class HeldFrames:
    """The frames held now on every connection, by id (1, 2, ... for the run)."""

    def __init__(self) -> None:
        self.frames: dict[int, Held] = {}
        self._ids = itertools.count(1)

    def add(self, frame: Frame, since_ns: int) -> Held:
        held = Held(next(self._ids), frame.conn, frame.direction, frame.index, frame.offset, frame.observation,
                    since_ns, f"intercept {frame.hold}", frame.data or b"", frame.secret, frame.redact)
        self.frames[held.id] = held
        return held

    def get(self, held_id: int) -> Held | None:
        return self.frames.get(held_id)

    def discard(self, held: Held) -> None:
        self.frames.pop(held.id, None)
