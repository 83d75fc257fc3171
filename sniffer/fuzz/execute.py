"""One execution: a fuzz session played against a server over TCP, judged.

Each frame is written (in pieces when it is cut, with a pause between them so
that each piece reaches the server in a read of its own), after the answers
the judge says are owed have come, unless it is pipelined.  The session ends
with the sync request (Fetch Configuration Settings) when the handshake let
it through: its answer says the server got through everything before it,
so a server that dies on a frame is caught in the execution that sent it.

What goes wrong: the server stops accepting connections, or closes the
connection while it owes an answer (``crash``); an owed answer does not come
within the deadline (``hang``); the analyzer's session finds a rule the server
broke (``violation``).
"""

from __future__ import annotations

import asyncio
import socket
import time
from dataclasses import dataclass

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.fuzz.grammar import SYNC_FRAME, Frame, Knowledge, Session, prelude
from whiztap.analyzer.fuzz.judge import CRASH, HANG, VIOLATION, Judge, Verdict
from whiztap.analyzer.protocol.handshake import SENDCHKPASS, Mode
from whiztap.analyzer.protocol.text import plural

SPLIT_PAUSE = 0.005  # seconds between the pieces of a cut frame, so each is a read of its own
GREETING_WAIT = 0.5  # how long a server has to say 'sendchkpass' before it is taken for a VPN one
READ_SIZE = 65536


class FuzzError(WhiztapError):
    """The fuzzer cannot run: the target cannot be reached or refuses the password."""


@dataclass(frozen=True, slots=True)
class Outcome:
    """An execution's result: its verdict (None: nothing wrong), what the
    server did (for the corpus), and whether the server closed the connection."""

    verdict: Verdict | None
    behaviour: tuple[str, ...] = ()
    closed: bool = False


def _now() -> int:
    return time.monotonic_ns()


class _Connection:
    """The client side of one execution, feeding the judge as it goes."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, judge: Judge,
                 deadline: float) -> None:
        self.reader, self.writer, self.judge, self.deadline = reader, writer, judge, deadline
        self.closed = False  # the server closed or reset

    async def settle(self) -> Verdict | None:
        """Read until nothing is owed; a crash or hang verdict if it never is,
        or the server's first breach as soon as it is seen."""
        loop = asyncio.get_running_loop()
        end = loop.time() + self.deadline
        while (owed := self.judge.due()) > 0:
            if (breach := self.judge.breach()) is not None:
                return breach  # no need to wait for what comes after it
            if self.closed:
                return Verdict(CRASH, f"the server closed the connection owing {plural(owed, 'answer')}")
            left = end - loop.time()
            try:
                data = await asyncio.wait_for(self.reader.read(READ_SIZE), max(left, 0))
            except TimeoutError:
                return Verdict(HANG, f"{plural(owed, 'answer')} owed, none within {self.deadline:g} s")
            except OSError:
                data = b""
            if not data:
                self.closed = True
                continue
            self.judge.server(data, _now())
        return None

    async def send(self, frame: Frame, password: bytes) -> bool:
        """Write the frame's pieces; False when the connection is gone."""
        pieces = frame.pieces(password)
        for n, piece in enumerate(pieces):
            if n:
                await asyncio.sleep(SPLIT_PAUSE)
            if self.writer.transport.is_closing():
                self.closed = True
                return False
            try:
                self.writer.write(piece)
                await self.writer.drain()
            except (OSError, RuntimeError):  # RuntimeError: uvloop's word for a transport gone meanwhile
                self.closed = True
                return False
            self.judge.client(piece, _now())
        return True

    async def play(self, frames: Session, password: bytes, sync: bool) -> Verdict | None:
        """The frames, then the sync request; the first verdict."""
        verdict = await self._frames(frames, password)
        if verdict is None and sync and self.judge.ready and not self.closed:
            await self.send(SYNC_FRAME, password)
            verdict = await self.settle()
        return verdict

    async def _frames(self, frames: Session, password: bytes) -> Verdict | None:
        for n, frame in enumerate(frames):
            # the first frame waits for the greeting, pipelined or not: a Winsock
            # server speaks first, and a frame sent before that would make its
            # greeting look out of order
            if (not n or not frame.pipelined) and (verdict := await self.settle()) is not None:
                return verdict
            if self.closed or not await self.send(frame, password):
                return None
        return await self.settle()

    def close(self) -> None:
        try:
            self.writer.transport.abort() if self.closed else self.writer.close()
        except OSError:
            pass


async def _connect(address: tuple[str, int], deadline: float) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.wait_for(asyncio.open_connection(*address), deadline)
    sock = writer.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return reader, writer


async def execute(address: tuple[str, int], session: Session, knowledge: Knowledge, password: bytes,
                  deadline: float, sync: bool = True) -> Outcome:
    """Play ``session`` on a new connection and judge it."""
    judge = Judge(knowledge.mode, password, knowledge.channels)
    try:
        reader, writer = await _connect(address, deadline)
    except (OSError, TimeoutError):
        return Outcome(Verdict(CRASH, "the server stopped accepting connections"), closed=True)
    conn = _Connection(reader, writer, judge, deadline)
    try:
        verdict = await conn.play(session, password, sync)
    finally:
        conn.close()
    judge.close(_now())
    if verdict is None:
        verdict = judge.breach()
    return Outcome(verdict, judge.behaviour(), conn.closed)


async def alive(address: tuple[str, int], knowledge: Knowledge, password: bytes, deadline: float) -> bool:
    """Whether the server still serves: a connection that gets its greeting
    (Winsock) or the answer to the sync request (VPN)."""
    frames = () if knowledge.mode is Mode.WINSOCK else (SYNC_FRAME,)
    outcome = await execute(address, frames, knowledge, password, deadline, sync=False)
    return outcome.verdict is None or outcome.verdict.kind not in (CRASH, HANG)


async def greeting(address: tuple[str, int], deadline: float) -> Mode:
    """The server's handshake: Winsock when it says 'sendchkpass' first."""
    try:
        reader, writer = await _connect(address, deadline)
    except (OSError, TimeoutError) as e:
        raise FuzzError(f"cannot connect to {address[0]}:{address[1]} ({e or 'timed out'}): "
                        "is the server running there?") from None
    try:
        first = await asyncio.wait_for(reader.readexactly(len(SENDCHKPASS)), GREETING_WAIT)
    except (TimeoutError, asyncio.IncompleteReadError, OSError):
        first = b""
    finally:
        writer.transport.abort()
    return Mode.WINSOCK if first == SENDCHKPASS else Mode.VPN


async def learn(address: tuple[str, int], password: bytes, deadline: float) -> Knowledge:
    """What ``discover`` learns, for a caller that judges the server by its own executions."""
    return (await discover(address, password, deadline))[0]


async def discover(address: tuple[str, int], password: bytes, deadline: float) -> tuple[Knowledge, Verdict | None]:
    """The server's handshake and the channels it configures, or a FuzzError
    saying why not.  A rule the server breaks on the way (a malformed
    Configuration Settings, a handshake out of step) is returned as the
    run's first finding rather than stopping it: it is a defect like any other,
    and the fuzzer goes on with what it learned (no channels, perhaps)."""
    mode = await greeting(address, deadline)
    if mode is Mode.WINSOCK and not password:
        raise FuzzError("the server asks for a password (winsock): give --password or set WHIZTAP_PASSWORD")
    knowledge = Knowledge.of(mode, ())
    judge = Judge(mode, password)
    reader, writer = await _connect(address, deadline)
    conn = _Connection(reader, writer, judge, deadline)
    try:
        verdict = await conn.play(prelude(knowledge), password, sync=False) or judge.breach()
    finally:
        conn.close()
    if mode is Mode.WINSOCK and not judge.ready:
        raise FuzzError("the server did not accept the password: give the right one with --password")
    if (verdict is not None and verdict.kind != VIOLATION) or (verdict is None and not judge.session.channel_map):
        detail = verdict.detail if verdict is not None else "no Configuration Settings came"
        raise FuzzError(f"the server did not answer Fetch Configuration Settings ({detail})")
    channels = judge.session.channel_map
    return Knowledge.of(mode, (channels[ch] for ch in sorted(channels))), verdict


async def checked(address: tuple[str, int], session: Session, knowledge: Knowledge, password: bytes,
                  deadline: float) -> tuple[Outcome, bool]:
    """An execution, then whether the server still serves (asked after every
    one: a frame may kill it after the last answer came); True when it is
    down, and the verdict is then a crash."""
    outcome = await execute(address, session, knowledge, password, deadline)
    verdict = outcome.verdict
    if await alive(address, knowledge, password, deadline):
        return outcome, False
    detail = f" ({verdict.detail})" if verdict is not None and verdict.kind == CRASH else ""
    return Outcome(Verdict(CRASH, "the server stopped accepting connections" + detail), outcome.behaviour, True), True
