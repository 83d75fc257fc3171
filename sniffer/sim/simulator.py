"""The simulated Progwhiz server on asyncio: sockets around the sans-IO robot.

Usable in-process (``async with Simulator(port=0) as sim: sim.port``) and from
``whiztap sim``.  One ``Robot`` is shared by every connection, as one robot would
be; each connection gets its own handshake, framer and fault generator.  Nothing
a client sends, and no error inside one connection, stops the server, unless a
planted bug (``bugs=``, ``sniffer/sim/bugs.py``) is there to crash it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.sniffer.sim.bugs import Planted, check_bugs
from whiztap.sniffer.sim.camera import render_frame
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, parse_channels
from whiztap.sniffer.sim.faults import FaultConfig, FaultPlanner
from whiztap.sniffer.sim.robot import (
    DEFAULT_PASSWORD,
    DEFAULT_SERVO_SPEED,
    Output,
    Robot,
    RobotConnection,
    ServerMode,
)
from whiztap.sniffer.sim.tcp_server import READ_SIZE, TcpServer

log = logging.getLogger("whiztap.sim")
log.addHandler(logging.NullHandler())  # a library stays quiet until its user sets up logging

MAX_QUEUED = 1024  # replies held back by fault injection before the connection stops reading


@dataclass(slots=True)
class Stats:
    """Counters a test or the CLI can read while the server runs."""

    connections: int = 0  # accepted so far
    open_connections: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    answers_sent: int = 0
    answers_dropped: int = 0
    errors: int = 0  # connections ended by an unexpected exception


class Simulator(TcpServer):
    """A Progwhiz Robotics Server on ``host:port`` (127.0.0.1 unless told)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        mode: ServerMode | str = ServerMode.WINSOCK,
        password: str | bytes = DEFAULT_PASSWORD,
        channels: tuple[ChannelConfig, ...] | str = DEFAULT_CHANNELS,
        seed: int = 0,
        servo_speed: float = DEFAULT_SERVO_SPEED,
        camera: bool = True,
        checksum_rule: str = DEFAULT_CHECKSUM_RULE,
        faults: FaultConfig = FaultConfig(),
        clock: Callable[[], int] = time.monotonic_ns,
        bugs: tuple[str, ...] = (),
    ) -> None:
        """``bugs`` plants defects by name (``sniffer/sim/bugs.py``); a name not
        known, or one the mode cannot show, is a ``BugError`` (a ValueError)."""
        super().__init__(host, port)
        self.mode = ServerMode(mode)
        self.password = password.encode() if isinstance(password, str) else password
        if self.mode is ServerMode.WINSOCK and not self.password:
            raise ValueError("winsock mode needs a non-empty password")
        self.seed = seed
        self.faults = faults
        self.clock = clock
        self.bugs = check_bugs(bugs, self.mode)
        self.crashed = asyncio.Event()  # set when a planted bug has crashed the server
        if isinstance(channels, str):
            channels = parse_channels(channels)
        self.robot = Robot(channels, seed=seed, servo_speed=servo_speed,
                           camera=render_frame if camera else None,
                           checksum_rule=checksum_rule, start_ns=clock())
        self.stats = Stats()
        self.crash_reason: str | None = None  # the planted bug that crashed the server

    # -- one connection ----------------------------------------------------------------

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.crashed.is_set():  # accepted while the crash was closing the listening socket
            writer.transport.abort()
            return
        self.stats.connections += 1
        self.stats.open_connections += 1
        number = self.stats.connections
        peer = writer.get_extra_info("peername")
        name = f"conn {number} {peer[0]}:{peer[1]}" if peer else f"conn {number}"
        sender = _Sender(writer, self.stats, FaultPlanner(self.faults, f"{self.seed}:{number}")
                         if self.faults.active else None)
        log.info("%s: connected", name)
        graceful = True
        try:
            hooks = Planted(self.bugs, self.robot) if self.bugs else None
            connection = self.robot.connect(self.mode, self.password, hooks=hooks)
            await self._serve(connection, reader, sender, name)
        except asyncio.CancelledError:  # the server is closing
            graceful = False
        except (ConnectionError, OSError) as e:
            graceful = False
            log.info("%s: %s", name, e)
        except Exception:  # a bug in one connection must not end the others
            self.stats.errors += 1
            log.exception("%s: internal error, closing this connection", name)
        finally:
            try:
                if graceful and not self.crashed.is_set():
                    await sender.close()
                else:
                    sender.abort()
            finally:
                self.stats.open_connections -= 1
                log.info("%s: closed", name)

    async def _serve(self, connection: RobotConnection, reader: asyncio.StreamReader,
                     sender: _Sender, name: str) -> None:
        if await self._emit(connection.start(self.clock()), sender, name):
            return
        while True:
            data = await reader.read(READ_SIZE)
            if not data:
                await self._emit(connection.end(self.clock()), sender, name)
                return
            self.stats.bytes_in += len(data)
            if await self._emit(connection.receive(data, self.clock()), sender, name):
                return

    async def _emit(self, out: Output, sender: _Sender, name: str) -> bool:
        """Log the notes and send the replies; True when the connection must close."""
        for note in out.notes:
            log.log(note.level, "%s: %s", name, note)
        if out.crash is not None:
            self._crash(out.crash, name)
            return True
        for reply in out.replies:
            sender.send(reply.data, reply.answer)
        await sender.flush()
        return out.close

    def _crash(self, bug: str, name: str) -> None:
        """A planted bug brings the whole server down, as a crashed process
        would: the listening socket closes, every connection is reset (this
        one as its handler returns) and ``crashed`` is set."""
        log.info("%s: this crashes the server (planted bug %s)", name, bug)
        self.crash_reason = bug
        self.crashed.set()
        self.stop_listening()
        current = asyncio.current_task()
        for task in list(self._handlers):
            if task is not current:
                task.cancel()


class _Sender:
    """Writes replies, directly or, with faults on, through a queue that keeps
    their order while delaying, splitting, dropping and garbling them."""

    def __init__(self, writer: asyncio.StreamWriter, stats: Stats, planner: FaultPlanner | None) -> None:
        self.writer = writer
        self.stats = stats
        self.planner = planner
        self._queue: asyncio.Queue[tuple[float, tuple[bytes, ...]] | None] | None = None
        self._task: asyncio.Task | None = None
        self._last_due = 0.0
        if planner is not None:
            self._queue = asyncio.Queue()
            self._task = asyncio.create_task(self._run())

    def send(self, data: bytes, answer: bool) -> None:
        if self.planner is None:
            self._count(answer)
            self.writer.write(data)
            self.stats.bytes_out += len(data)
            return
        plan = self.planner.plan(data, answer)
        if plan is None:
            self.stats.answers_dropped += 1
            return
        self._count(answer)
        loop = asyncio.get_running_loop()
        self._last_due = max(self._last_due, loop.time() + plan.delay_s)
        assert self._queue is not None
        self._queue.put_nowait((self._last_due, plan.pieces))

    def _count(self, answer: bool) -> None:
        if answer:
            self.stats.answers_sent += 1

    async def flush(self) -> None:
        """Stop reading while the peer is not keeping up, so nothing queues without bound."""
        if self._queue is None:
            await self.writer.drain()
        elif self._queue.qsize() > MAX_QUEUED:
            await self._queue.join()

    async def _run(self) -> None:
        assert self._queue is not None
        loop = asyncio.get_running_loop()
        while (entry := await self._queue.get()) is not None:
            due, pieces = entry
            await asyncio.sleep(max(0.0, due - loop.time()))
            for piece in pieces:
                self.writer.write(piece)
                self.stats.bytes_out += len(piece)
                await self.writer.drain()
            self._queue.task_done()

    async def close(self) -> None:
        """Send what is queued, then close the socket."""
        try:
            if self._task is not None and self._queue is not None:
                self._queue.put_nowait(None)
                await self._task
            self.writer.close()
            await self.writer.wait_closed()
        except (ConnectionError, OSError):
            self.abort()
        except asyncio.CancelledError:
            self.abort()
            raise

    def abort(self) -> None:
        """Drop whatever is queued and reset the connection."""
        if self._task is not None:
            self._task.cancel()
        self.writer.transport.abort()
