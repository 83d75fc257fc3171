"""A recording split by --split-size/--split-duration is one recording to every
command that reads it: named by its first part, its folder or a glob."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.sets import find_recordings
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from whiztap.sniffer.record.record_run import Recording, RecordSettings

from tests.cli_support import run_cli
from tests.record_support import LOCAL, WAIT, EchoServer, Segment, rebuild_streams

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
CONFIG = b"sr1-\x02200200-ss1"


def split_vpn_session(path: Path, parts: int = 3, idle_ticks: int = 0) -> list[str]:
    """One VPN connection whose requests and answers cross every split point:
    each split falls between a request and its answer."""
    file = RecordingFile(str(path), {"session_id": path.stem, "split_duration": "0.01"}, split_duration_ns=10 * MS)
    rec = Recorder(file)
    t = T0
    rec.start(t)
    rec.receive(Opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000"))
    rec.receive(Data(1, Direction.C2S, t, b"rr1-24--0--0-ss1"))
    rec.receive(Data(1, Direction.S2C, t + MS, CONFIG))
    for n in range(parts - 1):
        t += 2 * MS
        rec.receive(Data(1, Direction.C2S, t, b"rr1-1--0--0-ss1"))  # Sensor Request on channel 1
        t += 20 * MS
        rec.tick(t)  # the split duration is over
        for _ in range(idle_ticks):  # nothing happens for a while: no part is begun for it
            t += 20 * MS
            rec.tick(t)
        rec.receive(Data(1, Direction.S2C, t, b"cr1-1--%d--0-ss1" % n))  # its answer, in the next part
    rec.receive(Closed(1, t + MS, "client"))
    return rec.stop(t + 2 * MS).files


def test_a_session_crossing_split_points_is_judged_as_one(tmp_path):
    files = split_vpn_session(tmp_path / "s.mcap")
    assert len(files) == 3
    for name in (files[0], tmp_path, str(tmp_path / "s-*.mcap"), files[1]):
        result = run_cli("analyze", name, "--format", "json")
        assert result.returncode == 0, result.stdout + result.stderr  # no false config-first, no unanswered
        report = json.loads(result.stdout)
        assert report["rule_counts"] == {}
        assert len(report["connections"]) == 1
        assert {r["request"]: r["count"] for r in report["latency"]}["Sensor Request"] == 2
    lines = [json.loads(line) for line in run_cli("cat", files[0], "--format", "jsonl").stdout.splitlines()]
    answers = [line for line in lines if line["kind"] == "response"]
    assert len(answers) == 2 and not any(line["violations"] for line in lines)
    info = json.loads(run_cli("info", files[0], "--format", "json").stdout)
    assert info["connections"] == 1 and [p["path"] for p in info["parts"]] == files


def test_each_part_alone_still_reads(tmp_path):
    files = split_vpn_session(tmp_path / "s.mcap")
    [only] = find_recordings([files[1]])
    assert [str(p) for p in only.parts] == files  # a part names its whole set


def test_an_idle_recorder_and_a_stopping_one_leave_no_empty_part(tmp_path):
    files = split_vpn_session(tmp_path / "s.mcap", parts=2, idle_ticks=5)
    assert len(files) == 2  # not one part per idle tick, nor one for the stop alone


def test_two_recordings_in_one_folder_stay_two(tmp_path):
    split_vpn_session(tmp_path / "a.mcap")
    split_vpn_session(tmp_path / "b.mcap", parts=2)
    found = find_recordings([str(tmp_path)])
    assert [len(r.parts) for r in found] == [3, 2]


def test_a_missing_middle_part_is_said_and_the_rest_is_judged(tmp_path):
    files = split_vpn_session(tmp_path / "s.mcap", parts=4)
    Path(files[1]).unlink()
    result = run_cli("analyze", files[0], "--format", "json")
    assert "part 2 of this split recording is missing" in result.stderr
    assert "unexpected error" not in result.stderr
    assert result.returncode in (0, 1)


def test_replay_takes_the_set(tmp_path):
    files = split_vpn_session(tmp_path / "s.mcap")
    result = run_cli("replay", files[0], "--dry-run", "--target", "127.0.0.1:1")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("rr1-1--0--0-ss1") == 2


# -- a part name taken while recording: skipped, never a stop ---------------------------------------


def _whole_streams(files: list[str]) -> dict[tuple[int, str], bytes]:
    """Each stream rebuilt from every part's /tcp/reads, checked contiguous from 0."""
    segments: dict[tuple[int, str], list[Segment]] = {}
    for path in files:
        for key, found in rebuild_streams(path).items():
            segments.setdefault(key, []).extend(found)
    out = {}
    for key, found in segments.items():
        data = bytearray()
        for segment in sorted(found):
            assert segment.offset == len(data), f"{key}: a hole before {segment.offset}"
            data += segment.data
        out[key] = bytes(data)
    return out


@pytest.mark.slow
async def test_a_part_name_taken_while_recording_is_skipped_and_the_recording_goes_on(tmp_path):
    """Someone else's file at the second part's name, a link at the third's
    .part: each is skipped with a warning, neither is touched, the client's
    connection never notices, and every byte is in the parts written."""
    path = tmp_path / "r.mcap"
    foreign = tmp_path / "r-0002.mcap"
    foreign.write_bytes(b"someone else's")
    victim = tmp_path / "victim.txt"
    victim.write_bytes(b"keep me")
    (tmp_path / "r-0003.mcap.part").symlink_to(victim)
    warnings: list[str] = []
    finished: list[str] = []
    payload = bytes(range(256)) * 256  # 64 KiB a round trip: a part every few
    sent = 0
    async with EchoServer() as server:
        settings = RecordSettings((LOCAL, 0), (LOCAL, server.port), str(path), split_size=128 << 10,
                                  keep_secrets=True, overwrite=False)
        rec = Recording(settings, echo=finished.append, warn=warnings.append)
        await rec.start()
        try:
            reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
            # round trips until the writer has finished two parts (it rotates as it goes)
            while sum(line.startswith("finished ") for line in finished) < 2 and rec.error is None:
                assert sent < 1000, finished
                writer.write(payload)
                assert await asyncio.wait_for(reader.readexactly(len(payload)), WAIT) == payload
                sent += 1
                await asyncio.sleep(0.01)
            writer.close()
        finally:
            summary = await asyncio.wait_for(rec.stop(), WAIT)
    assert rec.error is None and summary is not None
    files = summary["files"]
    assert [Path(f).name for f in files[:2]] == ["r-0001.mcap", "r-0004.mcap"] and len(files) > 2
    assert foreign.read_bytes() == b"someone else's" and victim.read_bytes() == b"keep me"
    assert _whole_streams(files) == {(1, "c2s"): payload * sent, (1, "s2c"): payload * sent}
    assert len(warnings) == 1, warnings
    assert "r-0002.mcap" in warnings[0] and "r-0003.mcap.part" in warnings[0] and "r-0004.mcap" in warnings[0]
    # named by a part, one recording: the names skipped are neither in it nor said to be missing from it
    for named in (files[0], files[1]):
        [found] = find_recordings([named])
        assert [str(p) for p in found.parts] == files and found.missing == ()
