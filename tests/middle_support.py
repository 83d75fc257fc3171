"""Helpers for the tests of the proxy in the middle (test_faults.py,
test_scripts.py): a recording proxy with faults or scripts in front of the
simulator, a plain client that sees exact bytes and their arrival times, and
readers of what the recording says was sent, delivered and changed."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import socket
import threading
import time
from collections import defaultdict
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

from whiztap.analyzer.mitm.spec import FaultSpec, parse_fault
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import decode, encode
from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.analyzer.traffic import Intervention
from whiztap.sniffer.record.record_run import MiddleSettings, Recording, RecordSettings
from whiztap.sniffer.sim.simulator import Simulator
from tests.record_support import LOCAL, WAIT, ScriptedServer, read_all



def sensor(ch: int) -> bytes:
    return encode(m.SensorRequest(ch))


def answer_channel(raw: bytes) -> int:
    return decode(ItemKind.RESPONSE, raw).message.channel


# -- the proxy in the middle, in the test's loop -----------------------------------------------------


@dataclass
class Middle:
    """A recording proxy with faults or scripts in front of the simulator
    ``server``; what it reported on stderr (``warnings``) and what the event
    loop saw go wrong meanwhile (``loop_errors``)."""

    server: Simulator
    rec: Recording
    path: Path
    warnings: list[str] = field(default_factory=list)
    loop_errors: list[dict] = field(default_factory=list)

    @property
    def port(self) -> int:
        return self.rec.proxy.port

    def topics(self) -> dict[str, list[dict]]:
        """The finished recording by topic (after the ``middle`` block)."""
        return read_all(str(self.path))


@contextlib.asynccontextmanager
async def middle(path: Path, *faults: str | FaultSpec, seed: int | None = 1,
                 scripts: tuple[str, ...] = ()) -> AsyncIterator[Middle]:
    """The simulator (VPN mode, seed 7) and a recording proxy in front of it
    with ``faults`` and ``scripts``, recording to ``path``; finished on exit.
    Secrets are kept: these tests compare the bytes each side got, and a
    client's bytes before its login is over are masked otherwise
    (tests/test_middle_secrets.py)."""
    specs = tuple(parse_fault(f) if isinstance(f, str) else f for f in faults)
    loop = asyncio.get_running_loop()
    handler = loop.get_exception_handler()
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        settings = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(path), keep_secrets=True,
                                  middle=MiddleSettings(faults=specs, scripts=scripts, seed=seed))
        warnings: list[str] = []
        mid = Middle(sim, Recording(settings, warn=warnings.append), path, warnings)
        await mid.rec.start()
        loop.set_exception_handler(lambda _loop, context: mid.loop_errors.append(context))
        try:
            yield mid
        finally:
            loop.set_exception_handler(handler)
            if mid.rec.summary is None:
                await mid.rec.stop()


class Raw:
    """A plain client connection: exact bytes out, framed items in, each with
    the monotonic time it arrived."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.framer = Framer()
        self.items: list[tuple[float, bytes]] = []

    @classmethod
    async def open(cls, port: int) -> Raw:
        return cls(*await asyncio.open_connection(LOCAL, port))

    async def send(self, *frames: bytes) -> None:
        self.writer.write(b"".join(frames))
        await self.writer.drain()

    async def take(self, n: int, timeout: float = WAIT) -> list[bytes]:
        """Wait until ``n`` items (line breaks aside) have come; all of them so far."""
        async with asyncio.timeout(timeout):
            while len(self.items) < n:
                data = await self.reader.read(65536)
                assert data, f"EOF after {len(self.items)} items, waiting for {n}"
                now = time.monotonic()
                self.items += [(now, i.raw) for i in self.framer.feed(data, 0) if i.kind is not ItemKind.EOL]
        return [raw for _, raw in self.items]

    async def nothing_more(self, n: int) -> list[bytes]:
        """``n`` items came, and nothing else before the server's end."""
        got = await self.until_quiet()
        assert len(got) == n, f"{len(got)} items, not {n}: {got}"
        return got

    async def until_quiet(self) -> list[bytes]:
        """Every item that comes before the server's end of the connection.

        The client half-closes: the simulator answers what it read, then
        closes, and the proxy passes that end only after every frame it holds
        or delays.  So "nothing more" is known when the end comes, where a
        test waiting a quiet while would sleep and still guess."""
        self.writer.write_eof()
        async with asyncio.timeout(WAIT):
            while data := await self.reader.read(65536):
                now = time.monotonic()
                self.items += [(now, i.raw) for i in self.framer.feed(data, 0) if i.kind is not ItemKind.EOL]
        return [raw for _, raw in self.items]

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(ConnectionError, OSError):
            await self.writer.wait_closed()


class Reads(asyncio.Protocol):
    """A client that keeps the size of every read."""

    def __init__(self) -> None:
        self.sizes: list[int] = []
        self.data = bytearray()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.sizes.append(len(data))
        self.data += data

    async def until(self, size: int) -> None:
        async with asyncio.timeout(WAIT):
            while len(self.data) < size:
                await asyncio.sleep(0.005)


def delivered(topics: dict[str, list[dict]], direction: str, conn: int = 1) -> list[bytes]:
    """What the proxy wrote toward the receiver, write by write."""
    return [base64.b64decode(d["data"]) for d in topics.get("/tcp/delivered", [])
            if d["dir"] == direction and d["conn"] == conn]


def sent(topics: dict[str, list[dict]], direction: str, conn: int = 1) -> bytes:
    """What the sender of ``direction`` sent, from /tcp/reads."""
    return b"".join(base64.b64decode(d["data"]) for d in topics["/tcp/reads"]
                    if d["dir"] == direction and d["conn"] == conn)


def actions(topics: dict[str, list[dict]], conn: int | None = None) -> list[str]:
    return [i["action"] for i in topics.get("/interventions", []) if conn is None or i["conn"] == conn]


def held_ns(topics: dict[str, list[dict]], direction: str, conn: int = 1) -> list[tuple[str, int]]:
    """Each frame of ``direction`` (its text) and how long the proxy held it,
    as the recording says: the t_ns of the write that delivered its first
    byte minus the t_ns of the read it came in.  For faults that change no
    byte (delay, bandwidth), offsets in /tcp/delivered are those of /frames.
    A recorded gap is data, not a wall-clock race: the proxy writes a held
    frame only once its clock has passed the frame's time plus the hold."""
    writes = sorted((d["offset"], d["t_ns"]) for d in topics.get("/tcp/delivered", [])
                    if d["dir"] == direction and d["conn"] == conn)
    held = []
    for f in topics["/frames"]:
        if f["dir"] == direction and f["conn"] == conn:
            [t_ns] = [t for offset, t in writes if offset <= f["offset"]][-1:]
            held.append((f["text"], t_ns - f["t_end_ns"]))
    return held


def items_of(data: bytes) -> list[bytes]:
    framer = Framer()
    return [i.raw for i in framer.feed(data, 0) + framer.end(1) if i.kind is not ItemKind.EOL]



# -- a recording with faults on a loop of its own (for hypothesis) ------------------------------------


class Taps:
    """The interventions, by connection, as the proxy tells its consumers."""

    def __init__(self) -> None:
        self.by_conn: dict[int, list[Intervention]] = defaultdict(list)

    def receive(self, event: object) -> None:
        if isinstance(event, Intervention):
            self.by_conn[event.conn].append(event)


class Background:
    """A ScriptedServer and a recording with ``faults``, on a loop in another
    thread, so that each hypothesis example is a plain blocking client."""

    def __init__(self, path: Path, faults: tuple[str, ...]) -> None:
        self.faults = faults
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.path = path
        self.taps = Taps()

    def run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(WAIT)

    async def start(self) -> None:
        self.server = ScriptedServer()
        await self.server.start()
        middle_settings = MiddleSettings(faults=tuple(parse_fault(f) for f in self.faults), seed=1)
        settings = RecordSettings((LOCAL, 0), (LOCAL, self.server.port), str(self.path), keep_secrets=True,
                                  middle=middle_settings)
        self.rec = Recording(settings, consumers=[self.taps])
        await self.rec.start()

    async def stop(self) -> None:
        await self.rec.stop()
        await self.server.close()

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(WAIT)
        self.loop.close()


def exchange(port: int, tag: bytes, pieces: list[bytes]) -> bytes:
    with socket.create_connection((LOCAL, port), timeout=WAIT) as s:
        s.sendall(tag)
        for piece in pieces:
            s.sendall(piece)
        s.shutdown(socket.SHUT_WR)
        got = bytearray()
        while data := s.recv(65536):
            got += data
        return bytes(got)
