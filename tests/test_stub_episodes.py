"""New episodes: the stub forwards what its recording lacks to the real simulator and
appends it to the recording, atomically; a failed or killed run leaves the old file as it was."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.sniffer.replay.episodes import Episodes
from whiztap.sniffer.replay.stub import Stub
from whiztap.sniffer.sim.client import Client, ConnectionClosed
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import run_cli, start_process
from tests.outputs import SECRET, assert_no_leak, topics_text
from tests.record_support import LOCAL, WAIT, closed_port, recording
from tests.replay_support import FROZEN_NS, until_closed

PASSWORD = SECRET.decode()  # the secrets registry's password: any 8 bytes of it in a row is a leak


def simulator() -> Simulator:
    return Simulator(port=0, mode="winsock", password=PASSWORD, seed=1, clock=lambda: FROZEN_NS)


async def sensors(port: int, channels: tuple[int, ...]) -> list[int]:
    """The client under test: the configuration, then a few sensors."""
    async with await Client.connect(LOCAL, port, password=PASSWORD, timeout=WAIT) as client:
        await client.fetch_configuration()
        return [await client.sensor(ch) for ch in channels]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[bytes, list[int]]:
    """A recording of sensors 12 and 13 through the proxy; its bytes and what the client got."""
    path = tmp_path_factory.mktemp("episodes") / "sensors.mcap"

    async def make() -> list[int]:
        async with simulator() as sim, recording(sim.port, path) as rec:
            got = await sensors(rec.proxy.port, (12, 13))
            await until_closed(sim)
            await rec.stop()
        return got

    got = asyncio.run(make())
    return path.read_bytes(), got


def copy(recorded: tuple[bytes, list[int]], folder: Path) -> Path:
    path = folder / "sensors.mcap"
    path.write_bytes(recorded[0])
    return path


async def serve(path: Path, upstream: int | None, channels: tuple[int, ...]) -> tuple[Stub, Episodes | None, list]:
    """One client through a stub of ``path`` (forwarding to ``upstream``);
    the stub, its episodes (finished) and what the client got."""
    exchanges = load_exchanges(str(path))
    episodes = None if upstream is None else Episodes(path, (LOCAL, upstream), exchanges.checksum_rule, WAIT)
    if episodes is not None:
        episodes.open()
    async with Stub(exchanges, episodes=episodes) as stub:
        got = await sensors(stub.port, channels)
    if episodes is not None:
        episodes.finish()
    return stub, episodes, got


async def test_a_missing_exchange_is_appended_and_then_served_without_the_server(recorded, tmp_path):
    path = copy(recorded, tmp_path)
    async with simulator() as sim:
        live = await sensors(sim.port, (12, 13, 14, 15))
        stub, episodes, got = await serve(path, sim.port, (12, 13, 14, 15))
    assert got == live and got[:2] == recorded[1]
    assert (stub.answers, stub.forwarded, stub.unanswered) == (3, 2, [])  # the configuration and 12, 13 recorded
    assert episodes is not None and (episodes.connections, episodes.failure) == (1, None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sensors.mcap"]  # nothing left beside it

    again = load_exchanges(str(path))
    assert [(c.conn, c.client.startswith("whiztap stub")) for c in again.connections] == [(1, False), (2, True)]
    assert [i.obs.item.raw for i in again.connections[1].requests] == [
        b"rr1-24--0--0-ss1", b"rr1-14--0--0-ss1", b"rr1-15--0--0-ss1"]  # its channel map, then the two new
    stub, _, got = await serve(path, None, (12, 13, 14, 15))  # no server now: the recording answers all
    assert (got, stub.unanswered, stub.unused()) == (live, [], [])
    for args in (("analyze", path, "--severity-threshold", "info"), ("cat", path)):
        ran = run_cli(*args)
        assert ran.returncode == 0, ran
        assert_no_leak(" ".join(map(str, args)), ran.stdout)
    assert_no_leak("the appended recording's bytes", path.read_bytes())
    assert_no_leak("every topic of the appended recording", topics_text(path))


async def test_nothing_new_leaves_the_file_alone(recorded, tmp_path):
    path = copy(recorded, tmp_path)
    _, episodes, _ = await serve(path, closed_port(), (12, 13))  # the server is never asked
    assert episodes is not None and (episodes.connections, episodes.failure) == (0, None)
    assert path.read_bytes() == recorded[0]


async def test_an_upstream_that_dies_midway_leaves_the_recording_untouched(recorded, tmp_path):
    path = copy(recorded, tmp_path)
    exchanges = load_exchanges(str(path))
    async with simulator() as sim:
        episodes = Episodes(path, (LOCAL, sim.port), exchanges.checksum_rule, WAIT)
        episodes.open()
        async with Stub(exchanges, episodes=episodes) as stub:
            async with await Client.connect(LOCAL, stub.port, password=PASSWORD, timeout=WAIT) as client:
                await client.fetch_configuration()
                assert await client.sensor(14) >= 0  # forwarded and answered
                await sim.close()  # the server goes away with the client's upstream connection
                with pytest.raises(ConnectionClosed):
                    await client.sensor(15)
    assert episodes.finish() is False
    assert episodes.failure is not None and "closed the connection" in episodes.failure
    assert [u.why for u in stub.unanswered] == ["no recorded answer (the upstream failed)"]
    assert path.read_bytes() == recorded[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sensors.mcap"]


async def stub_process(path: Path, upstream: int, asked: tuple[int, ...], *more: str) -> asyncio.subprocess.Process:
    """``whiztap stub --upstream`` serving one client that asks ``asked``."""
    proc = await start_process("stub", path, "--listen", "127.0.0.1:0", "--upstream", f"{LOCAL}:{upstream}", *more)
    port = int(re.search(rb":(\d+) \(", await asyncio.wait_for(proc.stdout.readline(), WAIT)).group(1))
    try:
        await sensors(port, asked)
    except ConnectionClosed:  # the stub could not forward the request
        pass
    return proc


@pytest.mark.slow
async def test_the_command_appends_on_sigint_and_a_failed_or_killed_one_changes_nothing(recorded, tmp_path):
    """SIGINT is how a stub is stopped: it appends.  An upstream it cannot
    reach fails the run (one line, exit status 2) and SIGKILL ends it; both
    leave the recording byte for byte as it was, and nothing beside it."""
    path = copy(recorded, tmp_path)
    dead = closed_port()
    proc = await stub_process(path, dead, (12, 16), "--format", "json")
    proc.send_signal(signal.SIGINT)
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    summary = json.loads(out.decode().splitlines()[-1])
    assert {k: summary[k] for k in ("upstream", "forwarded", "appended")} == {
        "upstream": f"{LOCAL}:{dead}", "forwarded": 0, "appended": False}
    assert summary["upstream_error"].startswith(f"cannot connect to {LOCAL}:{dead}")
    assert [u["why"] for u in summary["unanswered"]] == ["no recorded answer (the upstream failed)"]
    assert proc.returncode == 2 and err.decode().startswith(f"whiztap: upstream {LOCAL}:{dead}: cannot connect to ")
    assert err.decode().endswith(f"; nothing appended, {path} is unchanged: run again once the server answers\n")
    assert err.count(b"\n") == 1
    async with simulator() as sim:
        live = sim.port
        for stop, asked in ((signal.SIGKILL, (12, 16)), (signal.SIGINT, (12, 16, 17))):
            assert path.read_bytes() == recorded[0]
            assert sorted(p.name for p in tmp_path.iterdir()) == ["sensors.mcap"]
            proc = await stub_process(path, sim.port, asked)  # 16 (and 17) forwarded
            proc.send_signal(stop)
            out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert (proc.returncode, err) == (0, b"")
    assert out.decode().endswith(f"2 requests forwarded to {LOCAL}:{live}; appended to {path} "
                                 "on 1 new connection\n")
    assert_no_leak("the stub's output", out)
    assert [i.obs.item.raw for i in load_exchanges(str(path)).connections[-1].requests][1:] == [
        b"rr1-16--0--0-ss1", b"rr1-17--0--0-ss1"]


def test_upstream_needs_one_local_file(tmp_path):
    """A split recording is refused before anything listens: one line saying
    how to make it one file, and the parts stay as they were."""
    from tests.test_split_recordings import split_vpn_session

    files = split_vpn_session(tmp_path / "s.mcap")
    before = [Path(f).read_bytes() for f in files]
    ran = run_cli("stub", files[0], "--listen", "127.0.0.1:0", "--upstream", "127.0.0.1:1")
    assert ran.returncode == 2 and ran.stdout == ""
    assert ran.stderr.startswith("whiztap: --upstream appends to RECORDING, so it must be one local file, "
                                 f"not {files[0]} (+")
    assert ran.stderr.endswith("make one with 'whiztap cut PARTS... -o ONE.mcap'\n") and ran.stderr.count("\n") == 1
    assert [Path(f).read_bytes() for f in files] == before


# -- whatever the upstream sends --------------------------------------------------------------------

_ANSWERS = st.sampled_from([b"cr1-14--500--0-ss1", b"cr1-99--1--0-ss1", b"garbage", b"sr1-", b"\r\n",
                            b"readytogo", b"cr1-14--7"])


@pytest.fixture(scope="module")
def vpn(tmp_path_factory) -> tuple[Path, bytes]:
    """A VPN recording (the configuration, sensor 12) and the configuration frame the server sent."""
    path = tmp_path_factory.mktemp("vpn") / "vpn.mcap"

    async def make() -> None:
        async with Simulator(port=0, mode="vpn", seed=1, clock=lambda: FROZEN_NS) as sim, \
                recording(sim.port, path) as rec:
            async with await Client.connect(LOCAL, rec.proxy.port, timeout=WAIT) as client:
                await client.fetch_configuration()
                await client.sensor(12)
            await until_closed(sim)
            await rec.stop()

    asyncio.run(make())
    [conn] = load_exchanges(str(path)).connections
    config = conn.requests[0].answer
    assert config is not None
    return path, config.item.raw


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sent=st.lists(st.one_of(_ANSWERS, st.binary(max_size=12)), max_size=4))
def test_whatever_the_upstream_answers_the_old_file_stays_or_a_readable_one_replaces_it(vpn, tmp_path, sent):
    """An upstream that answers the channel map, then meets the forwarded
    request with any bytes and closes: the client gets the answer the
    session model pairs with its request, or the run fails and the old
    recording stays; either way the file is a recording every reader opens."""
    original, config = vpn
    path = tmp_path / "vpn.mcap"
    before = original.read_bytes()
    path.write_bytes(before)
    request = b"rr1-14--0--0-ss1"

    async def upstream(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readexactly(len(b"rr1-24--0--0-ss1"))
        writer.write(config)
        await reader.readexactly(len(request))
        writer.write(b"".join(sent))
        await writer.drain()
        writer.close()

    async def run() -> tuple[bool, Episodes, bytes]:
        async with _past_the_map(upstream, path, config) as (episodes, reader, writer):
            writer.write(request)  # a Sensor Request, now that the channel map is known
            writer.write_eof()
            got = config + await asyncio.wait_for(reader.read(-1), WAIT)
        return episodes.finish(), episodes, got

    changed, episodes, got = asyncio.run(run())
    event("appended" if changed else "failed")
    if changed:
        answer = load_exchanges(str(path)).connections[-1].requests[-1].answer
        assert episodes.failure is None and answer is not None and got == config + answer.item.raw
    else:
        assert episodes.failure is not None and path.read_bytes() == before and got == config
    assert run_cli("analyze", path).returncode in (0, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vpn.mcap"]


def test_a_stub_stopped_while_a_forwarded_request_waits_appends_nothing(vpn, tmp_path):
    """Stopped mid-forward, the new connection would hold a request without
    its answer, which a later run would serve as "no answer": nothing is appended."""
    original, config = vpn
    path = tmp_path / "vpn.mcap"
    path.write_bytes(original.read_bytes())

    async def run() -> Episodes:
        asked = asyncio.Event()

        async def upstream(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readexactly(len(b"rr1-24--0--0-ss1"))
            writer.write(config)
            await reader.readexactly(len(b"rr1-14--0--0-ss1"))
            asked.set()  # and never answers
            await reader.read(-1)

        async with _past_the_map(upstream, path, config) as (episodes, _reader, writer):
            writer.write(b"rr1-14--0--0-ss1")
            await asyncio.wait_for(asked.wait(), WAIT)
        return episodes

    episodes = asyncio.run(run())
    assert episodes.finish() is False
    assert episodes.failure == "the stub stopped while a forwarded request waited for its answer"
    assert path.read_bytes() == original.read_bytes()


# -- memory, whatever the upstream does -------------------------------------------------------------

FLOOD = 12 << 20  # bytes of garbage an upstream sends instead of an answer
FLOOD_BOUND = 6 << 20  # the most the stub may hold while it does (the recorder's open chunk and its compression)


@pytest.mark.slow
def test_an_upstream_flooding_garbage_instead_of_an_answer_costs_bounded_memory(vpn, tmp_path):
    """The upstream answers the channel map, then meets the forwarded request
    with megabytes that never make an answer, and closes: the run fails, the
    recording stays, and what the stub held meanwhile (traced allocations)
    stays within a bound far below what was sent: the bytes go to the
    temporary recording's file, not to memory."""
    import tracemalloc

    original, config = vpn
    path = tmp_path / "vpn.mcap"
    path.write_bytes(original.read_bytes())
    piece = b"x" * (64 << 10)

    async def upstream(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readexactly(len(b"rr1-24--0--0-ss1"))
        writer.write(config)
        await reader.readexactly(len(b"rr1-14--0--0-ss1"))
        for _ in range(FLOOD // len(piece)):
            writer.write(piece)
            await writer.drain()
        writer.close()

    async def run() -> Episodes:
        async with _past_the_map(upstream, path, config) as (episodes, reader, writer):
            tracemalloc.start()
            writer.write(b"rr1-14--0--0-ss1")
            writer.write_eof()
            await asyncio.wait_for(reader.read(-1), WAIT)
        return episodes

    try:
        episodes = asyncio.run(run())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert episodes.finish() is False and episodes.failure is not None
    assert peak < FLOOD_BOUND, f"{peak:,} bytes held while {FLOOD:,} were sent"
    assert path.read_bytes() == original.read_bytes()


@contextlib.asynccontextmanager
async def _past_the_map(upstream: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]],
                        path: Path, config: bytes) -> AsyncIterator[tuple[Episodes, asyncio.StreamReader,
                                                                          asyncio.StreamWriter]]:
    """A stub serving ``path`` with a server running ``upstream`` as its
    --upstream, and a client of it that has fetched the channel map (the
    recorded answer, ``config``); the stub stopped after, then the client closed."""
    server = await asyncio.start_server(upstream, LOCAL, 0)
    async with server:
        exchanges = load_exchanges(str(path))
        episodes = Episodes(path, (LOCAL, server.sockets[0].getsockname()[1]), exchanges.checksum_rule, WAIT)
        episodes.open()
        async with Stub(exchanges, episodes=episodes) as stub:
            reader, writer = await asyncio.open_connection(LOCAL, stub.port)
            writer.write(b"rr1-24--0--0-ss1")
            assert await asyncio.wait_for(reader.readexactly(len(config)), WAIT) == config
            yield episodes, reader, writer
        writer.close()  # once the stub has stopped, as a client left behind would be
