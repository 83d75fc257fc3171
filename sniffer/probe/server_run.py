"""``probe server`` over sockets: the catalogue's steps played against a live server.

First one connection finds out what the server is (``discover``): Winsock
when it says ``sendchkpass`` within ``DETECT_S`` of connecting, VPN
otherwise; then the handshake, with the password given, and Fetch
Configuration, whose answer gives the channels the cases address.  Then each
case runs on its own connection(s), one case at a time, and is judged by
``whiztap.analyzer.probe.judging`` from what crossed its sockets.

With a recording directory every connection goes through the project's own
recording proxy (``sniffer/record``), run in this process: the file is a
normal recording (``analyze``, ``cat`` and ``tui`` open it), a connection per
case, numbered as the proxy numbers them (the discovery is connection 1).

A server that closes a connection is asked, once the case is over, whether it
still accepts connections; one that does not fails that case (``PROBE-DOWN``)
and the cases after it are skipped with the reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.probe.judging import Trace, judge
from whiztap.analyzer.probe.model import CaseResult, Outcome, ProbeReport
from whiztap.analyzer.probe.server_plan import (
    FETCH,
    Mode,
    Pause,
    Send,
    ServerCase,
    Step,
    Target,
    Until,
    opening,
    reached,
)
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, HANDSHAKE_WORDS, SENDCHKPASS
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.sniffer.nettext import reason, show_address
from whiztap.sniffer.record.proxy import try_upstream

if TYPE_CHECKING:
    from whiztap.sniffer.record.record_run import Recording

DETECT_S = 0.3  # how long a server has to say 'sendchkpass' before it is taken for a VPN server
WAIT_S = 2.0  # how long each wait of a case lasts at most (an answer, a handshake word)
LINGER_S = 0.5  # how long the probe reads after it closed its side, for the server's close
CONNECT_S = 5.0
READ_SIZE = 65536
RECORDING_NAME = "probe-server.mcap"
C2S, S2C = Direction.C2S, Direction.S2C


class ProbeError(WhiztapError):
    """The probe could not run at all (exit status 2); one line for the user."""


@dataclass(frozen=True, slots=True)
class ProbeSettings:
    host: str
    port: int
    password: bytes | None = None
    seed: int = 0
    record_dir: str | None = None
    wait_s: float = WAIT_S


class _Conn:
    """One connection of a case: its steps played, everything seen kept in a
    ``Trace`` and fed to a live session, which says when a wait is over."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, wait_s: float) -> None:
        self.reader, self.writer, self.wait_s = reader, writer, wait_s
        self.trace = Trace()
        self.session = Session()
        self.words: list[bytes] = []  # the handshake words the server said
        self.changed = asyncio.Event()
        self.closed = False  # the server's side is over
        self.done = False  # the probe is done: a close from now on is no finding
        self.task = asyncio.get_running_loop().create_task(self._read())

    def _note(self, direction: Direction, data: bytes) -> None:
        t_ns = time.monotonic_ns()
        self.trace.events.append((direction, data, t_ns))
        for event in self.session.receive(direction, data, t_ns):
            if isinstance(event, Observation) and event.item.kind is ItemKind.HANDSHAKE and direction is S2C:
                self.words.append(event.item.raw)

    def _lost(self, how: str) -> None:
        if not self.closed and not self.done:
            self.trace.closed_early, self.trace.how = True, how
        self.closed = True
        self.changed.set()

    async def _read(self) -> None:
        try:
            while data := await self.reader.read(READ_SIZE):
                self._note(S2C, data)
                self.changed.set()
        except (ConnectionError, OSError):
            self._lost("reset")
            return
        self._lost("closed")

    async def play(self, steps: list[Step]) -> None:
        for step in steps:
            if self.closed:
                return
            if isinstance(step, Send):
                await self._send(step)
            elif isinstance(step, Pause):
                await asyncio.sleep(step.seconds)
            else:
                await self._until(step)

    async def _send(self, step: Send) -> None:
        for i, piece in enumerate(step.chunks()):
            if i and step.gap_s:
                await asyncio.sleep(step.gap_s)
            if self.closed:
                return
            self._note(C2S, piece)
            try:
                self.writer.write(piece)
                await self.writer.drain()
            except (ConnectionError, OSError):
                self._lost("reset")
                return

    async def _until(self, point: Until) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.wait_s
        while not reached(point, self.session, self.words) and not self.closed:
            self.changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), deadline - loop.time())
            if loop.time() >= deadline:
                return

    async def finish(self) -> Trace:
        """Close the probe's side, read what the server still sends, and hand over the trace."""
        self.done = True
        if not self.closed:
            with contextlib.suppress(ConnectionError, OSError, RuntimeError):
                self.writer.write_eof()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(self.task), LINGER_S)
        self.task.cancel()
        self.writer.close()
        self.trace.end_ns = time.monotonic_ns()
        return self.trace


def _said(conn: _Conn, word: bytes) -> bool:
    return any(d is S2C and word in data for d, data, _ in conn.trace.events)


def _channels(session: Session) -> tuple[ChannelConfig, ...]:
    """The channel map the server announced, channel 0 upwards (empty if it announced none it could be read from)."""
    return tuple(session.channel_map[ch] for ch in sorted(session.channel_map))


class ServerProbe:
    """One run: ``discover()``, then ``run(case)`` for each case, then ``close()``."""

    def __init__(self, settings: ProbeSettings) -> None:
        self.settings = settings
        self.connect_to = (settings.host, settings.port)
        self.target_text = show_address(settings.host, settings.port)
        self.recording: Recording | None = None
        self.recording_path = ""
        self.conns = 0  # connections opened so far: the next one's number in the recording is this + 1
        self.down = ""  # why the server is taken to be down (the cases after are skipped)

    async def start(self) -> None:
        """Check the server is there, and start the recording (if asked). Raises ProbeError."""
        s = self.settings
        why = await try_upstream(s.host, s.port, CONNECT_S)
        if why is not None:
            raise ProbeError(f"cannot connect to {self.target_text}: {why}; is the server running, "
                             "and are HOST and PORT right?")
        if s.record_dir is not None:
            await self._start_recording(s.record_dir)

    async def _start_recording(self, directory: str) -> None:
        from whiztap.sniffer.record.feed import WriterError
        from whiztap.sniffer.record.record_run import Recording, RecordSettings

        path = Path(directory) / RECORDING_NAME
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ProbeError(f"--record {directory}: cannot create the directory: {e.strerror or e}") from None
        if path.exists():
            raise ProbeError(f"--record {directory}: {path} exists already; give another directory")
        settings = RecordSettings(listen=("127.0.0.1", 0), upstream=self.connect_to, output=str(path),
                                  quiet=True, overwrite=False)
        self.recording = recording = Recording(settings, warn=lambda text: None)
        try:
            await recording.start()
        except (WriterError, OSError) as e:
            raise ProbeError(f"--record {directory}: cannot record: {e}") from None
        self.connect_to = ("127.0.0.1", recording.port)
        self.recording_path = str(path)

    async def close(self) -> None:
        if self.recording is not None:
            await self.recording.stop("probe finished")

    async def _connect(self) -> _Conn:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(*self.connect_to), CONNECT_S)
        self.conns += 1
        return _Conn(reader, writer, self.settings.wait_s)

    async def _first_connection(self) -> _Conn:
        try:
            return await self._connect()
        except (TimeoutError, OSError) as e:
            raise ProbeError(f"cannot connect to {self.target_text}: {reason(e)}") from None

    async def discover(self) -> Target:
        """The server's mode and channels. Raises ProbeError.

        Winsock when the server says 'sendchkpass' within ``DETECT_S``;
        otherwise the first command, Fetch Configuration, says: answered with
        a handshake word, the server wants a password it never asked for
        (still Winsock, which the handshake cases then report); else VPN."""
        s = self.settings
        conn = await self._first_connection()
        conn.wait_s = DETECT_S
        await conn.play([Until.ASKED])
        conn.wait_s = s.wait_s
        greets = _said(conn, SENDCHKPASS)
        if not greets:
            await conn.play([Send(FETCH), Until.ANSWERED])
            if not any(_said(conn, word) for word in HANDSHAKE_WORDS):
                await conn.finish()
                return Target(Mode.VPN, b"", _channels(conn.session), seed=s.seed)
            await conn.finish()
            conn = await self._first_connection()
        if s.password is None:
            await conn.finish()
            raise ProbeError(f"{self.target_text} asks for a password (Winsock): give it with --password")
        target = Target(Mode.WINSOCK, s.password, (), seed=s.seed, greets=greets)
        await conn.play(opening(target)[1 if greets else 0:])
        await conn.finish()
        if _said(conn, FAILED_VALIDATION):
            raise ProbeError(f"{self.target_text} refused the password ('Failed Validation'): "
                             "give the right one with --password")
        return Target(Mode.WINSOCK, s.password, _channels(conn.session), seed=s.seed, greets=greets)

    async def run(self, case: ServerCase, target: Target) -> CaseResult:
        """One case, judged; skipped when it cannot run there or the server is down."""
        started = time.monotonic()

        def result(verdict: Outcome, findings: tuple = (), why: str = "", conn: int | None = None) -> CaseResult:
            return CaseResult(case.id, case.title, case.spec, verdict, findings, why,
                              conn if self.recording is not None else None, time.monotonic() - started)

        if self.down:
            return result(Outcome.SKIP, why=f"not run: {self.down}")
        plan = case.plan(target)
        if isinstance(plan, str):
            return result(Outcome.SKIP, why=plan)
        first = self.conns + 1
        conns: list[_Conn] = []
        try:
            for _ in range(case.connections):
                conns.append(await self._connect())
        except (TimeoutError, OSError) as e:
            for conn in conns:
                await conn.finish()
            self.down = f"{self.target_text} stopped accepting connections (case {case.id})"
            return result(Outcome.FAIL, judge(case, target, [], down=f"the connection was refused: {reason(e)}")[1],
                          conn=first)
        await asyncio.gather(*(conn.play(plan) for conn in conns))
        traces = [await conn.finish() for conn in conns]
        down = ""
        if any(t.closed_early for t in traces):
            why = await try_upstream(self.settings.host, self.settings.port, CONNECT_S)
            if why is not None:
                down = f"after this case the server accepts no connection ({why})"
                self.down = f"{self.target_text} stopped accepting connections after case {case.id}"
        verdict, findings, why = judge(case, target, traces, down)
        return result(verdict, findings, why, first)


async def probe_server(settings: ProbeSettings, cases: list[ServerCase],
                       on_case: Callable[[int, CaseResult], None] | None = None) -> ProbeReport:
    """Every case of ``cases`` against the server; ``on_case(index, result)`` after each. Raises ProbeError."""
    probe = ServerProbe(settings)
    started = time.monotonic()
    await probe.start()
    try:
        target = await probe.discover()
        report = ProbeReport(probe.target_text, "server", seed=settings.seed, mode=str(target.mode))
        for index, case in enumerate(cases):
            result = await probe.run(case, target)
            report.cases.append(result)
            if on_case is not None:
                on_case(index, result)
    finally:
        await probe.close()
    report.recording = probe.recording_path
    report.seconds = time.monotonic() - started
    return report
