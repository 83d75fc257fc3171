"""The replayed session written as a recording (``--output``), from the replay's traffic events.

A replay is a producer of traffic events like the proxy: what it wrote and
what the server answered, on the clock a recording uses.  With no output
asked for, the events go nowhere.  A write that fails stops the replay
(``on_error``) and the run ends with its message.

With faults the replay goes through a proxy in the middle
(``whiztap.sniffer.replay.faults``), and it is the proxy's events that are
recorded (``record``), on the proxy's clock, as ``whiztap record --fault``
would have: what the target sent, what each side was delivered, and each
intervention; the replay's own view (``receive``) would only repeat the
client's half of it, without the faults.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable

from whiztap.analyzer.traffic import TrafficEvent
from whiztap.sniffer.record.metadata import base_metadata
from whiztap.sniffer.nettext import show_address
from whiztap.sniffer.record.proxy import Clock
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError
from whiztap.sniffer.replay.faults import middle_metadata
from whiztap.sniffer.replay.options import ReplayError, ReplayOptions

TICK_S = 0.2  # how often the output recording is flushed


class OutputRecording:
    """The output recording of one replay (inactive when ``options.output`` is None)."""

    def __init__(self, options: ReplayOptions, replay_of: str, on_error: Callable[[], None]) -> None:
        self.options = options
        self.replay_of = replay_of
        self.clock: Callable[[], int] = Clock()  # the time of the recorded events (the proxy's, with faults)
        self.proxied = bool(options.faults)  # the proxy's events are recorded, not the replay's
        self._on_error = on_error
        self._recorder: Recorder | None = None
        self._error: str | None = None

    def open(self, path: str) -> None:
        """Begin the recording into ``path`` (``options.output``)."""
        options = self.options
        start = self.clock()
        target = show_address(*options.address)
        middle = middle_metadata(options) if self.proxied else {}
        metadata = base_metadata("replay", False, options.checksum_rule, start, None, replay_of=self.replay_of,
                                 target=target, pace=str(options.pace), rate=options.rate, **middle)
        recorder = Recorder(RecordingFile(path, metadata),
                            checksum_rule=options.checksum_rule)
        try:
            recorder.start(start, detail=f"replay of {self.replay_of} against {target}")
        except RecordingWriteError as e:
            raise ReplayError(str(e)) from None
        self._recorder = recorder

    def receive(self, event: TrafficEvent) -> None:
        """A traffic event of the replay itself: written, unless the proxy's are."""
        if not self.proxied:
            self.record(event)

    def record(self, event: TrafficEvent) -> None:
        """Write a traffic event (nothing when there is no output)."""
        recorder = self._recorder
        if recorder is None:
            return
        try:
            recorder.receive(event)
        except RecordingWriteError as e:
            self._failed(e)

    async def tick(self) -> None:
        """Flush the output recording now and then, as the recorder expects."""
        while self._recorder is not None:
            await asyncio.sleep(TICK_S)
            try:
                self._recorder.tick(self.clock())
            except RecordingWriteError as e:
                self._failed(e)

    def _failed(self, e: RecordingWriteError) -> None:
        self._recorder = None
        self._error = str(e)
        self._on_error()

    def close(self, discard_if_empty: bool = False) -> None:
        """Finish the output recording.  A replay that failed before any
        connection (the target unreachable) leaves no file: an empty recording
        would only make the next try refuse to overwrite it."""
        error = self._error
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            try:
                summary = recorder.stop(self.clock(), "replay finished")
            except RecordingWriteError as e:
                error = str(e)
            else:
                if discard_if_empty and summary.connections == 0:
                    for path in summary.files:
                        with contextlib.suppress(OSError):
                            os.unlink(path)
        if error:
            raise ReplayError(error)
