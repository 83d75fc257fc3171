"""When each write of a replay may leave: the recorded schedule, and pause / resume / step / stop."""

from __future__ import annotations

import asyncio
import time

from whiztap.sniffer.replay.plan import NS

SPIN_NS = 2_000_000  # the last stretch before a due time is waited out without a timer


class Stopped(Exception):
    """The replay was stopped while waiting for its turn."""


class Pacer:
    """When each write may leave: the schedule, and pause / resume / step.

    The schedule maps recorded times to ``perf_counter_ns``; time spent paused
    shifts it, and a stepped write re-anchors it so the write is due now."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.paused = False
        self.stopped = False
        self._tokens = 0
        self._pause_after_next = False
        self._changed = asyncio.Event()
        self._origin = 0
        self._base = time.perf_counter_ns()
        self._paused_at = 0

    def anchor(self, origin_ns: int) -> None:
        self._origin = origin_ns
        self._base = time.perf_counter_ns()
        self._paused_at = self._base

    def due(self, t_rec: int) -> int:
        return self._base + int((t_rec - self._origin) / self.rate)

    def _notify(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    def pause(self) -> None:
        if not self.paused:
            self.paused = True
            self._paused_at = time.perf_counter_ns()
            self._notify()

    def resume(self) -> None:
        self._tokens = 0
        self._pause_after_next = False
        if self.paused:
            self.paused = False
            self._base += time.perf_counter_ns() - self._paused_at
            self._notify()

    def step(self) -> None:
        if self.paused:
            self._tokens += 1
        else:
            self._pause_after_next = True
        self._notify()

    def stop(self) -> None:
        self.stopped = True
        self._notify()

    async def changed(self, timeout: float | None = None) -> None:
        try:
            await asyncio.wait_for(self._changed.wait(), timeout)
        except TimeoutError:
            pass

    def late_by(self, t_rec: int) -> int:
        """How far now is past the time ``t_rec`` is due (0 when not yet due)."""
        return max(0, time.perf_counter_ns() - self.due(t_rec))

    async def turn(self, t_rec: int, recorded: bool, write: bool, lag_ns: int = 0) -> int | None:
        """Wait until something recorded at ``t_rec`` may happen; the due time.

        ``lag_ns`` shifts the due time (a connection whose server answered its
        handshake later than recorded keeps its gaps, not its clock times).
        Only writes take a step; opening a connection waits out a pause unless
        a step is pending (the step's write needs the connection)."""
        while True:
            if self.stopped:
                raise Stopped
            if self.paused:
                if self._tokens and not write:
                    return None
                if self._tokens:
                    self._tokens -= 1
                    now = time.perf_counter_ns()
                    self._base = now - int((t_rec - self._origin) / self.rate)
                    self._paused_at = now
                    return now if recorded else None
                await self.changed()
                continue
            if not recorded:
                self._after_write(write)
                return None
            due = self.due(t_rec) + lag_ns
            remaining = due - time.perf_counter_ns()
            if remaining > SPIN_NS:
                await self.changed((remaining - SPIN_NS) / NS)
                continue
            while time.perf_counter_ns() < due and not (self.paused or self.stopped):
                await asyncio.sleep(0)
            if self.paused or self.stopped:
                continue
            self._after_write(write)
            return due

    def _after_write(self, write: bool) -> None:
        if write and self._pause_after_next:
            self._pause_after_next = False
            self.pause()
