"""The recording pipe: the proxy hands traffic events to a writer process.

Why a process and not a thread: the session model, JSON and MCAP encoding cost
tens of microseconds per frame in Python; in a thread of the proxy's process
they would hold the GIL the event loop needs to forward the next read (up to the
5 ms switch interval at a time), and round trips through the proxy would slow
down whenever traffic is being written.  In a child process they run on the
other core and the event loop does nothing per read but copy it into a batch.

Parent side (``WriterProcess``, a consumer of the proxy's traffic events:
``receive(event)``): each event becomes one binary record appended to a
batch; the batch goes down a pipe every ``BATCH_S`` (or sooner when large)
through an asyncio write-pipe transport.

When the writer falls behind, only the connections that cause it wait.  The
backlog is what the proxy holds for the writer (the batch and the pipe
transport's buffer); each connection's part of it is counted (the bytes of its
reads in each batch, until the kernel pipe has taken the whole batch).  Above
``BEHIND`` bytes the writer is behind, until the backlog is down to
``CAUGHT_UP``.  While it is behind, the connections with bytes in the backlog
share ``BEHIND`` equally, and a connection over its share is "over"; above
``LIMIT`` every open connection is, new ones from the moment they open.  What
happens to a connection that is over is the user's choice (``when_behind``):
"pause" (the default) stops reading it (``on_hold``: TCP pushes back on its
sender; the recording stays complete); "gap" keeps it flowing but leaves its
bytes out of the recording, recorded instead as a gap event with their count.
Either way the bytes read for the recording are bounded (``LIMIT`` plus one
batch), and a light connection keeps going while a heavy one waits.  The
decision is made again at each batch sent, and every ``BATCH_S`` while behind.

The child side, the writer process, is ``writer_child.py``.

Record layout: ``<BIBQI`` = type, connection id, direction (0 c2s, 1 s2c),
t_ns, payload length; then the payload: for a read (``REC_DATA``) the bytes
read; for bytes the proxy in the middle delivered (``REC_DELIVERED``) those
bytes (direction plus ``SECRET`` for a password's); for an intervention
(``REC_INTERVENTION``) its fields as JSON, bytes in base64; for a line of
the proxy's own for /log (``REC_NOTICE``, connection 0) its fields as JSON;
for ``record --mirror`` (``REC_MIRROR``: direction 1) the mirror's answer, or
(direction 0) its connection's event as JSON (``mirror.py``);
for any other event (``REC_EVENT``) its ``/tcp/events`` message
(``traffic.to_json``).  The recording's stop is its ``RecordingStopped`` event.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import os
import struct
import subprocess
import sys
from collections import deque
from collections.abc import Callable
from typing import Any

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.notice import Notice
from whiztap.analyzer.traffic import (
    Closed,
    ConnectionEvent,
    Data,
    Delivered,
    Gap,
    HalfClosed,
    Intervention,
    Opened,
    RecordingStopped,
    TrafficEvent,
    intervention_to_json,
    to_json,
)

REC_DATA, REC_EVENT, REC_DELIVERED, REC_INTERVENTION, REC_NOTICE, REC_MIRROR = 1, 2, 3, 4, 5, 6
SECRET = 2  # added to a delivery's direction byte: the bytes are a password's
_HEAD = struct.Struct("<BIBQI")
C2S, S2C = Direction.C2S, Direction.S2C
_DIRS = (C2S, S2C)
BATCH_S = 0.005
BATCH_MAX = 256 << 10
BEHIND = 8 << 20  # backlog bytes above which the writer is behind
CAUGHT_UP = 2 << 20  # ... until it is down to this
LIMIT = 2 * BEHIND  # above this, every connection with bytes in the backlog is over
GAP_DETAIL = ("bytes forwarded but not recorded: the writer was behind (--when-behind gap); "
              "the session model restarts after them")
_PIPE_SIZE = 1 << 20
_F_SETPIPE_SZ = 1031
TICK_S = 0.1
EXIT_WRITE_ERROR = 3
# Recording is background work: when the cores are busy, forwarding goes first.
# Measured here with 4 clients doing round trips (20 s): nice 5 gave about 20%
# more round trips than 0; at 10 the writer fell clearly behind.
WRITER_NICE = 5


class WriterError(WhiztapError):
    """The writer could not start or stopped recording; one line for the user."""


def _grow_pipe(fd: int) -> None:
    with contextlib.suppress(OSError):
        fcntl.fcntl(fd, _F_SETPIPE_SZ, _PIPE_SIZE)


# -- parent side ----------------------------------------------------------------------------


class _Pipe(asyncio.Protocol):
    def __init__(self, owner: WriterProcess) -> None:
        self.owner = owner

    def connection_lost(self, exc: Exception | None) -> None:
        self.owner._pipe_lost(exc)


class _Status(asyncio.Protocol):
    def __init__(self, owner: WriterProcess) -> None:
        self.owner = owner
        self._buf = b""

    def data_received(self, data: bytes) -> None:
        lines = (self._buf + data).split(b"\n")
        self._buf = lines.pop()
        for line in lines:
            if line:
                self.owner._status(json.loads(line))

    def connection_lost(self, exc: Exception | None) -> None:
        self.owner._status_closed()


class WriterProcess:
    """The proxy's handle on the writer process.  ``receive(event)`` never
    blocks and never raises: recording must not get in the way of traffic.

    ``when_behind`` is what happens to a connection over its share of the
    backlog (see the module docstring); in "pause" mode ``on_hold(conn, held)``
    is told when to stop and start reading it."""

    def __init__(self, config: dict[str, Any], when_behind: str = "pause") -> None:
        self.config = config
        self.when_behind = when_behind
        self.on_hold: Callable[[int, bool], None] | None = None
        self.on_violation: Callable[[dict], None] | None = None
        self.on_file: Callable[[str], None] | None = None
        self.on_error: Callable[[str], None] | None = None
        self.on_warning: Callable[[str], None] | None = None  # something the writer worked around
        self.on_mirror: Callable[[dict], None] | None = None  # --mirror: what the pairing found (mirror_record.py)
        self._behind = False
        self.error: str | None = None
        self.summary: dict | None = None
        self.verdict: dict | None = None  # in the middle: the writer's latest verdict (summary.verdict_dict)
        self.ready: dict = {}
        self._batch = bytearray()
        self._batch_bytes: dict[int, int] = {}  # connection -> bytes of its reads in the batch
        self._in_pipe: deque[tuple[int, dict[int, int]]] = deque()  # (end in _written, _batch_bytes) per batch
        self._written = 0  # bytes handed to the pipe transport
        self._waiting: dict[int, int] = {}  # connection -> bytes of its reads in the backlog
        self._open: set[int] = set()
        self._over: frozenset[int] = frozenset()
        self._unrecorded: frozenset[int] = frozenset()  # over, in "gap" mode
        self._gaps: dict[tuple[int, Direction], list[int]] = {}  # (connection, direction) -> [t_ns, bytes] left out
        self._timer: asyncio.TimerHandle | None = None
        self._pipe: asyncio.WriteTransport | None = None
        self._proc: subprocess.Popen | None = None
        self._ready: asyncio.Future[None] | None = None
        self._done: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    async def start(self) -> None:
        """Spawn the writer and wait until its file is open (raises WriterError)."""
        loop = self._loop = asyncio.get_running_loop()
        data_r, data_w = os.pipe()
        status_r, status_w = os.pipe()
        _grow_pipe(data_w)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "whiztap.sniffer.record.writer_child", json.dumps(self.config)],
            stdin=data_r, stdout=status_w, close_fds=True)
        os.close(data_r)
        os.close(status_w)
        self._ready = loop.create_future()
        self._done = loop.create_future()
        await loop.connect_read_pipe(lambda: _Status(self), os.fdopen(status_r, "rb", buffering=0))
        self._pipe, _ = await loop.connect_write_pipe(lambda: _Pipe(self), os.fdopen(data_w, "wb", buffering=0))
        await asyncio.wait([self._ready, self._done], return_when=asyncio.FIRST_COMPLETED)
        if not self._ready.done():
            await self._reap()
            raise WriterError(self.error or "the writer process exited before it was ready")

    # -- events from the proxy --------------------------------------------------------------

    def receive(self, event: TrafficEvent) -> None:
        """One event into the batch: a read as its bytes (the hot path, once per
        read), any other event as its message."""
        if isinstance(event, Data):
            conn, direction, t_ns, data, _offset, _masked = event
            if conn in self._unrecorded:
                self._leave_out(conn, direction, t_ns, len(data))
                return
            batch = self._batch
            batch += _HEAD.pack(REC_DATA, conn, 0 if direction is C2S else 1, t_ns, len(data))
            batch += data
            counts = self._batch_bytes
            counts[conn] = counts.get(conn, 0) + len(data)
            self._queued()
            return
        kind = type(event)
        conn = event.conn
        if isinstance(event, (Delivered, Intervention)):
            self._middle(event)
            return
        if kind is HalfClosed or kind is Closed:
            self._end_gaps(conn)  # what was left out came before
            if kind is Closed:
                self._open.discard(conn)
        self._event(event)
        if kind is Opened:
            self._open.add(conn)
            if self._behind:
                self._rebalance()  # over the limit, a new connection is over at once

    async def stop(self, t_ns: int, detail: str = "") -> dict | None:
        """Finish the recording; returns the writer's summary (None if it failed)."""
        if self._pipe is not None and not self._pipe.is_closing():
            self._event(RecordingStopped(t_ns, "recorder", detail))
            self._send()
            self._pipe.close()
        await self._reap()
        return self.summary

    def notice(self, notice: Notice) -> None:
        """A line of the proxy's own for the recording's /log (a fault that chose nothing)."""
        body = json.dumps(notice.as_dict()).encode()
        self._batch += _HEAD.pack(REC_NOTICE, 0, 0, notice.t_ns, len(body)) + body
        self._queued()

    def mirror(self, conn: int, t_ns: int, read: bool, payload: bytes) -> None:
        """The mirror's answer (``read``) or its connection's event (JSON), from ``mirror.py``: in
        order with the primary's traffic, and counted in no connection's share (the mirror
        drops itself rather than hold anyone up: see ``backlog``)."""
        self._batch += _HEAD.pack(REC_MIRROR, conn, 1 if read else 0, t_ns, len(payload)) + payload
        self._queued()

    @property
    def backlog(self) -> int:
        """What the proxy holds for the writer: the batch and the pipe transport's buffer."""
        pipe = self._pipe
        return len(self._batch) + (pipe.get_write_buffer_size() if pipe is not None else 0)

    def fail(self, message: str) -> None:
        """The recording cannot go on (the first reason is the one kept)."""
        if self.error is None:
            self.error = message
            if self.on_error is not None:
                self.on_error(message)

    # -- internals ---------------------------------------------------------------------------

    def _event(self, event: ConnectionEvent) -> None:
        body = json.dumps(to_json(event)).encode()
        self._batch += _HEAD.pack(REC_EVENT, event.conn, 0, event.t_ns, len(body)) + body
        self._queued()

    def _middle(self, event: Delivered | Intervention) -> None:
        """What the proxy in the middle delivered or changed (rare: no hot path)."""
        direction = 0 if event.direction is C2S else 1
        if isinstance(event, Delivered):
            body = event.data
            self._batch += _HEAD.pack(REC_DELIVERED, event.conn, direction + (SECRET if event.secret else 0),
                                      event.t_ns, len(body)) + body
        else:
            body = json.dumps(intervention_to_json(event)).encode()
            self._batch += _HEAD.pack(REC_INTERVENTION, event.conn, direction, event.t_ns, len(body)) + body
        self._queued()

    def _queued(self) -> None:
        if len(self._batch) >= BATCH_MAX:
            self._send()
        elif self._timer is None and self._loop is not None:
            self._timer = self._loop.call_later(BATCH_S, self._send)

    def _send(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        pipe = self._pipe
        if self._batch and pipe is not None and not pipe.is_closing():
            pipe.write(bytes(self._batch))
            self._written += len(self._batch)
            if self._batch_bytes:
                self._in_pipe.append((self._written, self._batch_bytes))
                waiting = self._waiting
                for conn, n in self._batch_bytes.items():
                    waiting[conn] = waiting.get(conn, 0) + n
        self._batch.clear()
        self._batch_bytes = {}
        self._rebalance()

    def _rebalance(self) -> None:
        """Count what the kernel pipe has taken, and decide again who is over
        (see the module docstring); while behind, again every ``BATCH_S``:
        nothing else notices the pipe draining while every heavy connection waits."""
        pipe = self._pipe
        buffered = pipe.get_write_buffer_size() if pipe is not None else 0
        taken = self._written - buffered
        in_pipe, waiting = self._in_pipe, self._waiting
        while in_pipe and in_pipe[0][0] <= taken:
            for conn, n in in_pipe.popleft()[1].items():
                left = waiting[conn] - n
                if left:
                    waiting[conn] = left
                else:
                    del waiting[conn]
        backlog = buffered + len(self._batch)
        if backlog > BEHIND:
            self._behind = True
        elif backlog <= CAUGHT_UP:
            self._behind = False
        over = self._over_share(backlog) if self._behind else frozenset()
        if over != self._over:
            self._set_over(over)
        if (self._behind and self._timer is None and pipe is not None and not pipe.is_closing()
                and self._loop is not None):
            self._timer = self._loop.call_later(BATCH_S, self._send)

    def _over_share(self, backlog: int) -> frozenset[int]:
        if backlog > LIMIT:
            return frozenset(self._open)
        waiting = self._waiting
        share = BEHIND // max(len(waiting), 1)
        return frozenset(conn for conn, n in waiting.items() if n > share)

    def _set_over(self, over: frozenset[int]) -> None:
        before, self._over = self._over, over
        if self.when_behind == "gap":
            self._unrecorded = over
            for conn in before - over:
                self._end_gaps(conn)
        elif self.on_hold is not None:
            for conn in over - before:
                self.on_hold(conn, True)
            for conn in before - over:
                self.on_hold(conn, False)

    def _leave_out(self, conn: int, direction: Direction, t_ns: int, length: int) -> None:
        """A read of a connection that is over, in "gap" mode: only counted."""
        gap = self._gaps.get((conn, direction))
        if gap is None:
            self._gaps[(conn, direction)] = [t_ns, length]
        else:
            gap[1] += length

    def _end_gaps(self, conn: int) -> None:
        """The gap records of what was left out, before anything else of ``conn``."""
        for direction in _DIRS:
            gap = self._gaps.pop((conn, direction), None)
            if gap is not None:
                self._event(Gap(conn, gap[0], direction, length=gap[1], detail=GAP_DETAIL))

    def _pipe_lost(self, exc: Exception | None) -> None:
        if exc is not None and self.error is None:
            self.fail("the writer process stopped reading")

    def _status(self, message: dict) -> None:
        kind = message.get("type")
        if kind == "ready":
            self.ready = message  # what the writer serves: "foxglove", its ws:// URL, with --foxglove
            if self._ready is not None and not self._ready.done():
                self._ready.set_result(None)
        elif kind == "violation" and self.on_violation is not None:
            self.on_violation(message)
        elif kind == "file" and self.on_file is not None:
            self.on_file(message["path"])
        elif kind == "error":
            self.fail(message["message"])
        elif kind == "warning" and self.on_warning is not None:
            self.on_warning(message["message"])
        elif kind == "summary":
            self.summary = message
        elif kind == "mirror" and self.on_mirror is not None:
            self.on_mirror(message)
        elif kind == "verdict":
            self.verdict = {k: v for k, v in message.items() if k != "type"}

    def _status_closed(self) -> None:
        if self.summary is None and self._ready is not None and self._ready.done():
            self.fail("the writer process exited unexpectedly")
        if self._done is not None and not self._done.done():
            self._done.set_result(None)

    async def _reap(self) -> None:
        if self._done is not None:
            await self._done
        if self._proc is not None:
            await asyncio.get_running_loop().run_in_executor(None, self._proc.wait)
