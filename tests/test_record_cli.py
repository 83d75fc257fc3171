"""``whiztap record`` as a user runs it: a real subprocess, real signals (refusals at
start run in this process)."""

from __future__ import annotations

import asyncio
import os
import re
import resource
import signal
import socket
from pathlib import Path

import pytest
from mcap.stream_reader import StreamReader

from whiztap.analyzer.recording.format import TOPIC_READS
from whiztap.analyzer.recording.scan import RecordingScan
from tests.cli_support import run_cli
from tests.record_support import (
    LOCAL,
    WAIT,
    EchoServer,
    RecordProcess,
    both_ways,
    closed_port,
    events,
    read_all,
    rebuild_streams,
    tcp_reads,
)

async def _talk(port: int, payload: bytes) -> bytes:
    reader, writer = await asyncio.open_connection(LOCAL, port)
    writer.write(payload)
    writer.write_eof()
    got = await asyncio.wait_for(reader.read(-1), WAIT)
    writer.close()
    return got


@pytest.mark.slow
async def test_ctrl_c_finishes_the_file_and_prints_a_summary(tmp_path):
    out = tmp_path / "session.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out)
        payload = b"rr1-24--0--0-ss1rr1-3--0--0-ss1"
        assert await _talk(rec.port, payload) == payload
        await rec.wait_line(r"#1 closed by client")
        code, stdout, stderr = await rec.finish(signal.SIGINT)
    assert code == 0, stderr
    assert stderr == ""
    assert "#1 opened from 127.0.0.1:" in stdout
    assert re.search(r"recorded 1 connection into .*session\.mcap \(\d", stdout)
    assert "c2s 2 frames 31 B; s2c 2 frames 31 B" in stdout
    assert re.search(r"violations: \d+ errors?, \d+ warnings?, \d+ info", stdout)
    assert not Path(str(out) + ".part").exists()
    assert both_ways(str(out)) == {(1, "c2s"): payload, (1, "s2c"): payload}


@pytest.mark.slow
async def test_sigterm_closes_open_connections_and_finishes_the_file(tmp_path):
    out = tmp_path / "term.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out, "-q")
        reader, writer = await rec.connect()
        writer.write(b"rr1-0--0--0-ss1")
        assert await asyncio.wait_for(reader.readexactly(15), WAIT) == b"rr1-0--0--0-ss1"
        code, stdout, stderr = await rec.finish(signal.SIGTERM)
        assert await asyncio.wait_for(reader.read(-1), WAIT) == b""  # the proxy closed it
        writer.close()
    assert (code, stdout, stderr) == (0, "", "")  # -q: nothing printed
    by_topic = read_all(str(out))
    closed = [e for e in by_topic["/tcp/events"] if e["event"] == "closed"]
    assert closed[0]["by"] == "recorder"
    assert events(by_topic, 0) == ["recording_started", "recording_stopped"]


@pytest.mark.slow
async def test_analyze_prints_violations_as_they_happen(tmp_path):
    out = tmp_path / "analyze.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out, "--analyze")
        _reader, writer = await asyncio.open_connection(LOCAL, rec.port)
        writer.write(b"rr1-99--5--0-ss1")
        line = await rec.wait_line(r"PW-RANGE-CHANNEL")
        writer.close()
        await rec.finish()
    assert re.match(r"! PW-RANGE-CHANNEL \(error\) conn #1 at \d\d:\d\d:\d\d\.\d{6} frame #0 "
                    r"'rr1-99--5--0-ss1': channel must be 0-23, got 99", line)


def test_user_errors_are_one_line_and_exit_2(tmp_path):
    port = closed_port()
    code, _, err = run_cli("record", "--upstream", f"{LOCAL}:{port}", "-o", tmp_path / "no" / "such" / "x.mcap",
                           "--listen", "0")
    assert code == 2 and err.count("\n") == 1 and err.startswith("whiztap: cannot write ")
    assert "No such file or directory" in err
    with socket.socket() as taken:
        taken.bind((LOCAL, 0))
        taken.listen()
        code, _, err = run_cli("record", "--upstream", f"{LOCAL}:{port}", "-o", tmp_path / "x.mcap",
                               "--listen", taken.getsockname()[1])
    assert code == 2 and err.count("\n") == 1 and err.startswith("whiztap: cannot listen on 127.0.0.1:")
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.mcap.part").exists()
    code, _, err = run_cli("record", "--upstream", "nowhere", "-o", tmp_path / "x.mcap")
    assert code == 2 and err == "whiztap: --upstream must be HOST:PORT, got 'nowhere'\n"


@pytest.mark.slow
async def test_an_existing_recording_is_not_overwritten_without_force(tmp_path):
    out = tmp_path / "kept.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out)
        assert await _talk(rec.port, b"rr1-1--0--0-ss1") == b"rr1-1--0--0-ss1"
        await rec.finish()
        first = out.read_bytes()

        async def record(*args: str) -> tuple[int, str]:
            done = await asyncio.to_thread(run_cli, "record", "--upstream", f"{LOCAL}:{server.port}", "--listen", "0",
                                           *args)
            return done.returncode, done.stderr

        assert await record("-o", str(out)) == (
            2, f"whiztap: {out} exists; use --force to overwrite it or -o to choose another name\n")
        assert out.read_bytes() == first
        crashed = tmp_path / "crashed.mcap"
        Path(f"{crashed}.part").write_bytes(first[:len(first) // 2])
        code, err = await record("-o", str(crashed))
        assert code == 2 and f"or save it first: whiztap recover {crashed}.part" in err
        assert Path(f"{crashed}.part").read_bytes() == first[:len(first) // 2]
        rec = await RecordProcess.start(server.port, out, "--force")
        assert await _talk(rec.port, b"rr1-2--0--0-ss1") == b"rr1-2--0--0-ss1"
        await rec.finish()
    assert both_ways(str(out))[(1, "c2s")] == b"rr1-2--0--0-ss1"


@pytest.mark.slow
async def test_split_size_rotates_without_losing_or_repeating_a_byte(tmp_path):
    out = tmp_path / "split.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out, "--split-size", "40k")
        reader, writer = await asyncio.open_connection(LOCAL, rec.port)
        sent = bytearray()
        for i in range(300):
            frame = b"rr1-%d--%d--0-ss1" % (i % 24, i)
            writer.write(frame * 20)
            sent += frame * 20
            await asyncio.wait_for(reader.readexactly(len(frame) * 20), WAIT)
        writer.close()
        code, stdout, stderr = await rec.finish()
    assert code == 0, stderr
    parts = sorted(tmp_path.glob("split-*.mcap"))
    assert len(parts) >= 3, stdout
    assert not list(tmp_path.glob("*.part"))
    c2s = bytearray()
    for part in parts:
        by_topic = read_all(str(part))
        continued = {e["c2s_offset"] for e in by_topic["/tcp/events"] if e["event"] == "continued"}
        for seg in rebuild_streams(str(part), TOPIC_READS).get((1, "c2s"), []):
            assert seg.offset == len(c2s)  # contiguous across files: nothing lost, nothing twice
            if seg.offset:  # a reader of this file alone learns where the open connection stands
                assert continued == {seg.offset}
            c2s += seg.data
    assert bytes(c2s) == bytes(sent)
    assert f"finished {parts[0]}" in stdout


@pytest.mark.slow
async def test_a_full_disk_stops_recording_cleanly_and_keeps_what_was_written(tmp_path):
    out = tmp_path / "full.mcap"
    limit = 1_000_000

    def small_files() -> None:  # the kernel refuses writes past this size: EFBIG, like ENOSPC
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out, preexec_fn=small_files)
        reader, writer = await asyncio.open_connection(LOCAL, rec.port)
        try:
            for _ in range(2000):  # a few flushes fit under the limit before one does not
                chunk = os.urandom(2 << 10)  # incompressible: the file grows as fast as traffic
                writer.write(chunk)
                await asyncio.wait_for(reader.readexactly(len(chunk)), WAIT)
                await asyncio.sleep(0.01)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the recorder stopped and closed the connection
        writer.close()
        code, _stdout, stderr = await rec.finish(None)
    assert code == 2
    assert stderr.count("\n") == 1 and stderr.startswith("whiztap: cannot write ")
    assert "File too large" in stderr and "recording stopped" in stderr
    assert out.exists() and out.stat().st_size <= limit
    # what was written is a valid MCAP: the stream reader checks every chunk's CRC
    with open(out, "rb") as f:
        records = list(StreamReader(f, validate_crcs=True).records)
    assert len(records) > 5
    with open(out, "rb") as f:
        scan = RecordingScan(f)
        got = list(tcp_reads(scan))
    assert got and not scan.truncated  # it ends with a proper footer
    assert {r.conn for r in got} == {1}
