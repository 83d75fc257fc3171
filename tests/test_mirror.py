"""Shadow traffic (issue 29, item 4): ``record --mirror HOST:PORT``.

Real parts: the proxy and its writer process in the test's loop, two frozen-
clock simulators (the same seed answers byte for byte alike; another seed
differs in its sensor readings), scripted servers for a mirror that is slow,
refuses or dies, and the recording read back with the real MCAP reader.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import socket

import pytest

import whiztap.sniffer.record.mirror as mirror_module
from whiztap.sniffer.record.mirror import mirror_lines
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import run_cli
from tests.outputs import FILE_OUTPUTS, MIRROR_ONLY, QUICK_FILE_OUTPUTS, SECRET, assert_no_leak
from tests.record_support import LOCAL, WAIT, EchoServer, closed_port, read_all, recording
from tests.replay_support import FROZEN_NS, PASSWORD, client_session, simulator, until_closed


async def _recorded(path, primary_seed: int, mirror_port_or_seed, session=client_session, **options):
    """``session`` through a proxy with a mirror; (what the client got, summary, lines, topics)."""
    async with simulator(primary_seed) as primary:
        if isinstance(mirror_port_or_seed, int) and mirror_port_or_seed > 100:
            mirror_port, shadow = mirror_port_or_seed, None
        else:
            shadow = simulator(mirror_port_or_seed)
            await shadow.__aenter__()
            mirror_port = shadow.port
        try:
            async with recording(primary.port, path, mirror=(LOCAL, mirror_port), **options) as rec:
                got = await session(rec.proxy.port)
                await until_closed(primary)
                if shadow is not None:
                    await until_closed(shadow)
                summary = await rec.stop()
        finally:
            if shadow is not None:
                await shadow.__aexit__(None, None, None)
    return got, summary, rec.lines, read_all(str(path))


async def test_a_mirror_equal_to_the_primary_shows_no_difference_and_the_client_gets_the_primary(tmp_path):
    alone = tmp_path / "alone.mcap"
    async with simulator(1) as sim, recording(sim.port, alone) as rec:
        expected = await client_session(rec.proxy.port)
        await until_closed(sim)
    got, summary, _, topics = await _recorded(tmp_path / "m.mcap", 1, 1)
    assert got == expected
    final = summary["mirror"]
    assert final["total"] == 0 and final["exchanges"] >= 10 and final["connections"] == 1, final
    assert [e["event"] for e in topics["/mirror/tcp/events"]] == ["connected", "closed"]
    primary = b"".join(base64.b64decode(m["data"]) for m in topics["/tcp/reads"] if m["dir"] == "s2c")
    mirror = b"".join(base64.b64decode(m["data"]) for m in topics["/mirror/tcp/s2c"])
    assert mirror == primary  # the same seed, the same clock: the same answers
    assert "/mirror/differences" not in topics
    assert "no differences" in mirror_lines(final)[0]
    from whiztap.analyzer.recording.scan import read_metadata

    assert read_metadata(str(tmp_path / "m.mcap"))["mirror"] == final["server"]


async def test_a_lying_mirror_differs_in_its_readings_and_each_difference_says_which_side(tmp_path):
    _, summary, _, topics = await _recorded(tmp_path / "m.mcap", 1, 2)
    final = summary["mirror"]
    assert final["total"] > 0 and set(final["by_kind"]) == {"value"}, final
    differences = topics["/mirror/differences"]
    assert len(differences) == final["total"]
    first = differences[0]
    assert first["kind"] == "value" and first["exchange"].startswith("Sensor Request #1 on channel 12")
    assert first["primary"] != first["mirror"] and first["at_fault"] == "neither"
    assert first["what"].startswith("the answer (sensor_value ")
    lines = mirror_lines(final)
    assert "differences (" in lines[0] and lines[1].strip().startswith("#1 Sensor Request")
    info = run_cli("info", tmp_path / "m.mcap").stdout.split("messages per topic\n", 1)[1]
    counts = [line for line in info.splitlines() if line.startswith("  /")]
    assert any(line.startswith("  /mirror/differences ") for line in counts), info
    assert len({line.rindex(" ") for line in counts}) == 1, info  # the longest topic name pushes no count out of line


# -- a slow, dead or refusing mirror never touches the primary ---------------------------------------


@contextlib.asynccontextmanager
async def _never_reading():
    """A mirror that accepts and never reads, with a small receive buffer: slow as can be."""
    held: list[asyncio.StreamWriter] = []
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.bind((LOCAL, 0))

    def accept(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.transport.pause_reading()
        held.append(writer)

    server = await asyncio.start_server(accept, sock=sock)
    try:
        yield sock.getsockname()[1]
    finally:
        for writer in held:
            writer.transport.abort()
        server.close()


async def _echoed(port: int, data: bytes) -> bytes:
    """Send ``data`` through the proxy to an echo server, reading the echo as it comes; the echo."""
    reader, writer = await asyncio.open_connection(LOCAL, port)

    async def send() -> None:
        for i in range(0, len(data), 1 << 16):
            writer.write(data[i:i + (1 << 16)])
            await writer.drain()
        writer.write_eof()

    sending = asyncio.ensure_future(send())
    got = await asyncio.wait_for(_read_all(reader), WAIT)
    await sending
    writer.close()
    return got


async def _read_all(reader: asyncio.StreamReader) -> bytes:
    chunks = []
    while chunk := await reader.read(1 << 16):
        chunks.append(chunk)
    return b"".join(chunks)


@pytest.mark.slow  # about a second: 1 MiB through the proxy, recorded
async def test_a_slow_mirror_is_dropped_past_its_buffer_and_the_clients_get_every_byte(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(mirror_module, "MIRROR_BUFFER", 32 << 10)  # small bounds: the test moves little
    monkeypatch.setattr(mirror_module, "MIRROR_SOCKET_BUFFER", 32 << 10)
    data = bytes(range(256)) * (1 << 10)  # 256 KiB a client: past what the mirror and the kernel may hold
    async with EchoServer() as echo, _never_reading() as slow, \
            recording(echo.port, tmp_path / "m.mcap", mirror=(LOCAL, slow)) as rec:
        echoed = await asyncio.gather(_echoed(rec.proxy.port, data), _echoed(rec.proxy.port, data))
        summary = await rec.stop()
    assert echoed == [data, data]  # the primary's traffic, whole, for both clients
    events = read_all(str(tmp_path / "m.mcap"))["/mirror/tcp/events"]
    dropped = [e for e in events if e["event"] == "dropped"]
    assert {e["conn"] for e in dropped} == {1, 2} and "took too little" in dropped[0]["detail"], events
    assert summary["mirror"]["events"]["dropped"] == 2
    said = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mirror:")]
    assert len(said) == 1 and "dropped" in said[0], said  # said once, counted in the summary
    assert "2 dropped" in mirror_lines(summary["mirror"])[0]


async def test_a_mirror_that_refuses_is_recorded_and_said_once(tmp_path, capsys):
    async def two_sessions(port: int) -> list:
        return await client_session(port) + await client_session(port)

    got, summary, _, topics = await _recorded(tmp_path / "m.mcap", 1, closed_port(), session=two_sessions)
    assert len(got) == 20  # both sessions' exchanges complete
    assert [e["event"] for e in topics["/mirror/tcp/events"]] == ["failed", "failed"]
    assert "cannot connect to the mirror" in topics["/mirror/tcp/events"][0]["detail"]
    final = summary["mirror"]
    assert final["total"] == 0 and final["events"] == {"failed": 2} and final["not_compared"] > 0
    said = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mirror:")]
    assert len(said) == 1 and "failed" in said[0] and "Connection refused" in said[0], said


async def test_a_mirror_that_dies_mid_way_is_recorded_and_what_it_never_got_is_not_compared(tmp_path, capsys):
    async def die_after_first_read(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"sendchkpass")
        await reader.read(1)
        writer.transport.abort()

    server = await asyncio.start_server(die_after_first_read, LOCAL, 0)
    async with server:
        got, summary, _, topics = await _recorded(tmp_path / "m.mcap", 1, server.sockets[0].getsockname()[1])
    assert len(got) == 10  # the session's exchanges complete
    events = topics["/mirror/tcp/events"]
    assert [e["event"] for e in events] == ["connected", "closed"] and "by the mirror" in events[1]["detail"]
    final = summary["mirror"]
    assert final["events"] == {"connected": 1, "closed": 1}, final
    # every request of the client's either compared (sent before the mirror died: unanswered) or not (after)
    assert final["exchanges"] + final["not_compared"] == 13 and final["not_compared"] >= 1, final
    assert set(final["by_kind"]) <= {"missing", "handshake"}, final
    said = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mirror:")]
    assert len(said) == 1 and "while the client was still connected" in said[0], said


# -- the password ------------------------------------------------------------------------------------


async def test_the_password_sent_to_both_servers_shows_nowhere(tmp_path):
    """A Winsock login through the proxy: the primary accepts it, a mirror with another password
    refuses it (a handshake difference); neither the recording's readers, the record's lines
    nor the differences show it."""
    password = SECRET.decode()
    path = tmp_path / "m.mcap"

    def sim(secret: str) -> Simulator:
        return Simulator(port=0, mode="winsock", password=secret, seed=1, clock=lambda: FROZEN_NS)

    async with sim(password) as primary, sim("another-one") as shadow, \
            recording(primary.port, path, mirror=(LOCAL, shadow.port)) as rec:
        async with await Client.connect(LOCAL, rec.proxy.port, password=password) as client:
            await client.sensor(12)
        await until_closed(primary)
        await until_closed(shadow)
        summary = await rec.stop()
    final = summary["mirror"]
    assert final["by_kind"].get("handshake") == 1, final
    topics = read_all(str(path))
    assert set(MIRROR_ONLY) <= set(topics)  # the registry's mirror topics, each reached and read below
    differences = topics["/mirror/differences"]
    assert any("refused" in d["mirror"] for d in differences), differences
    for name in QUICK_FILE_OUTPUTS:
        assert_no_leak(name, FILE_OUTPUTS[name](path))
    assert_no_leak("record's lines", "\n".join(rec.lines + mirror_lines(final)))


# -- the live TUI ------------------------------------------------------------------------------------


@pytest.mark.slow  # about a second: the app under Pilot with its proxy, writer and two simulators
async def test_the_live_tui_shows_how_many_differences_and_the_latest(tmp_path):
    """``whiztap tui --upstream --mirror``: the status line counts the lying mirror's
    differences as the client's exchanges are judged, and names the latest."""
    from whiztap.sniffer.record.record_run import RecordSettings
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.data.sources import LiveSource, ProxyRig

    from tests.tui_support import SIZE, until

    async with simulator(1) as primary, simulator(2) as shadow:
        settings = RecordSettings((LOCAL, 0), (LOCAL, primary.port), str(tmp_path / "live.mcap"), quiet=True,
                                  mirror=(LOCAL, shadow.port))
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            source = app.source
            await until(pilot, lambda: source.recording is not None and source.recording.proxy is not None, "proxy")
            async with await Client.connect(LOCAL, source.recording.proxy.port, password=PASSWORD) as client:
                await client.fetch_configuration()
                await client.sensor(12)
                await client.sensor(13)
            view = source.recording.mirror.view
            await until(pilot, lambda: view.differences >= 2, "the mirror's differences")
            app.refresh_summaries()
            await pilot.pause()
            status = str(app.status.content)
            assert f"mirror: {view.differences} differences" in status, status
            assert "latest #1 Sensor Request #" in status, status
            await pilot.press("q")  # finishes the recording first
            await until(pilot, lambda: not app.is_running, "the app to quit")


def test_a_mirror_that_cannot_be_is_refused_in_one_line(tmp_path):
    from tests.cli_support import run_cli

    out = tmp_path / "x.mcap"
    base = ("record", "--listen", "127.0.0.1:6123", "--upstream", "127.0.0.1:5000", "-o", out)
    for args, words in [((*base, "--mirror", "127.0.0.1:6123"), "is where the proxy listens"),
                        ((*base, "--mirror", "nonsense"), "--mirror must be HOST:PORT"),
                        (("tui", str(out), "--mirror", "127.0.0.1:5001"), "go with --upstream")]:
        done = run_cli(*args)
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert done.stderr.startswith("whiztap: ") and words in done.stderr, done.stderr
    assert not out.exists()


@pytest.mark.slow  # whiztap record as a process of its own: its terminal is the point
async def test_whiztap_record_says_what_the_mirror_did_when_it_closes(tmp_path):
    from tests.record_support import running_record

    async with simulator(1) as primary, simulator(2) as shadow, \
            running_record(primary.port, tmp_path / "m.mcap", "--mirror", f"{LOCAL}:{shadow.port}") as rec:
        mirror = f"{LOCAL}:{shadow.port}"
        assert f"mirror: {mirror}" in rec.first
        async with await Client.connect(LOCAL, rec.port, password=PASSWORD) as client:
            await client.fetch_configuration()
            await client.sensor(12)
        await until_closed(primary)
        code, out, err = await rec.finish()
    assert code == 0 and err == "", err
    [line] = [line for line in out.splitlines() if line.startswith("mirror ")]
    assert line == f"mirror {mirror}: 2 exchanges compared over 1 connection: 1 difference (1 value)"
    assert "  #1 Sensor Request #1 on channel 12: the answer (sensor_value " in out
    assert PASSWORD not in out


@pytest.mark.slow  # whiztap record as a process of its own: its terminal is the point
async def test_whiztap_record_says_at_start_that_the_mirror_refuses_and_no_more(tmp_path):
    from tests.record_support import running_record

    port = closed_port()
    async with simulator(1) as primary, \
            running_record(primary.port, tmp_path / "m.mcap", "--mirror", f"{LOCAL}:{port}") as rec:
        line = (await asyncio.wait_for(rec.proc.stderr.readline(), WAIT)).decode()
        assert line == (f"warning: the mirror {LOCAL}:{port} does not accept connections (Connection refused); "
                        "recording anyway: the clients' traffic goes on, and the mirror's answers are not compared\n")
        async with await Client.connect(LOCAL, rec.port, password=PASSWORD) as client:
            await client.sensor(12)  # the client's exchanges go on
        await until_closed(primary)
        code, out, err = await rec.finish()
    assert code == 0 and err == "", err  # the connection's failure is recorded, not said again
    assert "1 failed" in out and "1 connection: no differences" in out, out
