"""Faults at work: a parsed SPEC (``whiztap.analyzer.mitm.spec``) applied to frames.

Counting is per connection: ``nth:1`` is the first matching frame of each
connection (``conn:`` aims at one).  A fault's clock starts when the
connection opened or when the fault was added, whichever is later; ``after:``
a time waits that long from there, ``after:`` a count lets that many matching
frames pass first, and ``for:`` ends the fault that long after it began to act.
``reset`` and ``close`` with ``after:`` a time act on a timer (no frame need
come); with ``after:N`` they act right after the Nth matching frame is
delivered; otherwise a matching frame is replaced by the connection's end.
Whatever goes wrong inside a fault, the frame passes untouched (the stage
runner in ``stages.py`` isolates each call).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

from whiztap.analyzer.mitm.spec import CONNECTION_ACTIONS, FaultSpec
from whiztap.analyzer.mitm.frame import Frame
from whiztap.analyzer.protocol.codec import checksum_offset
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action, Cause, Source

MAX_FAULTS = 256  # faults in force at once (a file of faults, --fault, the control API, the TUI)
MAX_DUP_FAULTS = 64  # dup faults in force at once: each frame they all choose goes out at most 65 times


@dataclass
class _Count:
    """One connection's view of one fault."""

    since_ns: int  # the fault's clock for this connection
    seen: int = 0  # matching frames, before after:N let them through
    matched: int = 0  # matching frames while active (nth/every count these)
    active_from_ns: int | None = None
    free_ns: dict[str, int] = field(default_factory=dict)  # bandwidth: when each direction's link is free


@dataclass
class Fault:
    """A fault in force: its SPEC, whether it is switched on, how often it acted."""

    spec: FaultSpec
    rng: random.Random
    added_ns: int
    id: int = 0  # given by the controller: 1, 2, ... in the order added
    enabled: bool = True
    hits: int = 0  # times it acted
    matched: int = 0  # frames its filter words chose (whether or not it acted on them), of every connection
    _counts: dict[int, _Count] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.spec.name or f"fault-{self.id}"

    @property
    def active(self) -> bool:
        """It may act on a frame (``Stages.idle``)."""
        return self.enabled

    @property
    def direction(self) -> Direction | None:
        """The direction it chooses frames from (None: both)."""
        direction = self.spec.select.direction
        return Direction(direction) if direction else None

    @property
    def quiet(self) -> bool:
        """It chose no frame and never acted (``quiet.py``)."""
        return not self.matched and not self.hits

    def chooses(self, direction: Direction, kind: ItemKind) -> bool:
        """It may choose a frame of ``direction`` and ``kind`` (``Stages`` offers it no other)."""
        select = self.spec.select
        return (not select.direction or select.direction == direction) and (not select.kinds or kind in select.kinds)

    @property
    def cause(self) -> Cause:
        return Cause(Source.FAULT, self.name, self.spec.text)

    @property
    def action(self) -> Action:
        return Action(self.spec.action)

    def as_dict(self) -> dict:
        return {"id": self.id, "name": self.name, "spec": self.spec.text, "action": self.spec.action,
                "enabled": self.enabled, "hits": self.hits, "matched": self.matched, "meaning": self.spec.explain()}

    def forget(self, conn: int) -> None:
        self._counts.pop(conn, None)

    def timer_ns(self, opened_ns: int) -> int | None:
        """For a connection opened at ``opened_ns``: when this fault must act
        on a timer (reset or close after a time), or None."""
        spec = self.spec
        if spec.action in CONNECTION_ACTIONS and spec.after_ns is not None:
            return max(opened_ns, self.added_ns) + spec.after_ns
        return None

    def frame(self, frame: Frame) -> None:
        """The stage hook: act on ``frame`` if the SPEC chooses it now."""
        opened_ns = frame.opened_ns
        spec = self.spec
        if not self.enabled or frame.dropped or not spec.selects(frame.conn, frame.observation):
            return
        self.matched += 1
        count = self._counts.get(frame.conn)
        if count is None:
            count = self._counts[frame.conn] = _Count(max(opened_ns, self.added_ns))
        if not self._active(count, frame.t_ns):
            return
        if spec.action in CONNECTION_ACTIONS and spec.after_frames:  # after:0 acts on the first frame
            if count.seen == spec.after_frames:  # the Nth has just passed _active: end after it
                self._hit()
                frame.end_connection(self.action, self.cause)
            return
        count.matched += 1
        if spec.nth is not None and count.matched != spec.nth:
            return
        if spec.every is not None and count.matched % spec.every:
            return
        if spec.prob is not None and self.rng.random() >= spec.prob:
            return
        self._hit()
        ACT[spec.action](self, frame)

    def _active(self, count: _Count, t_ns: int) -> bool:
        spec = self.spec
        if spec.after_ns is not None and t_ns < count.since_ns + spec.after_ns:
            return False
        if spec.after_frames:
            count.seen += 1
            if spec.action in CONNECTION_ACTIONS:
                return count.seen == spec.after_frames
            if count.seen <= spec.after_frames:
                return False
        if count.active_from_ns is None:
            count.active_from_ns = t_ns
        return spec.for_ns is None or t_ns < count.active_from_ns + spec.for_ns

    def _hit(self) -> None:
        self.hits += 1

    # -- the actions --------------------------------------------------------------------------

    def _delay(self, frame: Frame) -> None:
        spec = self.spec
        jitter = self.rng.randint(-spec.jitter_ns, spec.jitter_ns) if spec.jitter_ns else 0
        frame.delay(max(0, spec.delay_ns + jitter), self.cause)

    def _drop(self, frame: Frame) -> None:
        frame.drop(self.cause)

    def _blackhole(self, frame: Frame) -> None:
        frame.drop(self.cause, Action.BLACKHOLE)

    def _dup(self, frame: Frame) -> None:
        frame.duplicate(self.cause)

    def _corrupt(self, frame: Frame) -> None:
        if frame.data is not None:  # not dropped already
            frame.replace(corrupted(frame.data), self.cause, Action.CORRUPT)

    def _replace(self, frame: Frame) -> None:
        frame.replace(self.spec.replacement or b"", self.cause)

    def _slice(self, frame: Frame) -> None:
        low, high = self.spec.slice_sizes or (1, 1)
        frame.slice(low, high, self.spec.pause_ns, self.cause)

    def _bandwidth(self, frame: Frame) -> None:
        """A rate as small writes at a steady pace: ``rate / 100`` bytes every
        10 ms.  The link is shared by the frames of a direction: a frame starts
        once the ones before it had their time, so small frames (shorter than
        one write) are paced too rather than sent back to back at full speed."""
        rate = self.spec.rate or 1
        size = max(1, rate // 100)
        pause = max(1, size * 1_000_000_000 // rate)
        free = self._counts[frame.conn].free_ns
        start = max(frame.t_ns + frame.delay_ns, free.get(frame.direction.value, 0))
        free[frame.direction.value] = start + len(frame.data or b"") * 1_000_000_000 // rate
        frame.delay_ns = start - frame.t_ns
        frame.slice(size, size, pause, self.cause, Action.BANDWIDTH)

    def _end(self, frame: Frame) -> None:
        frame.end_connection(self.action, self.cause, instead=True)


ACT = {"delay": Fault._delay, "drop": Fault._drop, "blackhole": Fault._blackhole, "dup": Fault._dup,
       "corrupt": Fault._corrupt, "replace": Fault._replace, "slice": Fault._slice,
       "bandwidth": Fault._bandwidth, "reset": Fault._end, "close": Fault._end}


def corrupted(data: bytes) -> bytes:
    """The frame with one byte wrong and everything else intact: a Set
    Configuration's checksum byte (plus one, skipping the bytes that would
    change its framing); for any other frame, the last digit of its first
    number; for anything else, its last byte."""
    if not data:
        return data
    at = checksum_offset(data)
    if at is None:
        digits = [i for i, b in enumerate(data) if 0x30 <= b <= 0x39]
        at = next((i for i in digits if i >= 4 and (i + 1 == len(data) or not 0x30 <= data[i + 1] <= 0x39)),
                  len(data) - 1)
        if 0x30 <= data[at] <= 0x39:
            return data[:at] + bytes([0x30 + (data[at] - 0x30 + 1) % 10]) + data[at + 1:]
    value = (data[at] + 1) % 256
    while value in b"-s\r\n":
        value = (value + 1) % 256
    return data[:at] + bytes([value]) + data[at + 1:]


