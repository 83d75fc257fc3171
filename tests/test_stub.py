"""Serving a recording's server side: to the client library, a raw socket and ``whiztap client``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.sim.client import Client, ConnectionClosed, HandshakeError, ResponseTimeout
from whiztap.sniffer.sim.dialogue import Dialogue
from whiztap.sniffer.replay.stub import Stub
from tests.cli_support import run_process_async, start_process
from tests.record_support import LOCAL, WAIT, both_ways, recording
from tests.replay_support import (
    PASSWORD,
    SENSORS,
    client_session,
    record,
    simulator,
    until_closed,
)

C2S, S2C = Direction.C2S, Direction.S2C


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("stub") / "session.mcap"
    got = asyncio.run(record(path, seed=1))
    return path, got


@pytest.fixture(scope="module")
def two_connections(tmp_path_factory):
    """Two VPN connections, the same request answered differently in each."""
    path = tmp_path_factory.mktemp("stub2") / "two.mcap"

    def steps(value: int) -> list:
        return [(C2S, b"rr1-24--0--0-ss1"), (S2C, b"sr1-\x0d" + b"000" * 12 + b"200-ss1"),
                (C2S, b"rr1-12--0--0-ss1"), (S2C, b"cr1-12--%d--0-ss1" % value)]

    async def make() -> None:
        async with Dialogue() as peer, recording(peer.port, path) as rec:
            await peer.play(steps(100), (LOCAL, rec.proxy.port))
            await peer.play(steps(200), (LOCAL, rec.proxy.port))
            await asyncio.sleep(0.1)
            await rec.stop()

    asyncio.run(make())
    return load_exchanges(str(path))


async def test_the_client_library_gets_the_recorded_bytes(recorded, tmp_path):
    path, got = recorded
    again = tmp_path / "through-stub.mcap"
    lines: list[str] = []
    async with Stub(load_exchanges(str(path)), pace="recorded", rate=4.0, on_log=lines.append) as stub, \
            recording(stub.port, again) as rec:
        assert await client_session(rec.proxy.port) == got
        for _ in range(int(WAIT * 100)):
            if stub.finished.is_set():
                break
            await asyncio.sleep(0.01)
        await rec.stop()
    assert both_ways(str(again))[(1, "s2c")] == both_ways(str(path))[(1, "s2c")]
    assert stub.unanswered == [] and stub.connections == 1
    assert lines[0].startswith("#1 opened from 127.0.0.1:") and lines[-1] == "#1 closed"


async def test_a_raw_socket_client_gets_the_recorded_stream(recorded):
    path, _ = recorded
    streams = both_ways(str(path))
    c2s = streams[(1, "c2s")].replace(b"*" * len(PASSWORD), PASSWORD.encode(), 1)
    async with Stub(load_exchanges(str(path)), password=PASSWORD.encode()) as stub:
        reader, writer = await asyncio.open_connection(LOCAL, stub.port)
        writer.write(c2s)  # everything at once: password and requests in one write
        writer.write_eof()
        got = await asyncio.wait_for(reader.read(-1), WAIT)
        writer.close()
    assert got == streams[(1, "s2c")]


@pytest.mark.slow
async def test_whiztap_client_gets_what_the_simulator_gave_it(tmp_path):
    """The simulator's own test client, before (simulator) and after (stub)."""
    script = b"config\nsensor 12\nsensor 13\nservo 2 1500\nservo 2\nswitch 7 on\nsensor 12\n"
    path = tmp_path / "client.mcap"
    async with simulator(seed=1) as sim, recording(sim.port, path) as rec:
        code, before, err = await run_process_async("client", f"{LOCAL}:{rec.proxy.port}", "-p", PASSWORD, stdin=script)
        assert (code, err) == (0, "")
        await until_closed(sim)
        await rec.stop()
    proc = await start_process("stub", path, "--listen", "127.0.0.1:0", "--once", "--strict", "--password", PASSWORD)
    first = (await asyncio.wait_for(proc.stdout.readline(), WAIT)).decode()
    m = re.match(r"whiztap stub: serving .*client\.mcap on 127\.0\.0\.1:(\d+) \(1 recorded connection\)$",
                 first.rstrip("\n"))
    assert m, first
    code, after, err = await run_process_async("client", f"{LOCAL}:{m.group(1)}", "-p", PASSWORD, stdin=script)
    assert (code, err) == (0, "")
    assert after == before and "sensor 12 = " in after
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert proc.returncode == 0, err
    assert "served 1 connection, 5 answers; 0 requests without a recorded answer" in out.decode()


async def test_strict_fails_when_a_request_has_no_recorded_answer(recorded):
    path, _ = recorded
    proc = await start_process("stub", path, "--listen", "127.0.0.1:0", "--once", "--strict")
    port = int(re.search(rb":(\d+) \(", await asyncio.wait_for(proc.stdout.readline(), WAIT)).group(1))
    async with await Client.connect(LOCAL, port, password="any password", timeout=WAIT) as client:
        assert await client.sensor(12) > 0
        with pytest.raises(ConnectionClosed):  # at once, not after the client's own timeout
            await client.servo_position(5)  # never asked in the recording
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert proc.returncode == 1 and err == b""
    assert (b"! #1: no recorded answer for rr1-5--0--2-ss1 (Servo Position Request ch 5); connection closed"
            in out)
    assert b"1 request without a recorded answer" in out


async def test_used_up_answers_repeat_the_last_or_fail(recorded):
    path, got = recorded
    exchanges = load_exchanges(str(path))
    recorded_13 = got[1 + SENSORS.index(13)]
    async with Stub(exchanges) as stub:
        async with await Client.connect(LOCAL, stub.port, password="x") as client:
            assert [await client.sensor(13) for _ in range(3)] == [recorded_13] * 3
    assert stub.unanswered == []
    async with Stub(exchanges, exhausted="fail", unmatched="ignore") as stub:
        async with await Client.connect(LOCAL, stub.port, password="x", timeout=0.3) as client:
            await client.fetch_configuration()  # the channel map makes the request unambiguous
            assert await client.sensor(13) == recorded_13
            with pytest.raises(ResponseTimeout):
                await client.sensor(13)
    assert [u.text for u in stub.unanswered] == ["Sensor Request ch 13"]


async def test_password_check(recorded):
    path, _ = recorded
    async with Stub(load_exchanges(str(path)), password=PASSWORD.encode()) as stub:
        with pytest.raises(HandshakeError, match="Failed Validation"):
            await Client.connect(LOCAL, stub.port, password="wrong")
        async with await Client.connect(LOCAL, stub.port, password=PASSWORD) as client:
            assert len((await client.fetch_configuration()).channels) == 24


async def test_each_client_connection_is_answered_from_its_recorded_connection(two_connections):
    async def read_sensor(port: int) -> int:
        async with await Client.connect(LOCAL, port) as client:
            await client.fetch_configuration()
            return await client.sensor(12)

    async with Stub(two_connections) as stub:
        assert [await read_sensor(stub.port) for _ in range(3)] == [100, 200, 200]
    async with Stub(two_connections, conn=1) as stub:
        assert [await read_sensor(stub.port) for _ in range(2)] == [100, 100]
    with pytest.raises(ValueError, match="no connection 7"):
        Stub(two_connections, conn=7)


async def test_stub_command_errors(tmp_path, recorded):
    path, _ = recorded
    code, _out, err = await run_process_async("stub", str(tmp_path / "nothing.mcap"))
    assert code == 2 and err == f"whiztap: {tmp_path / 'nothing.mcap'}: no such file (see 'whiztap stub --help')\n"
    blocker = await asyncio.start_server(lambda r, w: None, LOCAL, 0)
    port = blocker.sockets[0].getsockname()[1]
    try:
        code, _out, err = await run_process_async("stub", str(path), "--listen", f"{LOCAL}:{port}")
    finally:
        blocker.close()
    assert code == 2 and err.startswith(f"whiztap: cannot listen on {LOCAL}:{port}: ") and err.count("\n") == 1


async def test_sigterm_stops_the_stub_with_a_summary(recorded):
    path, _ = recorded
    proc = await start_process("stub", path, "--listen", "127.0.0.1:0", "-q")
    port = int(re.search(rb":(\d+) \(", await asyncio.wait_for(proc.stdout.readline(), WAIT)).group(1))
    async with await Client.connect(LOCAL, port, password="x") as client:
        await client.fetch_configuration()
    proc.send_signal(signal.SIGTERM)
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert (proc.returncode, err) == (0, b"")
    assert out == (b"served 1 connection, 1 answer; 0 requests without a recorded answer; "
                   b"9 recorded requests never asked for\n")  # -q: the count, not the list


async def test_an_unmatched_request_can_get_a_chosen_answer(recorded):
    path, _ = recorded
    async with Stub(load_exchanges(str(path)), unmatched=b"cr1-5--0--0-ss1") as stub:
        async with await Client.connect(LOCAL, stub.port, password="x", timeout=WAIT) as client:
            await client.fetch_configuration()
            assert await client.servo_position(5) == 0
    assert [u.text for u in stub.unanswered] == ["Servo Position Request ch 5"]


async def test_the_default_connection_is_one_that_got_in(tmp_path):
    """A recording whose first connection failed its login: the first client is
    served the connection that was let in, not refused."""
    async def refused_then_accepted(port: int) -> None:
        with pytest.raises(HandshakeError):
            await Client.connect(LOCAL, port, password="not-" + PASSWORD)
        async with await Client.connect(LOCAL, port, password=PASSWORD) as client:
            await client.sensor(12)

    path = tmp_path / "refused-first.mcap"
    async with simulator(seed=1) as sim, recording(sim.port, path) as rec:
        await refused_then_accepted(rec.proxy.port)
        await until_closed(sim)
        await rec.stop()
    async with Stub(load_exchanges(str(path))) as stub:
        async with await Client.connect(LOCAL, stub.port, password="any", timeout=WAIT) as client:
            assert await client.sensor(12) >= 0
    async with Stub(load_exchanges(str(path)), conn=1) as stub:  # asked for by number: served as recorded
        with pytest.raises(HandshakeError):
            await Client.connect(LOCAL, stub.port, password="any", timeout=WAIT)


# -- the password never shows in what the stub says ---------------------------------------------------

_PW_TAIL = st.text(alphabet="abcdefghijkmnopqrstuvwxyz0123456789-", min_size=5, max_size=16)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tail=_PW_TAIL, end=st.sampled_from([b"", b"\r\n", b"\n"]), right=st.booleans(),
       check=st.booleans(), split=st.integers(min_value=0, max_value=40),
       after=st.lists(st.sampled_from([b"rr1-99--0--0-ss1", b"rr1-12--0--0-ss1", b"sr1-2--1500-ss1",
                                       b"garbage", b"Zq7"]), max_size=4))
def test_no_miss_line_or_summary_shows_a_client_password(recorded, tail, end, right, check, split, after):
    """Miss lines print what a client asked; a client's password (right or
    wrong, with or without a line break, split anywhere, with requests right
    behind it) is never one of them, nor in the JSON summary."""
    path, _ = recorded
    secret = ("Zq7" + tail).encode()
    expected = secret if right else b"Zq7-the-right-one"
    stream = secret + end + b"".join(after)
    lines: list[str] = []

    async def run() -> str:
        async with Stub(load_exchanges(str(path)), password=expected if check else None,
                        unmatched="ignore", on_log=lines.append) as stub:
            reader, writer = await asyncio.open_connection(LOCAL, stub.port)
            await reader.readexactly(len(b"sendchkpass"))
            cut = min(split, len(stream))
            with contextlib.suppress(ConnectionError, OSError):  # a wrong password is shut out
                for part in (stream[:cut], stream[cut:]):
                    writer.write(part)
                    await writer.drain()
                    await asyncio.sleep(0.01)
                writer.write_eof()
                await asyncio.wait_for(reader.read(-1), WAIT)
            writer.close()
            await asyncio.wait_for(stub.finished.wait(), WAIT)
            return json.dumps({"unanswered": [u.as_dict() for u in stub.unanswered],
                               "unused": [r.as_dict() for r in stub.unused()]})

    summary = asyncio.run(run())
    said = "\n".join(lines) + summary
    assert tail not in said and escape(secret) not in said, said
