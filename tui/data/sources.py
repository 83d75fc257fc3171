"""Where the TUI's traffic comes from: a recording, a growing recording, or the proxy.

Each source has ``feed(model, stop)``, which runs in a worker thread and puts
reads and connection events into the model until the traffic ends or ``stop``
is set; the screen never waits on the disk or the network.  Live sources also
have ``start()`` and ``stop()`` coroutines that run on the app's event loop,
where the proxy lives.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import shlex
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from whiztap.analyzer.errors import WhiztapError

from whiztap.analyzer.recording.redaction import Redactor
from whiztap.analyzer.recording.remote import PartFile, open_part, part_size
from whiztap.analyzer.recording.scan import made_in_the_middle
from whiztap.analyzer.recording.sets import Follower, PartError, RecordingSet, Stopped, scan_set
from whiztap.analyzer.traffic import Closed, Data, TrafficEvent
from whiztap.tui.data.model import TrafficModel

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.controller import Controller
    from whiztap.sniffer.record.record_run import Recording, RecordSettings

DRAIN_S = 0.01  # the live queue is emptied this often when it runs dry
LOADING_GC_THRESHOLD = 100_000


class SourceError(WhiztapError):
    """The traffic cannot be read; one line for the user."""


class Source(Protocol):
    live: bool  # traffic keeps coming: the frame list follows it
    redact_passwords: bool  # show passwords as '*' (recordings are redacted already)
    progress: float | None  # 0..1 while a file loads, None when not known
    note: str  # what went wrong or is worth saying once the feed ended ("" if nothing)

    @property
    def title(self) -> str: ...  # what the header says

    def feed(self, model: TrafficModel, stop: threading.Event) -> None: ...


class FileSource:
    """A finished recording (every part of a split one), read once from start to end."""

    live = False
    redact_passwords = False

    def __init__(self, recording: RecordingSet | Path | str) -> None:
        if not isinstance(recording, RecordingSet):
            recording = RecordingSet((Path(recording),))
        self.recording = recording
        self.path = str(recording.name)
        self.title = str(recording)
        self.progress: float | None = 0.0
        self.note = ""
        self._size = max(sum(part_size(p) for p in recording.parts), 1)
        self._done = 0

    def feed(self, model: TrafficModel, stop: threading.Event) -> None:
        # Loading makes millions of short-lived tuples; the collector's default
        # threshold would run it every 700 of them (see whiztap.analyzer.analysis.throughput).
        threshold = gc.get_threshold()
        gc.set_threshold(LOADING_GC_THRESHOLD, *threshold[1:])
        try:
            self._read(model, stop)
        finally:
            gc.set_threshold(*threshold)

    def _read(self, model: TrafficModel, stop: threading.Event) -> None:
        if made_in_the_middle(str(self.recording.name)):
            model.in_the_middle(self.redact_passwords)
        receive = model.receive
        try:
            for event in scan_set(self.recording, lambda p: _Counting(open_part(p), self, stop)):
                receive(event)
        except Stopped:
            return
        except PartError as e:
            if e.truncated:
                self.note = (f"{e.path} is truncated (no footer): showing what was complete; "
                             f"to make a complete copy: whiztap recover {shlex.quote(str(e.path))}")
            else:
                self.note = f"{e}; showing what came before"
        self.progress = 1.0
        model.finish()

    def advance(self, n: int) -> None:
        self._done += n
        self.progress = min(self._done / self._size, 1.0)


class _Counting:
    """A file whose reads advance the source's progress and notice a stop."""

    def __init__(self, f: PartFile, source: FileSource, stop: threading.Event) -> None:
        self.f, self.source, self.stop = f, source, stop

    def __enter__(self) -> _Counting:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.f.close()

    def read(self, n: int = -1) -> bytes:
        if self.stop.is_set():
            raise Stopped
        data = self.f.read(n)
        self.source.advance(len(data))
        return data


class FollowSource:
    """A ``.mcap.part`` that a separate ``whiztap record`` is writing, and, when
    that recording is split (``--split-size``/``--split-duration``), each part
    after it as the recorder starts it: the analyzer's ``Follower`` reads them,
    the header says which part it is at."""

    live = True
    progress: float | None = None
    redact_passwords = False

    def __init__(self, path: str) -> None:
        self.path = path
        self.note = ""
        self._follower: Follower | None = None
        self._finished = ""

    @property
    def title(self) -> str:
        follower = self._follower
        if self._finished:
            return self._finished
        if follower is not None and follower.waiting_for is not None:
            return f"waiting for {follower.waiting_for}.part"
        return f"following {self.path if follower is None else follower.path}"

    def feed(self, model: TrafficModel, stop: threading.Event) -> None:
        def on_part(path: str) -> None:
            if model.middle is None and made_in_the_middle(path):
                model.in_the_middle(self.redact_passwords)

        follower = self._follower = Follower(self.path, stop, on_part)
        receive = model.receive
        try:
            for event in follower:
                receive(event)
        except Stopped:
            return
        except PartError as e:
            self.note = str(e)
            return
        self._finished = f"followed {follower.path.removesuffix('.part')}: the recorder finished it"
        model.finish()


# -- live -----------------------------------------------------------------------------------


class Tap:
    """The TUI's consumer of the proxy's traffic events: a copy of each goes on
    a queue.  Called on the proxy's forwarding path, so it only appends; the
    bytes on the queue are as sent, and ``LiveSource`` masks them by the
    recorder's rule before the model sees them."""

    def __init__(self, queue: deque, warn: Callable[[str], None] | None = None) -> None:
        self.receive = queue.append
        # what the proxy has to say while it runs (a script that raised): to the
        # screen, never to stderr, which would write over it
        self.warn = warn or (lambda text: None)


class Rig(Protocol):
    """What runs the proxy: ``start(tap)`` returns the running Recording, with
    ``tap`` among its consumers before any client is accepted."""

    output: str

    async def start(self, tap: Tap) -> Recording: ...
    async def stop(self) -> dict | None: ...  # the writer's summary, if it finished


class ProxyRig:
    """The recording proxy alone, in front of an upstream server, always in
    the middle (its ``MiddleSettings`` get ``always``): the TUI's keys drive
    its Controller, as ``whiztap ctl`` does."""

    def __init__(self, settings: RecordSettings) -> None:
        self.settings = dataclasses.replace(settings, middle=dataclasses.replace(settings.middle, always=True))
        self.output = settings.output
        self.recording: Recording | None = None

    async def start(self, tap: Tap) -> Recording:
        from whiztap.sniffer.record.record_run import Recording

        self.recording = recording = Recording(self.settings, consumers=[tap], warn=tap.warn)
        await recording.start()
        return recording

    async def stop(self) -> dict | None:
        if self.recording is not None and self.recording.writer is not None:
            return await self.recording.stop()
        return None


class LiveSource:
    """Traffic through the recording proxy running inside the app.

    Unless told to keep secrets, the traffic goes through the redaction the
    recorder applies (``whiztap.analyzer.recording.redaction``) before the model sees it: the
    model and the screen get the bytes the file gets, never the password."""

    live = True
    progress: float | None = None

    def __init__(self, rig: Rig, title: str, redact_passwords: bool = True) -> None:
        self.rig = rig
        self.redact_passwords = redact_passwords
        self.title = title
        self.note = ""
        self.queue: deque[TrafficEvent] = deque()
        self.recording: Recording | None = None
        self.stopped = threading.Event()  # the proxy is closed: drain and finish
        self.on_failure: Callable[[str], None] | None = None  # the recording stopped on its own
        self.on_warning: Callable[[str], None] | None = None  # the proxy has something to say (a script raised)
        self._watcher: asyncio.Task | None = None

    @property
    def controller(self) -> Controller | None:
        """The proxy's control layer (faults, interception, injection), once started."""
        return self.recording.controller if self.recording is not None else None

    @property
    def backlog(self) -> int:
        """Reads and events the proxy passed on that the model has not taken yet."""
        return len(self.queue)

    async def start(self) -> None:
        """Start the proxy (and whatever the rig runs with it); raises SourceError."""
        from whiztap.analyzer.mitm.spec import FaultSpecError
        from whiztap.sniffer.mitm.scripts import ScriptError
        from whiztap.sniffer.record.feed import WriterError
        from whiztap.sniffer.record.record_run import StartError

        try:
            self.recording = recording = await self.rig.start(Tap(self.queue, self._warn))
        except (WriterError, FaultSpecError, ScriptError, StartError) as e:
            raise SourceError(str(e)) from None
        except OSError as e:
            raise SourceError(f"cannot listen: {e.strerror or e}") from None
        proxy = recording.proxy
        assert proxy is not None  # started
        self.title = f"{self.title}: {proxy.listen_text} -> {proxy.upstream_text}, recording {self.rig.output}"
        if recording.foxglove_url:
            self.title += f", foxglove {recording.foxglove_url}"
        if recording.control_text:
            self.title += f", control {recording.control_text}"
        self._watcher = asyncio.get_running_loop().create_task(self._watch_writer(recording))

    def _warn(self, text: str) -> None:
        if self.on_warning is not None:
            self.on_warning(text)

    async def _watch_writer(self, recording: Recording) -> None:
        await recording.stopped.wait()
        self.note = f"recording stopped: {recording.error}"
        if self.on_failure is not None:
            self.on_failure(self.note)

    async def stop(self) -> None:
        """Close every connection and finish the recording file."""
        if self._watcher is not None:
            self._watcher.cancel()
        try:
            await self.rig.stop()
        finally:
            self.stopped.set()

    def feed(self, model: TrafficModel, stop: threading.Event) -> None:
        queue = self.queue
        if self.controller is not None:
            model.in_the_middle(self.redact_passwords)
        take = _Redacting(model) if self.redact_passwords else _Plain(model)
        while True:
            while queue:
                take(queue.popleft())
            if self.stopped.is_set() and not queue:
                break
            take.idle()
            if stop.wait(DRAIN_S):
                return
        take.finish()
        model.finish()


class _Plain:
    """The tap's events into the model as they are (``--keep-secrets``)."""

    def __init__(self, model: TrafficModel) -> None:
        self.model = model

    def __call__(self, event: TrafficEvent) -> None:
        self.model.receive(event)

    def idle(self) -> None:
        pass

    def finish(self) -> None:
        pass


class _Redacting:
    """The tap's events into the model through the recorder's redaction: held
    while undecided (at most ``HOLD_LIMIT_S``, as in the writer), then masked
    or shown.

    One Redactor per connection, not one for all as the file has: the file
    keeps every stream in one order, the screen needs each connection's only,
    and with one queue a connection whose first request the proxy holds (so
    its server has said nothing that decides whether a password comes) kept
    every other connection off the screen for those two seconds."""

    def __init__(self, model: TrafficModel) -> None:
        self.model = model
        self.redactors: dict[int, Redactor[TrafficEvent]] = {}

    def __call__(self, event: TrafficEvent) -> None:
        conn = event.conn
        redactor = self.redactors.get(conn)
        if redactor is None:
            redactor = self.redactors[conn] = Redactor()
        if type(event) is Data:
            redactor.read(conn, event.direction, event.data, event, time.monotonic())
        else:
            redactor.tell(event)
            redactor.event(conn, event)
        self._release(redactor)
        if type(event) is Closed and redactor.idle:
            del self.redactors[conn]

    def idle(self) -> None:
        """Nothing new came: let what was held too long out, masked."""
        now = time.monotonic()
        for redactor in list(self.redactors.values()):
            redactor.tick(now)
            self._release(redactor)

    def finish(self) -> None:
        for redactor in self.redactors.values():
            redactor.finish()
            self._release(redactor)

    def _release(self, redactor: Redactor[TrafficEvent]) -> None:
        receive = self.model.receive
        for r in redactor.released():
            event = r.record
            receive(event._replace(data=r.data) if isinstance(event, Data) else event)


def default_output() -> str:
    """A new recording's name when none is given: whiztap-YYYYmmdd-HHMMSS.mcap."""
    return time.strftime("whiztap-%Y%m%d-%H%M%S.mcap")


def follow_path(path: str) -> str:
    """The file to follow: the ``.part`` if it is still there, else what it became."""
    if not Path(path).exists() and path.endswith(".part") and Path(path[:-5]).exists():
        return path[:-5]
    return path
