"""``probe client``'s runner: whiztap plays the server, the client under test runs as a process.

For each case a server listens on 127.0.0.1 (a free port), the client's
command starts once in a process group of its own, and the case ends when the
client does or the wait runs out (then the whole group is killed: a shell
pipeline's children too).  The played server is the simulator's robot
(``whiztap.sniffer.sim.robot``) with the case's schedule on its replies
(``whiztap.analyzer.probe.client_cases``); everything that crosses each
connection is fed, in the order it crossed, to the analyzer's session, and
the client's own error-severity violations are the case's findings.

Memory stays bounded whatever the client does: replies wait in a bounded
queue (a client that floods waits for the server to catch up), the session
keeps its own bounds, findings are one per rule, the client's standard error
is looked at as it streams (its last few KiB kept) and its standard output
is not kept.
"""

from __future__ import annotations

import asyncio
import os
import shlex
import signal
import socket
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.probe.client_cases import (
    GAP_S, LARGEST_IMAGE, LINGER_S, MAX_GAPPED, NEED_REASON, ClientCase, Need, Shaper, pad_jpeg)
from whiztap.analyzer.probe.model import CaseResult, Finding, Outcome, ProbeReport
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.protocol.session import Limits, Session
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, parse_channels
from whiztap.sniffer.sim.robot import DEFAULT_PASSWORD, Camera, Output, Robot, ServerMode
from whiztap.sniffer.sim.tcp_server import READ_SIZE

LOCAL = "127.0.0.1"
DEFAULT_TIMEOUT = 10.0
MAX_QUEUED = 256  # replies waiting for their turn on one connection before reading stops
MAX_CONNECTIONS = 8  # a case's connections judged; more are closed at once
SETTLE_S = 1.0  # after the client ended, how long its connections get to be seen closing
TRACEBACK = b"Traceback (most recent call last):"
STDERR_TAIL = 4096
ENV_HOST, ENV_PORT, ENV_CASE, ENV_PASSWORD = (
    "WHIZTAP_PROBE_HOST", "WHIZTAP_PROBE_PORT", "WHIZTAP_PROBE_CASE", "WHIZTAP_PROBE_PASSWORD")


class ProbeClientError(WhiztapError):
    """The run cannot happen at all (the command cannot be started or parsed)."""


@dataclass(frozen=True, slots=True)
class ClientProbe:
    """One run's settings.  ``command``: as typed, ``{host}`` and ``{port}``
    not yet filled in; ``timeout``: how long a client may take per case."""

    command: str
    mode: ServerMode = ServerMode.WINSOCK
    password: str = DEFAULT_PASSWORD
    seed: int = 0
    timeout: float = DEFAULT_TIMEOUT

    def argv(self, host: str, port: int) -> list[str]:
        """The command's words with ``{host}`` and ``{port}`` filled in."""
        try:
            words = shlex.split(self.command)
        except ValueError as e:
            raise ProbeClientError(f"--run: cannot split {self.command!r} into words: {e}") from None
        if not words:
            raise ProbeClientError("--run: the command is empty")
        return [w.replace("{host}", host).replace("{port}", str(port)) for w in words]

    def environment(self, host: str, port: int, case: str) -> dict[str, str]:
        env = dict(os.environ, **{ENV_HOST: host, ENV_PORT: str(port), ENV_CASE: case})
        if self.mode is ServerMode.WINSOCK:
            env[ENV_PASSWORD] = self.password
        else:
            env.pop(ENV_PASSWORD, None)
        return env


async def probe_client(probe: ClientProbe, cases: Iterable[ClientCase]) -> ProbeReport:
    """Every case, one after another, into one report."""
    started = time.monotonic()
    report = ProbeReport(target=probe.command, role="client", seed=probe.seed, mode=str(probe.mode))
    for case in cases:
        report.cases.append(await run_case(probe, case))
    report.seconds = time.monotonic() - started
    return report


async def run_case(probe: ClientProbe, case: ClientCase) -> CaseResult:
    started = time.monotonic()
    why_not = case.applies(str(probe.mode))
    if why_not:
        return CaseResult(case.id, case.title, case.spec, Outcome.SKIP, reason=why_not)
    server = PlayedServer(probe, case)
    await server.start()
    try:
        ended = await _run_client(probe, case, server.port)
    finally:
        await server.finish()
    found = server.findings() + ended.findings(probe, case, bool(server.connections))
    verdict, reason = Outcome.FAIL if found else Outcome.PASS, ""
    unmet = server.unmet(case.need)
    if not found and unmet:
        verdict, reason = Outcome.SKIP, unmet
    return CaseResult(case.id, case.title, case.spec, verdict, tuple(_redact(f, probe.password) for f in found),
                      reason=reason, seconds=time.monotonic() - started)


def _redact(finding: Finding, password: str) -> Finding:
    """What a client printed or sent may hold the password: never shown."""
    if password and password in finding.detail:
        return Finding(finding.rule, finding.detail.replace(password, "***"))
    return finding


# -- the client's process ----------------------------------------------------------------------------


@dataclass(slots=True)
class ClientEnd:
    """How the client's process ended: its status (negative: a signal),
    whether it was killed for taking too long, and what its standard error
    showed."""

    status: int
    hung: bool
    traceback: bool
    last_line: str

    def findings(self, probe: ClientProbe, case: ClientCase, connected: bool) -> list[Finding]:
        if self.hung:
            return [Finding("PROBE-CLIENT-HANG", f"still running after {probe.timeout:g} s: "
                            "killed with its process group")]
        out = []
        if self.traceback or self.status < 0:
            how = (f"killed by {signal.Signals(-self.status).name}" if self.status < 0
                   else f"exit status {self.status} after a traceback")
            out.append(Finding("PROBE-CLIENT-CRASH", f"{how}: {self.last_line}" if self.last_line else how))
        elif case.must_succeed and self.status != 0:
            said = f": {self.last_line}" if self.last_line else ""
            out.append(Finding("PROBE-CLIENT-EXIT", f"exit status {self.status} against a server that keeps "
                               f"the spec{said}"))
        if not connected:
            out.append(Finding("PROBE-CLIENT-NO-CONNECTION", f"exited with status {self.status} "
                               "without connecting to the server"))
        return out


async def _run_client(probe: ClientProbe, case: ClientCase, port: int) -> ClientEnd:
    argv = probe.argv(LOCAL, port)
    try:
        process = await asyncio.create_subprocess_exec(
            *argv, env=probe.environment(LOCAL, port, case.id), stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, start_new_session=True)
    except OSError as e:
        raise ProbeClientError(f"--run: cannot start {argv[0]!r}: {e.strerror or e}") from None
    assert process.stderr is not None
    watch = asyncio.create_task(_watch_stderr(process.stderr))
    hung = False
    try:
        await asyncio.wait_for(process.wait(), probe.timeout)
    except TimeoutError:
        hung = True
    finally:
        _kill_group(process.pid)  # a hung client, or what an ended one left running
        status = await process.wait()
    try:
        seen_traceback, tail = await asyncio.wait_for(watch, SETTLE_S)
    except TimeoutError:  # something outside the group holds its standard error open
        seen_traceback, tail = False, b""
    lines = tail.decode("utf-8", "replace").strip().splitlines()
    return ClientEnd(status, hung, seen_traceback, lines[-1].strip() if lines else "")


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass  # the group is gone already


async def _watch_stderr(stream: asyncio.StreamReader) -> tuple[bool, bytes]:
    """Whether a Python traceback began on the stream, and its last bytes."""
    seen = False
    tail = b""
    while chunk := await stream.read(READ_SIZE):
        window = tail[-len(TRACEBACK):] + chunk
        seen = seen or TRACEBACK in window
        tail = (tail + chunk)[-STDERR_TAIL:]
    return seen, tail


# -- the played server ---------------------------------------------------------------------------------


class PlayedServer:
    """The simulator's robot behind a listening socket, the case's schedule on
    its replies; one analyzer session per connection."""

    def __init__(self, probe: ClientProbe, case: ClientCase) -> None:
        self.probe = probe
        self.case = case
        self.robot = Robot(parse_channels(DEFAULT_CHANNELS), seed=probe.seed, camera=_camera(case),
                           start_ns=time.monotonic_ns())
        self.connections: list[PlayedConnection] = []
        self.errors: list[Exception] = []  # raised while serving a connection
        self._tasks: set[asyncio.Task] = set()
        self._server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        assert self._server is not None
        return self._server.sockets[0].getsockname()[1]

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, LOCAL, 0, limit=READ_SIZE)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self.connections) >= MAX_CONNECTIONS:
            writer.transport.abort()
            return
        sock = writer.get_extra_info("socket")
        if sock is not None:  # each piece of a cut reply its own segment
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        connection = PlayedConnection(self, reader, writer, len(self.connections) + 1)
        self.connections.append(connection)
        try:
            await connection.serve()
        except Exception as e:  # whiztap's own bug: asyncio would only log it; finish() raises it
            self.errors.append(e)
        finally:
            self._tasks.discard(task)

    async def finish(self) -> None:
        """The client has ended: let its connections be seen closing, then close
        the rest.  An error that escaped serving a connection is raised here."""
        assert self._server is not None
        self._server.close()
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=SETTLE_S)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for connection in self.connections:
            connection.close_session()
        await self._server.wait_closed()
        if self.errors:
            raise self.errors[0]

    def findings(self) -> list[Finding]:
        """The client's violations on every connection, one finding per rule."""
        counted: dict[str, list] = {}
        for connection in self.connections:
            for rule, (detail, n) in connection.violations.items():
                entry = counted.setdefault(rule, [detail, 0])
                entry[1] += n
        return [Finding(rule, detail if n == 1 else f"{detail} ({n} times)")
                for rule, (detail, n) in counted.items()]

    def unmet(self, need: Need) -> str:
        """Why the case's schedule had nothing to act on ("" when it had)."""
        if need is Need.IMAGE and not self.robot.frames:
            return NEED_REASON[need]
        if need is Need.ANSWER and not any(c.shaper.answers for c in self.connections):
            return NEED_REASON[need]
        return ""


def _camera(case: ClientCase) -> Camera:
    """The simulator's test picture, or with the largest-image schedule that
    picture padded to the largest size: made once and sent again, never copied."""
    from whiztap.sniffer.sim.camera import render_frame  # Pillow: only once a case runs

    if not case.schedule.largest_image:
        return render_frame
    image = pad_jpeg(render_frame(1, 0.0), LARGEST_IMAGE)

    def largest(frame: int, t_s: float) -> bytes:
        return image

    return largest


@dataclass(slots=True)
class _Write:
    due: float  # loop time
    pieces: list[bytes] | None  # None: close instead


@dataclass(slots=True)
class PlayedConnection:
    """One connection: a reader that feeds the robot and the session, a writer
    that sends the shaped replies at their time and feeds the session too."""

    server: PlayedServer
    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    number: int
    session: Session = field(default_factory=lambda: Limits().session())
    violations: dict[str, tuple[str, int]] = field(default_factory=dict)
    shaper: Shaper = field(init=False)
    _queue: asyncio.Queue[_Write | None] = field(default_factory=lambda: asyncio.Queue(MAX_QUEUED))
    _eof: asyncio.Event = field(default_factory=asyncio.Event)
    _last_due: float = 0.0
    _closed: bool = False

    def __post_init__(self) -> None:
        self.shaper = Shaper(self.server.case.schedule, f"{self.server.probe.seed}:{self.number}")

    async def serve(self) -> None:
        probe, schedule = self.server.probe, self.server.case.schedule
        password = probe.password.encode()
        if schedule.verdict is not None:  # refuse any password: the robot's check, on one that differs at once
            password = bytes([password[0] ^ 1]) + password[1:]
        robot = self.server.robot.connect(probe.mode, password)
        sending = asyncio.create_task(self._send())
        try:
            await self._queue_replies(robot.start(time.monotonic_ns()))
            while not sending.done() and (data := await self.reader.read(READ_SIZE)):
                self._observe(Direction.C2S, data)
                await self._queue_replies(robot.receive(data, time.monotonic_ns()))
            self._eof.set()
            self._observe_end()
            if not sending.done():
                await self._queue.put(None)
            await sending
        except (ConnectionError, OSError):
            pass
        finally:
            sending.cancel()
            self.writer.transport.abort()

    async def _queue_replies(self, out: Output) -> None:
        loop = asyncio.get_running_loop()
        for reply in out.replies:
            self._last_due = max(self._last_due, loop.time() + self.server.case.schedule.delay_s)
            await self._queue.put(_Write(self._last_due, self.shaper.shape(reply.data, reply.answer)))
        if out.close:  # after Failed Validation: the client's turn to close
            await self._queue.put(_Write(self._last_due + LINGER_S, None))

    async def _send(self) -> None:
        loop = asyncio.get_running_loop()
        while (write := await self._queue.get()) is not None:
            if write.pieces is None:
                try:  # a close after a verdict waits for the client's own close, a while
                    await asyncio.wait_for(self._eof.wait(), max(0.0, write.due - loop.time()))
                except TimeoutError:
                    pass
                break
            await asyncio.sleep(max(0.0, write.due - loop.time()))
            gap = GAP_S if 1 < len(write.pieces) <= MAX_GAPPED else 0.0
            for n, piece in enumerate(write.pieces):
                if gap and n:
                    await asyncio.sleep(gap)
                self.writer.write(piece)
                self._observe(Direction.S2C, piece)
                await self.writer.drain()
        self.writer.close()

    def _observe(self, direction: Direction, data: bytes) -> None:
        self._judge(self.session.receive(direction, data, time.monotonic_ns()))

    def _observe_end(self) -> None:
        self._judge(self.session.end(Direction.C2S, time.monotonic_ns()))

    def close_session(self) -> None:
        if not self._closed:
            self._closed = True
            self._judge(self.session.close(time.monotonic_ns()))

    def _judge(self, events: list) -> None:
        """Keep the client's own error-severity violations (the server's are the schedule's doing)."""
        for event in events:
            if not isinstance(event, Observation) or event.direction is not Direction.C2S:
                continue
            for v in event.violations:
                if v.severity >= Severity.ERROR:
                    detail, n = self.violations.get(v.rule_id, (v.detail, 0))
                    self.violations[v.rule_id] = (detail, n + 1)
