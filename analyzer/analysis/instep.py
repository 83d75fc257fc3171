"""Reads held until the proxy in the middle delivers them as they were.

A connection is *in step* while the proxy delivers each read at once and as
it was: the same bytes at the same time (whole, or in pieces one after
another), before anything else is read or happens on the connection.  Both
sides then got exactly what the other sent, and one session judges the
connection for both (``sides.py``).  ``InStep`` holds one connection's reads,
of one direction at a time, until their delivery shows them, and says when
the connection goes out of step.
"""

from __future__ import annotations

from collections import deque

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Data

HELD_MAX = 1 << 20  # bytes of reads held awaiting their delivery; past that, out of step


class OutOfStep(Exception):
    """A delivery that is not the next bytes read, at their time."""


class InStep:
    """One connection's reads not yet (all) delivered, and how much of the first was."""

    __slots__ = ("reads", "at", "size")

    def __init__(self) -> None:
        self.reads: deque[Data] = deque()
        self.at = 0  # bytes of the first read delivered so far
        self.size = 0  # bytes of all the reads held

    def hold(self, read: Data) -> bool:
        """Hold a read until it is delivered; False if that would be out of
        step (the other direction's reads are still held, or too much would be)."""
        reads = self.reads
        size = self.size + len(read.data)
        if (reads and reads[0].direction is not read.direction) or size > HELD_MAX:
            return False
        reads.append(read)
        self.size = size
        return True

    def deliver(self, direction: Direction, t_ns: int, data: bytes) -> Data | None:
        """A delivery: the read it completes (no longer held), or None if the
        read is only partly delivered so far.  Raises ``OutOfStep``."""
        if not data:
            return None  # nothing delivered
        reads = self.reads
        if not reads:
            raise OutOfStep
        read = reads[0]
        if read.direction is not direction or read.t_ns != t_ns:
            raise OutOfStep
        at = self.at
        if at == 0 and data == read.data:  # the usual case: the read, whole
            reads.popleft()
            self.size -= len(data)
            return read
        if not read.data.startswith(data, at):
            raise OutOfStep
        at += len(data)
        if at < len(read.data):
            self.at = at
            return None
        reads.popleft()
        self.at = 0
        self.size -= at
        return read

    def take(self) -> tuple[list[Data], int]:
        """The reads held and how much of the first was delivered; nothing is held after."""
        reads, at = list(self.reads), self.at
        self.reads.clear()
        self.at = self.size = 0
        return reads, at
