"""Flow control of ``whiztap record`` run as a user runs it, against clients
that never read, slow readers and a flood, with the writer process made to
fall behind for real (SIGSTOP): the proxy's memory stays bounded, and one
connection's traffic never stalls another's."""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from whiztap.analyzer.recording.format import TOPIC_EVENTS
from whiztap.analyzer.recording.scan import RecordingScan
from tests.record_support import LOCAL, WAIT, RecordProcess, rebuild_streams, running_record

RSS_BOUND_KIB = 300 << 10  # the proxy process; it starts at about 30 MB
SAMPLE_S = 0.02
ROUND_TRIP_BOUND_S = 3.0  # generous: a loaded 2-core box answers in milliseconds
STOP_S = 4.0  # how long the writer is kept stopped
FLOOD_MARK = b"junk:"  # a connection that begins so is an upload the server drops
CHUNK = 1 << 16


# -- the parts: threaded servers and clients, so the test's own loop stays free -----------


class _ThreadedServer:
    """A blocking-socket server, one thread per connection; closed on exit."""

    def __init__(self) -> None:
        self.sock = socket.create_server((LOCAL, 0), backlog=256)
        self.sock.settimeout(0.1)  # accept() wakes to see the stop
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(0.1)
            self._conns.append(conn)
            thread = threading.Thread(target=self._guarded, args=(conn,), daemon=True)
            self._threads.append(thread)
            thread.start()

    def _guarded(self, conn: socket.socket) -> None:
        with contextlib.suppress(OSError):
            self.serve(conn)

    def serve(self, conn: socket.socket) -> None:
        raise NotImplementedError

    def __enter__(self) -> _ThreadedServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.sock.close()
        for conn in self._conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
        for thread in self._threads:
            thread.join(WAIT)
        for conn in self._conns:
            conn.close()


class Pusher(_ThreadedServer):
    """Sends to every client as fast as TCP takes it (digits: cheap to record,
    so the writer can catch up at the end)."""

    DATA = random.Random(2).randbytes(CHUNK).translate(bytes(48 + b % 10 for b in range(256)))

    def serve(self, conn: socket.socket) -> None:
        while not self.stop.is_set():
            with contextlib.suppress(TimeoutError):
                conn.send(self.DATA)


class EchoOrDrop(_ThreadedServer):
    """Echoes each connection's bytes, except a connection that begins with
    ``FLOOD_MARK``: an upload, read and dropped; ``uploads`` gets its length at its end."""

    def __init__(self) -> None:
        super().__init__()
        self.uploads: list[int] = []

    def serve(self, conn: socket.socket) -> None:
        echo: bool | None = None
        got = 0
        while not self.stop.is_set():
            try:
                data = conn.recv(1 << 20)
            except TimeoutError:
                continue
            if not data:
                break
            if echo is None:
                echo = not data.startswith(FLOOD_MARK)
            if echo:
                conn.sendall(data)
            got += len(data)
        if echo is False:
            self.uploads.append(got)


class _SocketThread:
    """A client socket served by a thread of its own until ``finish()``."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection((LOCAL, port))
        self.sock.settimeout(0.1)
        self.stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        raise NotImplementedError

    def finish(self) -> None:
        self.stop.set()
        self._thread.join(WAIT)
        self.sock.close()


class Flood(_SocketThread):
    """A client sending binary junk as fast as the proxy takes it, from a thread.

    Bytes 0x80-0xff, nothing a frame can begin with: the writer records them
    several times faster than random bytes, so the test stays short.  SIGSTOP
    of the writer, not the cost of the junk, is what makes the backlog."""

    DATA = random.Random(3).randbytes(1 << 20).translate(bytes(0x80 | b for b in range(256)))

    def __init__(self, port: int) -> None:
        self.sent = 0
        super().__init__(port)

    def _run(self) -> None:
        self.sock.sendall(FLOOD_MARK)
        self.sent = len(FLOOD_MARK)
        data = memoryview(self.DATA)
        while not self.stop.is_set():
            at = (self.sent - len(FLOOD_MARK)) % len(data)
            with contextlib.suppress(TimeoutError):
                self.sent += self.sock.send(data[at:at + CHUNK])

    def at(self, offset: int, length: int) -> bytes:
        """The bytes sent at ``offset`` of the stream (the mark, then DATA over and over)."""
        got = bytearray(FLOOD_MARK[offset:offset + length])
        offset = max(offset - len(FLOOD_MARK), 0)
        while len(got) < length:
            at = offset % len(self.DATA)
            piece = self.DATA[at:at + length - len(got)]
            got += piece
            offset += len(piece)
        return bytes(got)

    def finish(self) -> None:
        self.stop.set()
        self._thread.join(WAIT)  # no send after the FIN
        self.sock.shutdown(socket.SHUT_WR)
        super().finish()


class FastReader(_SocketThread):
    """Reads and drops everything, from a thread: makes recorded traffic."""

    def __init__(self, port: int) -> None:
        self.received = 0
        super().__init__(port)

    def _run(self) -> None:
        while not self.stop.is_set():
            with contextlib.suppress(TimeoutError):
                self.received += len(self.sock.recv(1 << 20))


# -- the processes -----------------------------------------------------------------------------


def writer_pid(proxy_pid: int) -> int:
    """The writer process: the proxy's one child."""
    children: list[int] = []
    for task in os.listdir(f"/proc/{proxy_pid}/task"):
        children += map(int, Path(f"/proc/{proxy_pid}/task/{task}/children").read_text().split())
    assert len(children) == 1, children
    return children[0]


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for {pid}")


async def watch_memory(pid: int, seconds: float, bound_kib: int = RSS_BOUND_KIB, every_s: float = SAMPLE_S) -> int:
    """The proxy's highest resident size over ``seconds`` (KiB); fails at once above ``bound_kib``."""
    high = 0
    for _ in range(int(seconds / every_s)):
        high = max(high, rss_kib(pid))
        assert high < bound_kib, f"proxy resident size {high >> 10} MiB"
        await asyncio.sleep(every_s)
    return high


@contextlib.contextmanager
def writer_stopped(pid: int) -> Iterator[None]:
    """The writer frozen (a real backlog builds up in the proxy), then thawed."""
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(pid, signal.SIGCONT)


async def finish(rec: RecordProcess) -> None:
    code, _, err = await rec.finish()
    assert code == 0 and not err, err


# -- memory is bounded whatever the clients do -----------------------------------------------------


async def _never_reader(port: int, held: list) -> None:
    _reader, writer = await asyncio.open_connection(LOCAL, port, limit=1 << 16)
    writer.transport.pause_reading()
    held.append(writer)


async def _slow_reader(port: int, held: list) -> None:
    reader, writer = await asyncio.open_connection(LOCAL, port, limit=1 << 16)
    held.append(writer)
    with contextlib.suppress(ConnectionError):
        while await reader.read(1024):
            await asyncio.sleep(0.1)


@pytest.mark.slow
@pytest.mark.parametrize("clients", [(1, _never_reader), (20, _slow_reader)], ids=["never-reader", "20-slow"])
async def test_memory_bounded_with_readers_that_lag_before_during_and_after_a_backlog(tmp_path, clients):
    count, client = clients
    held: list[asyncio.StreamWriter] = []
    tasks: list[asyncio.Task] = []

    async def connect() -> None:
        tasks.extend(asyncio.create_task(client(rec.port, held)) for _ in range(count))
        await watch_memory(rec.proc.pid, 0.5)

    with Pusher() as server:
        async with running_record(server.port, tmp_path / "r.mcap") as rec:
            await connect()  # before any backlog
            fast = await asyncio.to_thread(FastReader, rec.port)
            try:
                for _ in range(int(WAIT * 20)):  # traffic flows (on a loaded machine it may take a while)
                    if fast.received:
                        break
                    await asyncio.sleep(0.05)
                assert fast.received > 0, "no traffic reached the fast reader before the backlog"
                with writer_stopped(writer_pid(rec.proc.pid)):
                    await watch_memory(rec.proc.pid, 1.0)  # the backlog fills
                    await connect()  # during it
                    await watch_memory(rec.proc.pid, 2.0)
                await connect()  # just after, as the writer catches up
                await watch_memory(rec.proc.pid, 2.0)
            finally:
                await asyncio.to_thread(fast.finish)
                for task in tasks:
                    task.cancel()
                for writer in held:
                    writer.close()
            await finish(rec)


# -- traffic is never held hostage by the recording --------------------------------------------------


async def _round_trips(port: int, until: asyncio.Event, done: list[float]) -> bytes:
    """Request/answer through the proxy until told to stop; each answer within
    ROUND_TRIP_BOUND_S (else TimeoutError); returns everything sent."""
    reader, writer = await asyncio.open_connection(LOCAL, port)
    sent = bytearray()
    try:
        for n in range(1_000_000):
            if until.is_set():
                break
            message = b"round trip %08d\n" % n
            writer.write(message)
            sent += message
            try:
                answer = await asyncio.wait_for(reader.readexactly(len(message)), ROUND_TRIP_BOUND_S)
            except TimeoutError:
                raise AssertionError(f"round trip {n} not answered within {ROUND_TRIP_BOUND_S} s") from None
            assert answer == message
            done.append(time.monotonic())
            await asyncio.sleep(0.005)  # a client with something to do between requests
    finally:
        writer.close()
    return bytes(sent)


def _gaps(out: Path, conn: int, direction: str) -> list[tuple[int, int]]:
    with open(out, "rb") as f:
        return [(e["offset"], e["length"]) for _, _, e in RecordingScan(f, (TOPIC_EVENTS,)).messages()
                if e["event"] == "gap" and e["conn"] == conn and e["dir"] == direction]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["pause", "gap"])
async def test_a_flood_never_stalls_another_connections_round_trips(tmp_path, mode):
    out = tmp_path / "flood.mcap"
    with EchoOrDrop() as server:
        options = ("--when-behind", mode) if mode != "pause" else ()  # pause is the default
        # --keep-secrets: no server greeting, so the junk would count as a possible password
        async with running_record(server.port, out, "--keep-secrets", *options) as rec:
            stop = asyncio.Event()
            done: list[float] = []
            talker = asyncio.create_task(_round_trips(rec.port, stop, done))  # connection 1
            while not done:
                await asyncio.sleep(0.01)
            flood = await asyncio.to_thread(Flood, rec.port)  # connection 2
            try:
                while flood.sent < (1 << 20):
                    await asyncio.sleep(0.01)
                with writer_stopped(writer_pid(rec.proc.pid)):
                    start = time.monotonic()
                    high = await watch_memory(rec.proc.pid, STOP_S)
                    during = sum(t > start + 0.5 for t in done)  # once the backlog is full
                    flooded = flood.sent
            finally:
                await asyncio.to_thread(flood.finish)
                stop.set()
                talked = await asyncio.wait_for(talker, WAIT)
            for _ in range(int(WAIT / 0.05)):  # the proxy passes on the flood's last bytes
                if server.uploads:
                    break
                await asyncio.sleep(0.05)
            assert server.uploads == [flood.sent]
            await finish(rec)
    assert during > 0, "no round trip while the writer was behind"  # before: every connection paused
    assert high < RSS_BOUND_KIB
    recorded = rebuild_streams(str(out))
    assert [s.data for s in recorded[(1, "c2s")]] == [talked]
    assert [s.data for s in recorded[(1, "s2c")]] == [talked]
    segments = recorded[(2, "c2s")]
    for s in segments:  # every recorded byte is the byte sent at that offset
        assert s.data == flood.at(s.offset, len(s.data))
    gaps = _gaps(out, 2, "c2s")
    covered = sorted([(s.offset, len(s.data)) for s in segments] + gaps)
    at = 0
    for offset, length in covered:  # reads and gaps tile the stream, no overlap, no hole
        assert offset == at, covered
        at += length
    assert at == flood.sent
    if mode == "pause":
        assert not gaps
    else:
        assert gaps and flooded > 16 << 20  # past the most the proxy holds for the writer: it went on, unrecorded
