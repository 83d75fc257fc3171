"""Only what can be a password is masked, through the real ``whiztap record``.

The rule (docs/recording-format.md, *Passwords*) masks the client's first
line, and only when the server begins with ``sendchkpass`` or never says.
Traffic with nothing secret in it is recorded exactly as it was sent, however
long the server takes, however much the client sends first, and even to a
server that never speaks: a VPN client pipelining 2,000 requests at connect, a
VPN server whose first answer is 2.5 s late, commands that get no answer to a
server that never answers, binary echoed back.  A Winsock client's command
sent before ``readytogo`` is shown, reported as the client's fault, and paired
with its answer; its password is still masked.
"""

from __future__ import annotations

import asyncio
import base64
import json
import random
import re
from pathlib import Path

import pytest
from whiztap.analyzer.protocol.examples import CONFIG
from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import run_cli
from tests.record_support import (
    LOCAL,
    WAIT,
    EchoServer,
    RecordProcess,
    StepServer,
    both_ways,
    play_client,
    read_all,
    record_dialogue,
    streams,
)
SECRET = b"Kx9hunter2Tq4"
FETCH = b"rr1-24--0--0-ss1"
REQUEST = b"rr1-12--0--0-ss1"  # a Sensor Request on the simulator's channel 12
SENSOR, SENSOR_ANSWER = b"rr1-3--0--0-ss1", b"cr1-3--5--0-ss1"  # channel 3 is a sensor in CONFIG
ONE_WAY = 500_000  # as many as `make bench` sends (7 s here)


def analyse(path: Path) -> tuple[int, dict]:
    """``whiztap analyze --format json``: its exit status and report."""
    result = run_cli("analyze", path, "--format", "json")
    assert result.returncode in (0, 1), result.stderr
    return result.returncode, json.loads(result.stdout)


def client_stream(path: Path) -> bytes:
    """The one connection's client stream, rebuilt from /tcp/reads."""
    recorded = streams(str(path))
    [conn] = {conn for conn, _ in recorded}
    return recorded.get((conn, "c2s"), b"")


async def count_frames(reader: asyncio.StreamReader, wanted: int) -> bytes:
    """Read until ``wanted`` frames came back."""
    framer, got, seen = Framer(), bytearray(), 0
    while seen < wanted:
        data = await asyncio.wait_for(reader.read(1 << 16), WAIT)
        assert data, f"the connection closed after {seen} of {wanted} frames"
        got += data
        seen += sum(item.kind is not ItemKind.EOL for item in framer.feed(data, 0))
    return bytes(got)


@pytest.mark.slow
async def test_a_vpn_client_pipelining_2000_requests_at_connect_is_recorded_as_sent(tmp_path):
    path = tmp_path / "pipelined.mcap"
    sent = FETCH + REQUEST * 1999
    async with Simulator(mode="vpn") as sim:
        rec = await RecordProcess.start(sim.port, path)
        reader, writer = await asyncio.open_connection(LOCAL, rec.port)
        writer.write(sent)  # at connect, before the server has said a thing
        await count_frames(reader, 2000)
        writer.close()
        await rec.wait_line(r"#1 closed by")
        code, _, stderr = await rec.finish()
    assert code == 0, stderr
    assert client_stream(path) == sent
    status, report = analyse(path)
    assert status == 0 and report["passed"], report["rule_counts"]


@pytest.mark.slow
async def test_a_vpn_server_whose_first_answer_is_late_is_recorded_as_sent(tmp_path):
    """2.5 s: longer than anything is held undecided.  The request stays a
    request and its answer answers it."""
    path = tmp_path / "late.mcap"
    sent = FETCH + SENSOR
    async with StepServer([("recv", len(sent)), ("sleep", 2.5), ("send", CONFIG + SENSOR_ANSWER)]) as server:
        rec = await RecordProcess.start(server.port, path)
        await play_client(rec.port, [("send", sent), ("recv", len(CONFIG) + len(SENSOR_ANSWER))])
        await rec.wait_line(r"#1 closed by")
        code, _, stderr = await rec.finish()
    assert code == 0, stderr
    assert client_stream(path) == sent
    status, report = analyse(path)
    assert status == 0 and report["passed"], report["rule_counts"]
    assert "PW-PAIR-UNSOLICITED" not in report["rule_counts"]


@pytest.mark.slow
async def test_commands_to_a_server_that_never_speaks_are_every_one_recorded(tmp_path):
    """A client that only drives outputs: Normal Sends, which get no answer,
    blasted at a server that says nothing at all."""
    path = tmp_path / "one-way.mcap"
    sent = b"".join(b"rr1-%d--%d--0-ss1" % (i % 24, 2 + i % 1999) for i in range(ONE_WAY))
    async with StepServer([]) as server:
        rec = await RecordProcess.start(server.port, path)
        await play_client(rec.port, [("send", sent), ("eof",), ("sleep", 0.2)])
        await rec.wait_line(r"#1 closed by")
        # the writer (a niced process) has a million messages to write: under a loaded
        # machine (both cores running tests) that takes longer than a hang's usual bound
        code, stdout, stderr = await rec.finish(wait=120)
        assert server.received == sent
    assert code == 0, stderr
    assert client_stream(path) == sent
    m = re.search(r"c2s ([\d,]+) frames", stdout)
    assert m and int(m.group(1).replace(",", "")) == ONE_WAY, stdout  # every one a frame of its own in /frames


@pytest.mark.slow
async def test_binary_echoed_back_is_never_masked(tmp_path):
    """64 KiB of binary in one write at connect, echoed: 20 connections, none masked."""
    path = tmp_path / "binary.mcap"
    rng = random.Random(25)
    sent = [bytes(rng.randrange(256) for _ in range(64 * 1024)) for _ in range(20)]
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, path)
        for n, data in enumerate(sent, 1):
            assert await play_client(rec.port, [("send", data), ("recv", len(data))]) == data
            await rec.wait_line(rf"#{n} closed by")
        code, _, stderr = await rec.finish()
    assert code == 0, stderr
    recorded = streams(str(path))
    for n, data in enumerate(sent, 1):
        assert recorded[(n, "c2s")] == data, f"#{n} was masked"


@pytest.mark.slow
@pytest.mark.parametrize("after", [b"\r\n", b""], ids=["line break", "none"])
async def test_a_command_before_readytogo_is_the_clients_fault_and_is_answered(tmp_path, after):
    """A Winsock client sends its password and, without waiting, a Fetch
    Configuration (after a line break, or right after the password): the
    password is masked, the command is shown, it breaks
    PW-HS-COMMAND-BEFORE-READY, and the server's answer answers it."""
    path = tmp_path / "eager-command.mcap"
    sent = SECRET + after + FETCH
    script = [("send", b"sendchkpass"), ("recv", len(sent)), ("send", b"readytogo"), ("send", CONFIG)]
    async with StepServer(script) as server:
        rec = await RecordProcess.start(server.port, path, "--analyze")
        await play_client(rec.port, [("recv", 11), ("send", sent), ("recv", 9 + len(CONFIG))])
        await rec.wait_line(r"#1 closed by")
        code, printed, stderr = await rec.finish()
    assert code == 0, stderr
    assert client_stream(path) == b"*" * len(SECRET) + after + FETCH
    frames = read_all(str(path))["/frames"]
    [password] = [f for f in frames if f["kind"] == "password"]
    assert password["redacted"] and base64.b64decode(password["raw"]) == b"*" * len(SECRET)
    [command] = [f for f in frames if f["kind"] == "command"]
    [answer] = [f for f in frames if f["kind"] == "config"]
    assert command["violations"] == ["PW-HS-COMMAND-BEFORE-READY"]
    assert answer["answers"] == command["index"] and answer["violations"] == []
    _, report = analyse(path)
    assert report["rule_counts"] == {"PW-HS-COMMAND-BEFORE-READY": 1}, report["rule_counts"]
    assert SECRET.decode() not in printed + json.dumps(report)


async def test_a_line_judged_early_and_too_long_to_be_a_password_reads_the_same_from_frames_and_reads(tmp_path):
    """Refused at its first byte, the client's line then runs past 256 bytes:
    the byte the server judged is masked, the rest is not, and /frames says
    exactly what /tcp/reads says."""
    rest = b"x" * 300 + b"\r\n"
    path = await record_dialogue(tmp_path / "long.mcap",
                                 [("send", b"sendchkpass"), ("recv", 1), ("send", b"Failed Validation"),
                                  ("recv", len(rest))],
                                 [("recv", 11), ("send", SECRET[:1]), ("recv", 17), ("send", rest)])
    assert both_ways(str(path))[(1, "c2s")] == b"*" + rest
