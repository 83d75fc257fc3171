"""Faults that choose nothing: named, so a SPEC that does not say what was
meant does not go unnoticed.

A fault whose filter words fit no frame (a channel the client never uses, a
kind that never travels that way) looks like one that works but has not had
its chance yet.  ``QuietFaults`` counts the frames each direction carried
through the stages since each fault was put in force (added, or switched on),
and tells of a fault that chose none of ``QUIET_AFTER`` frames of its
direction (of both, for a fault without ``dir:``), once; and, when the proxy
stops (``ending``), of every fault in force that chose none of the frames it
saw.  A fault that acted on a timer (a reset after a time) is not quiet.

It costs a frame two additions and two comparisons, whatever the count of
faults: the count at which the next fault falls due is kept, per direction.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from whiztap.analyzer.protocol.observations import Direction

QUIET_AFTER = 1000  # frames of its direction a fault may let by, choosing none, before it is named
Quiet = Callable[[Any, int, bool], None]  # (the fault, frames of its direction it saw, at the end)


@dataclass
class _Watched:
    fault: Any  # has ``quiet`` (it chose nothing yet) and ``direction`` (None: both)
    since: int  # the count of its direction's frames when it was put in force
    told: bool = False


class QuietFaults:
    """The faults in force that chose no frame yet, and the frames that went by them."""

    def __init__(self, tell: Quiet) -> None:
        self.tell = tell
        self.counts: dict[Direction | None, int] = {Direction.C2S: 0, Direction.S2C: 0, None: 0}
        self._watched: dict[int, _Watched] = {}  # by id(fault)
        self._due: dict[Direction | None, float] = {Direction.C2S: math.inf, Direction.S2C: math.inf, None: math.inf}

    def watch(self, stages: Iterable[Any]) -> None:
        """The stages switched on now: a fault among them not watched yet is
        watched from now on; one no longer among them (removed, switched off)
        is forgotten, and starts again if it comes back."""
        watched = {}
        for stage in stages:
            if hasattr(stage, "quiet"):
                key = id(stage)
                watched[key] = self._watched.get(key) or _Watched(stage, self.counts[stage.direction])
        self._watched = watched
        self._plan()

    def carried(self, direction: Direction) -> None:
        """A frame of ``direction`` went through the stages (hot: once a frame)."""
        counts = self.counts
        counts[direction] += 1
        counts[None] += 1
        if counts[direction] >= self._due[direction] or counts[None] >= self._due[None]:
            for w in self._watched.values():
                if not w.told and w.fault.quiet and self.counts[w.fault.direction] - w.since >= QUIET_AFTER:
                    w.told = True
                    self.tell(w.fault, self.counts[w.fault.direction] - w.since, False)
            self._plan()

    def end(self) -> None:
        """The proxy stops: tell of each fault in force that saw frames and chose none."""
        for w in self._watched.values():
            seen = self.counts[w.fault.direction] - w.since
            if seen and w.fault.quiet:
                self.tell(w.fault, seen, True)

    def _plan(self) -> None:
        """When (at which count of each direction) the next watched fault falls due."""
        due = dict.fromkeys(self._due, math.inf)
        for w in self._watched.values():
            if not w.told and w.fault.quiet:
                direction = w.fault.direction
                due[direction] = min(due[direction], w.since + QUIET_AFTER)
        self._due = due
