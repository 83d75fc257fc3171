"""The recording proxy against tiny loopback servers: bytes forwarded exactly,
recorded exactly, and no connection's trouble reaching another."""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import random
import re
import socket
import struct
import threading

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.sniffer.record.proxy import TRANSPORT_HIGH_WATER
from tests.record_support import (
    LOCAL,
    WAIT,
    EchoServer,
    ScriptedServer,
    both_ways,
    check_frames,
    closed_port,
    events,
    frame_items,
    read_all,
    recording,
    running_record,
)
from tests.streams import stream_pieces


def _cut(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


# -- byte-exactness with random payloads and segmentations ---------------------------------------------


class _Background:
    """A ScriptedServer and a recording running in a loop on another thread, so
    each hypothesis example can be a plain blocking client."""

    def __init__(self, path: str) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.path = path

    def run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(WAIT)

    async def start(self) -> None:
        self.server = ScriptedServer()
        await self.server.__aenter__()
        # secrets kept: a server that says nothing leaves the client's bytes undecided,
        # and a redacting recording masks them (tests/test_secrets.py)
        self.ctx = recording(self.server.port, self.path, keep_secrets=True)
        self.rec = await self.ctx.__aenter__()

    async def stop(self) -> None:
        await self.ctx.__aexit__(None, None, None)
        await self.server.__aexit__(None, None, None)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(WAIT)
        self.loop.close()


def _exchange(port: int, tag: bytes, c2s_pieces: list[bytes]) -> bytes:
    with socket.create_connection((LOCAL, port), timeout=WAIT) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(tag)
        for piece in c2s_pieces:
            s.sendall(piece)
        s.shutdown(socket.SHUT_WR)
        got = bytearray()
        while data := s.recv(65536):
            got += data
        return bytes(got)


@pytest.mark.slow
def test_random_payloads_and_segmentations_arrive_and_are_recorded_exactly(tmp_path):
    bg = _Background(str(tmp_path / "exact.mcap"))
    expected: dict[bytes, tuple[bytes, bytes]] = {}
    tags = itertools.count(1)
    try:
        bg.run(bg.start())
        port = bg.rec.proxy.port

        @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
        @given(c2s=st.one_of(stream_pieces().map(b"".join), st.binary(max_size=3000)),
               s2c=st.binary(max_size=3000),
               c2s_cuts=st.lists(st.integers(0, 4000), max_size=12),
               s2c_cuts=st.lists(st.integers(0, 4000), max_size=12))
        def one_connection(c2s: bytes, s2c: bytes, c2s_cuts: list[int], s2c_cuts: list[int]) -> None:
            tag = struct.pack(">Q", next(tags))
            bg.server.replies[tag] = _cut(s2c, s2c_cuts)
            got = _exchange(port, tag, _cut(c2s, c2s_cuts))
            assert got == s2c  # the client got exactly what the server sent
            expected[tag] = (tag + c2s, s2c)

        one_connection()
        bg.run(bg.stop())
    finally:
        bg.close()
    assert {tag: bg.server.received[tag] for tag in expected} == {t: c for t, (c, _) in expected.items()}
    recorded = both_ways(bg.path)
    by_topic = read_all(bg.path)
    by_tag = {recorded[(conn, "c2s")][:8]: conn for conn, d in recorded if d == "c2s"}
    assert set(by_tag) == set(expected)
    for tag, (c2s, s2c) in expected.items():
        conn = by_tag[tag]
        assert recorded[(conn, "c2s")] == c2s
        assert recorded.get((conn, "s2c"), b"") == s2c
        # every byte went through the live framer, with the same items as framing the whole stream
        # (a run of unframed bytes and line breaks may be one message)
        check_frames(by_topic["/frames"], conn, "c2s", c2s)


# -- lifecycle ---------------------------------------------------------------------------------------------


async def test_half_close_passes_through_both_ways(tmp_path):
    path = tmp_path / "half.mcap"

    async def late_talker(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        got = await reader.read(-1)  # until the client's FIN
        writer.write(b"after your FIN: " + got)
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(late_talker, LOCAL, 0)
    async with recording(server.sockets[0].getsockname()[1], path) as rec:
        reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
        writer.write(b"rr1-24--0--0-ss1")
        writer.write_eof()
        answer = await asyncio.wait_for(reader.read(-1), WAIT)
        writer.close()
        assert answer == b"after your FIN: rr1-24--0--0-ss1"
    server.close()
    by_topic = read_all(str(path))
    assert events(by_topic, 1) == ["opened", "upstream_connected", "half_closed", "half_closed", "closed"]
    halves = [e["by"] for e in by_topic["/tcp/events"] if e["event"] == "half_closed"]
    assert halves == ["client", "server"]
    assert both_ways(str(path)) == {(1, "c2s"): b"rr1-24--0--0-ss1",
                                    (1, "s2c"): b"after your FIN: rr1-24--0--0-ss1"}


async def test_upstream_down_resets_the_client_and_is_recorded(tmp_path):
    """The client is reset (as docs/recorder.md says), whether it sent
    something first or not: never a FIN, which would look like a server that
    answered and closed."""
    path = tmp_path / "down.mcap"
    port = closed_port()
    async with recording(port, path, connect_timeout=WAIT) as rec:
        for request in (b"rr1-24--0--0-ss1", b""):
            reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
            writer.write(request)
            with pytest.raises(ConnectionResetError):
                await asyncio.wait_for(reader.read(-1), WAIT)
            writer.close()
        # the upstream comes back: the same proxy now forwards
        echo = await asyncio.start_server(_echo, LOCAL, port, reuse_address=True)
        reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
        writer.write(b"hello")
        assert await asyncio.wait_for(reader.readexactly(5), WAIT) == b"hello"
        writer.close()
        summary = await rec.stop()
        echo.close()
    assert summary["upstream_failures"] == 2 and summary["connections"] == 3
    by_topic = read_all(str(path))
    for conn in (1, 2):
        assert events(by_topic, conn) == ["opened", "upstream_failed", "closed"]
    failed = [e for e in by_topic["/tcp/events"] if e["event"] == "upstream_failed"]
    assert all("refused" in e["detail"].lower() for e in failed)
    assert both_ways(str(path))[(3, "s2c")] == b"hello"
    assert any(re.fullmatch(rf"#1 reset after \d+\.\d\d s: cannot connect to {LOCAL}:{port}: Connection refused; "
                            r"the client's connection was reset \(c2s \d+ B, not forwarded\)", line)
               for line in rec.lines), rec.lines


@pytest.mark.slow
async def test_record_says_at_start_that_the_upstream_refuses(tmp_path):
    """whiztap record tries the upstream once as it starts: a wrong
    --upstream is said at once, and the recording runs anyway."""
    port = closed_port()
    async with running_record(port, tmp_path / "r.mcap") as rec:
        line = (await asyncio.wait_for(rec.proc.stderr.readline(), WAIT)).decode()
        assert line == (f"warning: the upstream {LOCAL}:{port} does not accept connections (Connection refused); "
                        "recording anyway: each client is reset until it does\n")
        # the reset can come before this loop sees its connect done (under load):
        # then the connect itself fails with it, which is the same word to the client
        with pytest.raises(ConnectionResetError):
            reader, writer = await rec.connect()
            try:
                await asyncio.wait_for(reader.read(-1), WAIT)
            finally:
                writer.close()
        code, out, err = await rec.finish()
    assert code == 0 and err == "", err
    assert "reset after" in out and "recorded 1 connection" in out, out


@pytest.mark.slow
async def test_record_says_nothing_of_an_upstream_that_listens(tmp_path):
    async with EchoServer() as server, running_record(server.port, tmp_path / "r.mcap") as rec:
        await asyncio.wait_for(_until(lambda: len(server.received) == 1), WAIT)  # the start's try, closed at once
        code, _, err = await rec.finish()
    assert code == 0 and err == "" and server.received == [bytearray()], err


async def _until(condition) -> None:
    while not condition():
        await asyncio.sleep(0.01)


async def _echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    while data := await reader.read(65536):
        writer.write(data)
        await writer.drain()
    writer.close()


async def test_client_vanishing_mid_frame_harms_nobody_else(tmp_path):
    path = tmp_path / "midframe.mcap"
    async with EchoServer() as server, recording(server.port, path) as rec:
        steady_r, steady_w = await asyncio.open_connection(LOCAL, rec.proxy.port)
        # a client that sends half a frame and resets the connection
        s = socket.create_connection((LOCAL, rec.proxy.port))
        s.sendall(b"rr1-2--0")
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        await asyncio.sleep(0)
        for _ in range(200):  # until the proxy has read the half frame
            if len(server.received) >= 2 and server.received[1] == b"rr1-2--0":
                break
            await asyncio.sleep(0.01)
        s.close()  # RST
        for i in range(20):
            frame = b"rr1-%d--0--0-ss1" % i
            steady_w.write(frame)
            assert await asyncio.wait_for(steady_r.readexactly(len(frame)), WAIT) == frame
        steady_w.close()
    by_topic = read_all(str(path))
    assert both_ways(str(path))[(2, "c2s")] == b"rr1-2--0"
    assert frame_items(by_topic["/frames"], 2, "c2s") == [("unframed", b"rr1-2--0")]
    closed = [e for e in by_topic["/tcp/events"] if e["conn"] == 2 and e["event"] == "closed"]
    assert closed[0]["by"] == "client"
    assert any(v["rule_id"] == "PW-FRAME-TRUNCATED" and v["conn"] == 2 for v in by_topic["/violations"])
    assert len(frame_items(by_topic["/frames"], 1, "c2s")) == 20


async def test_a_hundred_concurrent_clients(tmp_path):
    path = tmp_path / "hundred.mcap"
    rng = random.Random(4)
    async with EchoServer() as server, recording(server.port, path) as rec:

        async def client(n: int) -> bytes:
            reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
            sent = b""
            for k in range(5):
                frame = b"rr1-%d--%d--0-ss1" % (n % 24, k)
                writer.write(frame)
                sent += frame
                assert await asyncio.wait_for(reader.readexactly(len(frame)), WAIT) == frame
            writer.write(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 2000))))
            writer.write_eof()
            rest = await asyncio.wait_for(reader.read(-1), WAIT)
            writer.close()
            return sent + rest

        echoed = await asyncio.gather(*(client(n) for n in range(100)))
        summary = await rec.stop()
    assert summary["connections"] == 100
    recorded = both_ways(str(path))
    assert len(recorded) == 200
    assert sorted(recorded[(c, "s2c")] for c in range(1, 101)) == sorted(echoed)
    assert sorted(bytes(r) for r in server.received) == sorted(echoed)
    for conn in range(1, 101):
        assert recorded[(conn, "c2s")] == recorded[(conn, "s2c")]


@pytest.mark.slow
async def test_a_client_that_stops_reading_does_not_grow_the_proxy(tmp_path):
    path = tmp_path / "backpressure.mcap"
    # random digits: more than every kernel buffer on the way can hold, and cheap
    # to record (they frame as a few large unframed items)
    flood = random.Random(1).randbytes(16 << 20).translate(bytes(48 + b % 10 for b in range(256)))

    async def flooder(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(flood)  # the server's own buffer takes what TCP will not
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(flooder, LOCAL, 0)
    async with recording(server.sockets[0].getsockname()[1], path) as rec:
        reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port, limit=1 << 16)
        reader._transport.pause_reading()  # this client stops reading
        conn = None
        for _ in range(500):
            await asyncio.sleep(0.01)
            conn = next(iter(rec.proxy.connections.values()), None)
            if conn is not None and conn.upstream.received > (2 << 20):
                break
        high = 0
        for _ in range(50):  # while the server is blocked, the proxy holds at most one buffer
            await asyncio.sleep(0.01)
            high = max(high, conn.client.transport.get_write_buffer_size())
        assert high <= TRANSPORT_HIGH_WATER + (1 << 20)
        assert conn.upstream.received < len(flood)  # the proxy stopped pulling from the server
        reader._transport.resume_reading()
        got = await asyncio.wait_for(reader.read(-1), WAIT)
        writer.close()
        assert got == flood
    server.close()
    assert both_ways(str(path))[(1, "s2c")] == flood


@pytest.mark.parametrize("keep", [False, True])
async def test_password_redacted_in_every_channel_unless_kept(tmp_path, keep):
    path = tmp_path / "secret.mcap"
    secret = b"hunter2-\x01zz"

    async def winsock(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"sendchkpass")
        await writer.drain()
        got = b""
        while len(got) < len(secret):  # the password arrives in pieces, with no terminator
            got += await reader.read(3)
        writer.write(b"readytogo")
        await writer.drain()
        frame = await reader.readexactly(16)
        writer.write(b"sr1-\x02200200-ss1" if frame == b"rr1-24--0--0-ss1" else b"?")
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(winsock, LOCAL, 0)
    async with recording(server.sockets[0].getsockname()[1], path, keep_secrets=keep) as rec:
        reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
        assert await reader.readexactly(11) == b"sendchkpass"
        for i in range(0, len(secret), 3):
            writer.write(secret[i:i + 3])
            await writer.drain()
            await asyncio.sleep(0.01)
        assert await reader.readexactly(9) == b"readytogo"
        writer.write(b"rr1-24--0--0-ss1")
        assert await asyncio.wait_for(reader.read(-1), WAIT) == b"sr1-\x02200200-ss1"
        writer.close()
    server.close()
    recorded = both_ways(str(path))
    by_topic = read_all(str(path))
    password = [f for f in by_topic["/frames"] if f["kind"] == "password"]
    assert len(password) == 1 and password[0]["fields"]["length"] == len(secret)
    if keep:
        assert recorded[(1, "c2s")] == secret + b"rr1-24--0--0-ss1"
    else:
        assert recorded[(1, "c2s")] == b"*" * len(secret) + b"rr1-24--0--0-ss1"
        assert password[0]["text"] == "<redacted>" and password[0]["redacted"] is True
        assert sum(len(r.get("redacted", [])) for r in by_topic["/tcp/reads"]) >= 1
        everything = json.dumps(by_topic)
        assert "hunter2" not in everything
        assert all(b"hunter2" not in base64.b64decode(m[key]) for messages in by_topic.values()
                   for m in messages for key in ("data", "raw") if key in m)
