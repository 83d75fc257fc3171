"""A replay (``whiztap.sniffer.replay.engine``) on its own event loop, in a worker thread.

The screen must never wait on the target, and the replay engine paces writes
by spinning its loop for the last couple of milliseconds before each one, so
it gets a loop of its own: ``run()`` is the worker thread's body, control
calls go to that loop with ``call_soon_threadsafe`` (as the engine's docstring
prescribes), and the engine's events land in plain lists the screen reads on
its timer.

With ``faults_from_recording`` the faults the recording was made under
(``whiztap.sniffer.replay.faults.recorded_faults``, its seed too) replace the
options' faults, read here in the worker thread: finding those added at run
time means reading the whole file.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import replace

from whiztap.analyzer.analysis.exchanges import RecordedSessions
from whiztap.analyzer.recording.scan import RecordingError
from whiztap.sniffer.replay.engine import Replay
from whiztap.sniffer.replay.events import (
    ConnectionOpened,
    Event,
    Finished,
    ReplayResult,
    RequestSent,
    ResponseCompared,
)
from whiztap.sniffer.replay.options import ReplayError, ReplayOptions

CONTROLS = ("pause", "resume", "step", "stop")


class ReplayRunner:
    """One replay of a recording; ``state`` is loading, running, paused, finished, stopped or failed."""

    def __init__(self, path: str, options: ReplayOptions, start_paused: bool = False,
                 faults_from_recording: bool = False) -> None:
        self.path = path
        self.options = options
        self.faults_from_recording = faults_from_recording
        self.note = ""  # about the faults, for the screen
        self.comparisons: list[ResponseCompared] = []  # appended by the replay's thread only
        self.sent = 0
        self.connections = 0
        self.result: ReplayResult | None = None
        self.error: str | None = None
        self._state = "loading"
        self._lock = threading.Lock()
        self._early: list[str] = ["pause"] if start_paused else []  # controls before the engine exists
        self._loop: asyncio.AbstractEventLoop | None = None
        self._replay: Replay | None = None

    @property
    def state(self) -> str:
        replay = self._replay
        if self._state == "running" and replay is not None and replay.paused:
            return "paused"
        return self._state

    @property
    def done(self) -> bool:
        return self._state in ("finished", "stopped", "failed")

    def run(self) -> None:
        """The worker thread's body: load the recording, replay it, keep the result."""
        from whiztap.analyzer.analysis.exchanges import load_exchanges

        try:
            recording = load_exchanges(self.path)
            if self.faults_from_recording:
                self._take_recorded_faults(recording.metadata)
        except (OSError, RecordingError) as e:
            self._fail(f"{self.path}: {getattr(e, 'strerror', None) or e}")
            return
        except ReplayError as e:  # a recorded fault or seed that does not read
            self._fail(str(e))
            return
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._replay_on(loop, recording))
        finally:
            loop.close()

    def _take_recorded_faults(self, metadata: dict[str, str]) -> None:
        """Replay under the faults (and seed) the recording was made under."""
        from whiztap.sniffer.replay.faults import recorded_faults

        recorded = recorded_faults(recording_parts(self.path), metadata)
        if not recorded.faults:
            self.note = "the recording was made without faults: there are none to re-apply"
        self.options = replace(self.options, faults=recorded.faults, fault_seed=recorded.seed)

    async def _replay_on(self, loop: asyncio.AbstractEventLoop, recording: RecordedSessions) -> None:
        try:
            replay = Replay(recording, self.options, on_event=self._on_event)
            replay.check()
        except ReplayError as e:
            self._fail(e.explained({"password": "type it in Password"}))  # the screen checks Target itself
            return
        with self._lock:
            self._replay, self._loop = replay, loop
            for what in self._early:
                getattr(replay, what)()
            self._early.clear()
            self._state = "running"
        result = await replay.run()
        self.result = result
        self.error = result.error
        self._state = "failed" if result.error else "stopped" if result.stopped else "finished"

    def _fail(self, error: str) -> None:
        self.error = error
        self._state = "failed"

    def _on_event(self, event: Event) -> None:
        if isinstance(event, ResponseCompared):
            self.comparisons.append(event)
        elif isinstance(event, RequestSent):
            self.sent += 1
        elif isinstance(event, ConnectionOpened):
            self.connections += 1
        elif isinstance(event, Finished):
            self.result = event.result

    def control(self, what: str) -> None:
        """pause, resume, step or stop, from the screen's thread."""
        if what not in CONTROLS:
            raise ValueError(what)
        with self._lock:
            if self._replay is None:
                self._early.append(what)
                return
            loop, replay = self._loop, self._replay
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(getattr(replay, what))


def recording_parts(path: str) -> tuple[str, ...]:
    """The files of the recording ``path`` names (a split one's parts, in order)."""
    from whiztap.analyzer.recording.sets import RecordingInputError, find_one

    try:
        return tuple(str(p) for p in find_one((path,)).parts)
    except RecordingInputError:
        return (path,)
