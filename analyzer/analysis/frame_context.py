"""The frames around each listed violation, for the HTML report's frame view.

The analysis keeps no frames (its memory does not grow with the recording),
so the report reads the recordings that have listed violations once more,
through the same session ``cat`` uses, and keeps for each violation the
``AROUND`` items before and after it on its connection, decoded.  Memory:
at most ``2 * AROUND + 1`` items per listed violation, shared where windows
overlap.

A violation is found by its connection and the item's position in the
session (``ViolationRecord.index``) with the same bytes; an intervention's
effect at its position whatever its bytes (the proxy may have changed them:
the view shows what the sender sent).  With the proxy in
the middle a violation may have been judged by one side's session, whose
positions differ: it is then found by its bytes and direction, the first such
item at or after the time it was judged minus ``SLACK_NS``.  A violation not
found (a recording changed since) has no frames; the report says so.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from whiztap.analyzer.analysis.facts import NS, RAW_KEPT, ViolationRecord
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.text import escape

if TYPE_CHECKING:
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.traffic import TrafficEvent

AROUND = 3  # items shown before and after the violating one
TEXT_SHOWN = 240  # characters of an item's escaped bytes in the frame view
HEX_SHOWN = 64  # bytes of an item shown in hex
SLACK_NS = 5 * NS


@dataclass(frozen=True, slots=True)
class FrameRow:
    """One item as the frame view shows it."""

    index: int  # position in its connection's session
    t_ns: int
    direction: str
    kind: str
    text: str  # escaped bytes, cut at TEXT_SHOWN
    hex: str  # the first HEX_SHOWN bytes
    size: int
    meaning: str
    section: str  # the spec section of its message
    rules: tuple[str, ...]  # rules it broke, as the session judged it here


@dataclass
class ConnectionFrames:
    """The items kept for one connection: those around its listed violations."""

    rows: dict[int, FrameRow] = field(default_factory=dict)  # by index
    hits: dict[int, int] = field(default_factory=dict)  # violation number -> index of its item


Key = tuple[str, int]  # (file, conn)


def row_of(obs: Observation) -> FrameRow:
    """An observation as a frame row: what it means, its bytes, its spec section."""
    item = obs.item
    raw = item.raw
    text = escape(raw[:TEXT_SHOWN * 2])
    if len(text) > TEXT_SHOWN or len(raw) > TEXT_SHOWN * 2:
        text = text[:TEXT_SHOWN] + "…"
    message = obs.message
    section = message.title if message is not None else ""
    return FrameRow(obs.index, item.t_end_ns, str(obs.direction), str(item.kind), text, raw[:HEX_SHOWN].hex(" "),
                    len(raw), meaning(obs), section, tuple(v.rule_id for v in obs.violations))


class _Finder:
    """Walks one connection's items, keeping the windows around its violations."""

    def __init__(self, wanted: list[tuple[int, ViolationRecord]], out: ConnectionFrames) -> None:
        self.by_index: dict[int, list[tuple[int, ViolationRecord]]] = {}
        for number, v in wanted:
            self.by_index.setdefault(v.index, []).append((number, v))
        self.loose: list[tuple[int, ViolationRecord]] = []  # not at their index: found by bytes
        self.recent: deque[Observation] = deque(maxlen=AROUND)
        self.after = 0  # items still to keep after the last hit
        self.out = out

    def take(self, obs: Observation) -> None:
        hit = False
        for number, v in self.by_index.pop(obs.index, ()):
            same_place = str(obs.direction) == v.direction
            if same_place and (obs.item.raw[:RAW_KEPT] == v.raw or v.cause):
                self.out.hits[number] = obs.index
                hit = True
            else:
                self.loose.append((number, v))
        if self.loose:
            hit = self._loose(obs) or hit
        if hit:
            for before in self.recent:
                self.out.rows.setdefault(before.index, row_of(before))
            self.out.rows[obs.index] = row_of(obs)
            self.after = AROUND
        elif self.after:
            self.out.rows.setdefault(obs.index, row_of(obs))
            self.after -= 1
        self.recent.append(obs)

    def _loose(self, obs: Observation) -> bool:
        raw, direction, t = obs.item.raw[:RAW_KEPT], str(obs.direction), obs.item.t_end_ns
        found = [(n, v) for n, v in self.loose if v.raw == raw and v.direction == direction and t >= v.t_ns - SLACK_NS]
        for number, v in found:
            self.out.hits[number] = obs.index
            self.loose.remove((number, v))
        return bool(found)


def frames_around(file: str, events: Iterable[TrafficEvent], violations: list[tuple[int, ViolationRecord]],
                  checksum_rule: str, limits: Limits) -> dict[int, ConnectionFrames]:
    """For one recording (its ``events``, named ``file`` as in the analysis),
    the frames around ``violations`` ((number, record) pairs, those of this
    file), by connection."""
    from whiztap.analyzer.analysis.analyzer import Analyzer

    by_conn: dict[int, list[tuple[int, ViolationRecord]]] = {}
    for number, v in violations:
        by_conn.setdefault(v.conn, []).append((number, v))
    out = {conn: ConnectionFrames() for conn in by_conn}
    finders = {conn: _Finder(wanted, out[conn]) for conn, wanted in by_conn.items()}
    analyzer = Analyzer(file, checksum_rule, limits)

    def walk(conn: int, found: list) -> None:
        finder = finders.get(conn)
        if finder is not None:
            for e in found:
                if isinstance(e, Observation):
                    finder.take(e)

    for event in events:
        walk(event.conn, analyzer.receive(event))
    for conn, found in analyzer.close_all():
        walk(conn, found)
    return out


Views = dict[Key, ConnectionFrames]
Hits = dict[int, tuple[Key, int]]  # violation number -> ((file, conn), the item's index there)


def collect(listed: list[ViolationRecord], scan: Callable[[str], Iterable[TrafficEvent]], checksum_rule: str,
            limits: Limits) -> tuple[Views, Hits]:
    """The frames around each of ``listed`` (numbered in its order, the
    report's), reading each file that has one with ``scan(file)``."""
    by_file: dict[str, list[tuple[int, ViolationRecord]]] = {}
    for number, v in enumerate(listed):
        by_file.setdefault(v.file, []).append((number, v))
    views: Views = {}
    hits: Hits = {}
    for file, wanted in by_file.items():
        for conn, frames in frames_around(file, scan(file), wanted, checksum_rule, limits).items():
            views[(file, conn)] = frames
            hits.update({number: ((file, conn), index) for number, index in frames.hits.items()})
    return views, hits


def read_frames(path: str) -> dict[int, list[FrameRow]]:
    """Every connection's items in a recording, decoded and judged by the
    analyzer's session, by connection number."""
    from whiztap.analyzer.protocol.session import Session
    from whiztap.analyzer.recording.sets import find_one, scan_set
    from whiztap.analyzer.traffic import Traffic

    traffic = Traffic(Session)
    frames: dict[int, list[FrameRow]] = {}

    def add(conn: int, events: list) -> None:
        for event in events:
            if isinstance(event, Observation):
                frames.setdefault(conn, []).append(row_of(event))

    for event in scan_set(find_one([path])):
        add(event.conn, traffic.receive(event))
    for conn, events in traffic.finish():
        add(conn, events)
    return frames
