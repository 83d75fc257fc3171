"""The gate in front of the live Foxglove server (sniffer/record/live_gate.py):
its verdict on any request head, and its bounds, against real sockets.  The
server behind it here is a plain TCP server standing for the SDK's, so the
tests can make it flood or wait; tests/test_foxglove_live.py checks the
gate in front of the real one with real WebSocket handshakes."""

from __future__ import annotations

import asyncio
import socket

import pytest
from hypothesis import given
from hypothesis import strategies as st

from whiztap.sniffer.record import live_gate
from whiztap.sniffer.record.live_gate import (
    HEAD_LIMIT,
    HIGH_WATER,
    MAX_CLIENTS,
    LiveGate,
    origin_allowed,
    origin_text,
    verdict,
)

from tests.record_support import LOCAL, WAIT

HANDSHAKE = ["GET / HTTP/1.1", "Host: 127.0.0.1:8765", "Upgrade: websocket", "Connection: Upgrade",
             "Sec-WebSocket-Version: 13", "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
             "Sec-WebSocket-Protocol: foxglove.sdk.v1"]
NONE: frozenset[str] = frozenset()


def head(*extra: str) -> bytes:
    return "\r\n".join(HANDSHAKE + list(extra)).encode("latin-1")


# -- the verdict on a request head ------------------------------------------------------------------


@given(st.binary(max_size=4096))
def test_any_bytes_get_a_verdict_and_never_an_exception(data):
    status, _ = verdict(data, NONE)
    assert status in (0, 400, 403)


_FIELD_TEXT = st.text(st.characters(min_codepoint=0x20, max_codepoint=0xFF, blacklist_characters="\x7f"),
                      max_size=60)


@pytest.mark.slow
@given(origin=_FIELD_TEXT.filter(lambda o: not origin_allowed(o.strip(" \t") or None, NONE)),
       name=st.sampled_from(["Origin", "origin", "ORIGIN", "oRiGiN"]),
       before=st.lists(st.tuples(st.from_regex(r"X-[A-Za-z0-9-]{1,12}", fullmatch=True), _FIELD_TEXT), max_size=4),
       where=st.integers(0, len(HANDSHAKE)))
def test_a_foreign_origin_is_never_served_however_the_head_is_written(origin, name, before, where):
    lines = HANDSHAKE[1:]
    lines.insert(min(where, len(lines)), f"{name}: {origin}")
    text = [HANDSHAKE[0]] + [f"{n}: {v}" for n, v in before] + lines
    status, _ = verdict("\r\n".join(text).encode("latin-1"), NONE)
    assert status == 403


@pytest.mark.parametrize("origin", [None, "https://app.foxglove.dev", "http://localhost", "https://localhost:3000",
                                    "http://127.0.0.1:8080", "http://[::1]:9", "HTTPS://App.Foxglove.Dev"])
def test_the_app_local_pages_and_no_origin_are_served(origin):
    extra = () if origin is None else (f"Origin: {origin}",)
    assert verdict(head(*extra), NONE) == (0, origin)


@pytest.mark.parametrize("origin", ["http://evil.example", "null", "https://app.foxglove.dev.evil.example",
                                    "http://localhost.evil.example", "http://127.0.0.1.evil.example:80",
                                    "file://", "https://app.foxglove.dev:444", "http://app.foxglove.dev"])
def test_other_origins_are_refused_unless_named(origin):
    assert verdict(head(f"Origin: {origin}"), NONE)[0] == 403
    assert verdict(head(f"Origin: {origin}"), frozenset({origin_text(origin)}))[0] == 0


def test_two_origins_or_no_websocket_upgrade_are_refused():
    assert verdict(head("Origin: http://localhost", "Origin: http://evil.example"), NONE)[0] == 403
    assert verdict(head().replace(b"Upgrade: websocket", b"Upgrade: h2c"), NONE)[0] == 400
    assert verdict(head().replace(b"GET ", b"POST "), NONE)[0] == 400
    assert verdict(head(" folded: line"), NONE)[0] == 400


@pytest.mark.parametrize("text", ["evil.example", "https://x.example/path", "http://a b", ""])
def test_an_origin_option_that_is_no_origin_is_refused(text):
    with pytest.raises(ValueError, match="is not an origin"):
        origin_text(text)


# -- the gate on real sockets ------------------------------------------------------------------------


class _Behind:
    """The server behind the gate: reads the request head, then sends
    ``flood`` bytes as fast as it is let (counted in ``sent``)."""

    def __init__(self, flood: int = 0) -> None:
        self.flood = flood
        self.sent = 0
        self.heads: list[bytes] = []
        self.server: asyncio.AbstractServer | None = None

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.heads.append(await reader.readuntil(b"\r\n\r\n"))
        block = bytes(64 << 10)
        try:
            while self.sent < self.flood:
                writer.write(block)
                await writer.drain()
                self.sent += len(block)
            writer.write(b"served")
            await writer.drain()
            await reader.read()
        except ConnectionError:
            pass
        writer.close()


@pytest.fixture
async def gate():
    """A LiveGate on a free port in front of a ``_Behind`` server; both stopped after."""
    behind = _Behind()
    behind.server = await asyncio.start_server(behind.serve, LOCAL, 0)
    sock = socket.create_server((LOCAL, 0), backlog=MAX_CLIENTS)
    sock.setblocking(False)
    warnings: list[str] = []
    g = LiveGate(sock, (LOCAL, behind.server.sockets[0].getsockname()[1]), (), warnings.append)
    g.behind, g.warnings, g.port = behind, warnings, sock.getsockname()[1]
    g.start()
    yield g
    g.loop.call_soon_threadsafe(g.loop.stop)
    behind.server.close()


async def test_an_allowed_viewer_is_spliced_through_byte_for_byte(gate):
    reader, writer = await asyncio.open_connection(LOCAL, gate.port)
    request = head("Origin: http://localhost:5173") + b"\r\n\r\nand what came after it"
    writer.write(request)
    assert await asyncio.wait_for(reader.readexactly(6), WAIT) == b"served"
    writer.close()
    assert gate.behind.heads == [request[:request.index(b"\r\n\r\n") + 4]]


async def test_a_viewer_that_stops_reading_stops_the_gate_reading(gate):
    """The server behind floods; the viewer reads nothing.  What the gate
    holds stays within its high-water mark and one read, and the server is
    held back (TCP pushes back on it) rather than the gate taking it all."""
    behind = gate.behind
    behind.flood = 256 << 20
    _reader, writer = await asyncio.open_connection(LOCAL, gate.port, limit=1 << 16)
    writer.transport.pause_reading()
    writer.write(head() + b"\r\n\r\n")
    quiet, last = 0, -1
    while quiet < 10 and behind.sent < behind.flood:  # until the server can send no more
        await asyncio.sleep(0.05)
        quiet, last = (quiet + 1, last) if behind.sent == last else (0, behind.sent)
    held = sum(c.client.transport.get_write_buffer_size() for c in list(gate.conns))
    assert held <= HIGH_WATER + (256 << 10), held
    assert behind.sent < behind.flood // 4, behind.sent
    writer.close()


async def test_a_viewer_that_ends_before_its_request_does_is_closed(gate, caplog):
    reader, writer = await asyncio.open_connection(LOCAL, gate.port)
    writer.write(b"GET / HTTP/1.1\r\nOrigin: http://localhost")
    writer.write_eof()
    assert await asyncio.wait_for(reader.read(-1), WAIT) == b""
    writer.close()
    await _until(lambda: not gate.conns)
    assert gate.behind.heads == []
    assert not [r for r in caplog.records if r.name == "asyncio"], caplog.text  # closed, not failed


async def test_a_head_too_large_or_too_slow_is_refused_and_closed(gate, monkeypatch):
    big = await _answer(gate.port, b"GET / HTTP/1.1\r\nX-Junk: " + b"a" * (HEAD_LIMIT + 1))
    assert big.startswith(b"HTTP/1.1 431 ")
    monkeypatch.setattr(live_gate, "HEAD_TIMEOUT_S", 0.1)
    assert await _answer(gate.port, b"GET / HTTP/1.1\r\n") == b""  # closed, nothing passed on
    assert gate.behind.heads == []


async def test_past_the_limit_a_connection_is_closed_at_once(gate):
    held = [await asyncio.open_connection(LOCAL, gate.port) for _ in range(MAX_CLIENTS)]
    try:
        await _until(lambda: len(gate.conns) == MAX_CLIENTS)
        assert await _answer(gate.port, head() + b"\r\n\r\n") == b""
        assert gate.behind.heads == []
    finally:
        for _, writer in held:
            writer.close()
    await _until(lambda: not gate.conns)


async def test_a_refused_origin_is_said_once_and_answered_403(gate):
    for _ in range(3):
        answer = await _answer(gate.port, head("Origin: http://evil.example\x1b[2J") + b"\r\n\r\n")
        assert answer.startswith(b"HTTP/1.1 403 Forbidden\r\n") and b"\x1b" not in answer
    assert gate.behind.heads == []
    [warning] = gate.warnings
    assert "http://evil.example\\x1b[2J" in warning and "\x1b" not in warning


# Every container the gate keeps, with its bound: a new one fails
# test_every_container_of_the_gate_is_registered_and_bounded until it joins.
READ = 256 << 10  # at most one read past a limit
GATE_BUFFERS: dict[str, dict[str, int]] = {
    "LiveGate": {"origins": 64, "conns": MAX_CLIENTS + 1},  # origins: those given with --foxglove-origin
    "_Refusals": {"said": live_gate.MAX_ORIGINS_SAID},
    "_Conn": {},
    "_Client": {"head": HEAD_LIMIT + READ},
    "_Side": {},
}


def _containers(gate) -> list[tuple[str, str, object]]:
    owners = [gate, gate.refusals]
    for conn in list(gate.conns):
        owners += [conn, conn.client] + ([conn.upstream] if conn.upstream is not None else [])
    return [(type(owner).__name__, name, value) for owner in owners for name, value in list(vars(owner).items())
            if isinstance(value, (bytes, bytearray, list, dict, set, frozenset)) and name not in _FIXTURE]


_FIXTURE = ("behind", "warnings", "port")  # what the fixture hangs on the gate for the tests


async def test_every_container_of_the_gate_is_registered_and_bounded(gate):
    """Abuse it every way at once: many refused origins, every slot taken
    by a connection sending a head that never ends (one of them past the
    limit), then look at every container it keeps."""
    for n in range(3 * live_gate.MAX_ORIGINS_SAID):
        await _answer(gate.port, head(f"Origin: http://evil{n}.example") + b"\r\n\r\n")
    held = [await asyncio.open_connection(LOCAL, gate.port) for _ in range(MAX_CLIENTS)]
    try:
        for _, writer in held:
            writer.write(b"GET / HTTP/1.1\r\nX-Junk: " + b"a" * (HEAD_LIMIT // 2))
        await _until(lambda: sum(len(c.client.head) for c in list(gate.conns)) >= MAX_CLIENTS * HEAD_LIMIT // 2)
        found = _containers(gate)
        assert {(owner, name) for owner, name, _ in found} <= {
            (owner, name) for owner, names in GATE_BUFFERS.items() for name in names}, found
        for owner, name, value in found:
            assert len(value) <= GATE_BUFFERS[owner][name], (owner, name, len(value))
        assert len(gate.warnings) == live_gate.MAX_ORIGINS_SAID + 1  # and one line saying more were refused
    finally:
        for _, writer in held:
            writer.close()


async def _answer(port: int, data: bytes) -> bytes:
    reader, writer = await asyncio.open_connection(LOCAL, port)
    writer.write(data)
    try:
        return await asyncio.wait_for(reader.read(-1), WAIT)
    except ConnectionResetError:
        return b""
    finally:
        writer.close()


async def _until(condition) -> None:
    for _ in range(int(WAIT * 100)):
        if condition():
            return
        await asyncio.sleep(0.01)
    raise AssertionError("never happened")
