"""Verdicts on ordinary malformed traffic, recorded through the real proxy: every
command that judges a recording gives the same verdict, and none crashes."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.cli_support import WHIZTAP, run_cli, start_process
from tests.record_support import record_dialogue

CONFIG = b"sr1-\x18" + b"200" * 24 + b"-ss1"  # 24 sensors
FETCH_CONFIG = b"rr1-24--0--0-ss1"


async def config_then(path, config: bytes, command: bytes, answer: bytes):
    """Recorded through the real proxy: Fetch Configuration answered with
    ``config``, then ``command`` answered with ``answer``."""
    return await record_dialogue(
        path, [("recv", len(FETCH_CONFIG)), ("send", config), ("recv", len(command)), ("send", answer)],
        [("send", FETCH_CONFIG), ("recv", len(config)), ("send", command), ("recv", len(answer))])


def judged(path) -> tuple[dict, list[dict]]:
    """The report and cat's items; neither may crash."""
    report = run_cli("analyze", path, "--format", "json")
    assert report.returncode in (0, 1), report.stderr
    items = run_cli("cat", path, "--format", "jsonl")
    assert items.returncode == 0, items.stderr
    assert "unexpected error" not in report.stderr + items.stderr
    return json.loads(report.stdout), [json.loads(line) for line in items.stdout.splitlines()]


@pytest.mark.parametrize("answer", [b"cr1-12-ss1", b"cr1--ss1", b"cr1-12--\xff\xfe--0-ss1", b"cr1-12--1x0--0-ss1"])
async def test_an_answer_that_does_not_parse_is_judged_not_a_crash(tmp_path, answer):
    path = await config_then(tmp_path / "r.mcap", CONFIG, b"rr1-12--0--0-ss1", answer)
    report, items = judged(path)
    assert not report["passed"]
    assert any(line["kind"] == "response" and line["violations"] for line in items)
    live = run_cli("decode", "-f", answer.decode("latin-1").encode("unicode_escape").decode())
    assert live.returncode == 1 and "unexpected error" not in live.stderr


async def test_a_login_abandoned_mid_password_is_judged_not_a_crash(tmp_path):
    """Recorded with the default redaction: the password bytes are masked."""
    path = await record_dialogue(
        tmp_path / "r.mcap", [("send", b"sendchkpass\r\n"), ("recv", 4)],
        [("recv", 13), ("send", b"prog"), ("eof",), ("sleep", 0.1)])
    report, items = judged(path)
    [conn] = report["connections"]
    assert conn["mode"] == "winsock"
    assert b"prog" not in json.dumps(items).encode()
    # the file is in stream order: the held (masked) password read comes before its side's half-close
    from whiztap.analyzer.recording.format import STREAM_TOPICS, TOPIC_READS
    from whiztap.analyzer.recording.scan import RecordingScan

    with open(path, "rb") as f:
        order = [("read", m["dir"]) if topic == TOPIC_READS else (m["event"], m.get("dir"))
                 for topic, _t, m in RecordingScan(f, STREAM_TOPICS).messages()]
    assert order.index(("read", "c2s")) < order.index(("half_closed", "c2s"))


# -- CI gates ---------------------------------------------------------------------------------


def foreign_mcap(path) -> str:
    """An MCAP file another tool wrote: its own topic, no whiztap metadata."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start("other", "another tool")
        schema = w.register_schema("Foo", "jsonschema", b"{}")
        channel = w.register_channel("/foo", "json", schema)
        w.add_message(channel, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    return str(path)


@pytest.mark.slow
async def test_a_report_on_nothing_does_not_pass(tmp_path):
    from tests.record_support import closed_port, recording

    async with recording(closed_port(), str(tmp_path / "empty.mcap")):
        pass  # nobody connected
    unreached = tmp_path / "unreached.mcap"
    async with recording(closed_port(), str(unreached), connect_timeout=0.2) as rec:
        from tests.record_support import play_client

        await play_client(rec.proxy.port, [("send", b"rr1-24--0--0-ss1"), ("sleep", 0.5)])
    foreign = run_cli("analyze", foreign_mcap(tmp_path / "other.mcap"))  # says what it found, fails the gate
    assert foreign.returncode == 2 and "not a whiztap recording" in foreign.stderr and "/foo" in foreign.stderr
    for path, why in ((tmp_path / "empty.mcap", "no connection"), (unreached, "never reached")):
        for fmt in ("text", "json", "junit", "markdown"):
            result = run_cli("analyze", path, "--format", fmt)
            assert result.returncode == 3, (path, fmt, result.stdout, result.stderr)
            assert why in result.stdout and why in result.stderr and len(result.stderr.splitlines()) == 1
            assert "PASS" not in result.stdout
        allowed = run_cli("analyze", path, "--allow-empty", "--format", "json")
        assert allowed.returncode == 0 and json.loads(allowed.stdout)["passed"]


async def test_markdown_never_cuts_a_frame_silently(tmp_path):
    long_garbage = b"\x01" * 300
    path = await record_dialogue(tmp_path / "r.mcap", [("recv", 16 + len(long_garbage))],
                                 [("send", b"rr1-24--0--0-ss1" + long_garbage)])
    md = run_cli("analyze", path, "--format", "markdown").stdout
    data = json.loads(run_cli("analyze", path, "--format", "json").stdout)
    [garbage] = [v for v in data["violations"] if v["rule_id"] == "PW-FRAME-GARBAGE"]
    assert garbage["frame"] == "\\x01" * 300  # whole in the JSON
    assert "\\x01" * 20 + "…`" in md and "\\x0…" not in md


def test_dash_is_standard_output_and_a_closed_pipe_is_quiet():
    from tests.test_analyze import CLEAN

    for args in (("analyze", CLEAN, "-o", "-", "--format", "json"), ("cat", CLEAN, "-o", "-")):
        result = run_cli(*args)
        assert result.returncode == 0 and result.stdout, args
    # processes of their own: a real pipe that closes early
    piped = subprocess.run(f"{WHIZTAP} cat {CLEAN} | head -1", shell=True, capture_output=True, text=True,
                           timeout=60, executable="/bin/bash")
    code = subprocess.run(f"set -o pipefail; {WHIZTAP} cat {CLEAN} | head -1 >/dev/null", shell=True,
                          capture_output=True, text=True, timeout=60, executable="/bin/bash")
    assert len(piped.stdout.splitlines()) == 1 and piped.stderr == ""
    assert code.returncode == 0 and code.stderr == ""


@pytest.mark.parametrize("args", [("record", "--upstream", "127.0.0.1:1"), ("capture", "--pcap", "x", "--port", "1"),
                                  ("recover", "x.part"), ("replay", "missing.mcap", "--target", "127.0.0.1:1")])
def test_a_recording_cannot_go_to_standard_output_and_no_file_named_dash_appears(tmp_path, args):
    result = run_cli(*args, "-o", "-", cwd=tmp_path)
    assert result.returncode == 2 and "-o -: a recording is written to a file" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_cat_takes_the_filter_bars_words():
    from tests.test_analyze import CLEAN

    lines = [json.loads(line) for line in
             run_cli("cat", CLEAN, "--format", "jsonl", "--filter", "kind:response ch:12").stdout.splitlines()]
    assert lines and all(line["kind"] == "response" and line["fields"]["channel"] == 12 for line in lines)
    bad = run_cli("cat", CLEAN, "--filter", "kind:nonsense")
    assert bad.returncode == 2 and bad.stderr.startswith("whiztap: --filter: kind:")


@pytest.mark.slow
async def test_cat_follow_tails_a_recording_being_written(tmp_path):
    import asyncio

    from whiztap.sniffer.sim.simulator import Simulator
    from tests.record_support import RecordProcess, play_client

    out = tmp_path / "live.mcap"
    async with Simulator(mode="vpn", seed=1) as sim:
        rec = await RecordProcess.start(sim.port, out)
        follower = await start_process("cat", "--follow", f"{out}.part")
        await play_client(rec.port, [("send", b"rr1-24--0--0-ss1"), ("recv", 4 + 1 + 3 * 24 + 4)])
        first = await asyncio.wait_for(follower.stdout.readline(), 20)
        assert b"rr1-24--0--0-ss1" in first  # shown while the recording goes on
        await rec.finish()
        rest, err = await asyncio.wait_for(follower.communicate(), 20)
    assert follower.returncode == 0, err
    assert b"config" in rest


async def test_info_and_cat_say_a_recording_is_being_written_not_a_crash_leftover(tmp_path):
    from whiztap.sniffer.sim.simulator import Simulator
    from tests.record_support import RecordProcess, play_client

    out = tmp_path / "live.mcap"
    async with Simulator(mode="vpn", seed=1) as sim:
        rec = await RecordProcess.start(sim.port, out)
        await play_client(rec.port, [("send", b"rr1-24--0--0-ss1"), ("recv", 4 + 1 + 3 * 24 + 4)])
        try:
            info = run_cli("info", f"{out}.part")
            cat = run_cli("cat", f"{out}.part")
        finally:
            await rec.finish()
    assert "being written by a running recorder" in info.stdout and "crash" not in info.stdout
    assert "recover" not in info.stdout
    assert cat.returncode == 2 and "is being written by a running recorder" in cat.stderr
    assert "cut short" not in cat.stderr


@pytest.mark.slow
async def test_a_camera_image_of_several_megabytes_is_one_frame_end_to_end(tmp_path):
    from tests.streams import big_jpeg

    picture = big_jpeg(5_000_000)
    config = b"sr1-\x01200-ss1"
    path = await config_then(tmp_path / "camera.mcap", config, b"rr1-29--0--0-ss1", picture)
    report, items = judged(path)
    assert report["rule_counts"] == {} and report["passed"], report["rule_counts"]
    [image] = [i for i in items if i["kind"] == "image"]
    assert image["fields"]["data"] == len(picture)
    assert {r["request"] for r in report["latency"]} >= {"Fetch Camera Image"}
    small = run_cli("analyze", path, "--max-image", "1M", "--format", "json")  # the bound is the user's to set
    assert "PW-FRAME-OVERSIZE" in json.loads(small.stdout)["rule_counts"]


def test_the_progress_bar_moves_with_several_processes(tmp_path, monkeypatch):
    """analyze -j 2: each file done in a worker advances the bar by its size."""
    import shutil
    import sys

    from whiztap.analyzer.cli import analyze as analyze_cli
    from whiztap.analyzer.recording.sets import find_recordings
    from whiztap.analyzer.protocol.session import Limits
    from tests.test_analyze import CLEAN, VPN

    for i, sample in enumerate((CLEAN, VPN, CLEAN, VPN)):
        shutil.copy(sample, tmp_path / f"{i}.mcap")
    monkeypatch.setattr(analyze_cli.ByteProgress, "THRESHOLD", 0)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: the bar shows
    found = find_recordings([str(tmp_path)])
    total = sum(p.stat().st_size for r in found for p in r.parts)
    with analyze_cli.ByteProgress([p for r in found for p in r.parts], enabled=True) as progress:
        analysis, unreadable = analyze_cli._analyse_all(found, "dev-sum", Limits(), 2, progress)
        done = progress.bar.tasks[0].completed
    assert unreadable == [] and len(analysis.files) == 4
    assert done == total


@pytest.mark.slow
def test_columns_is_honoured_on_a_terminal():
    import os
    import pty

    from tests.test_analyze import VIOLATIONS

    widths = {}
    for columns in ("60", "200"):
        leader, follower = pty.openpty()
        proc = subprocess.Popen([WHIZTAP, "analyze", str(VIOLATIONS)], stdout=follower, stderr=follower,
                                env={**os.environ, "COLUMNS": columns, "TERM": "xterm"})
        os.close(follower)
        out = b""
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:
                break
            if not chunk:
                break
            out += chunk
        proc.wait(timeout=60)
        os.close(leader)
        import re

        text = re.sub(rb"\x1b\[[0-9;]*m", b"", out).decode(errors="replace")
        widths[columns] = max(len(line.rstrip("\r")) for line in text.splitlines())
    assert widths["60"] <= 60 < widths["200"] <= 200


def test_the_answer_deadline_is_set_from_the_command_line():
    from tests.test_analyze import CLEAN

    default = json.loads(run_cli("analyze", CLEAN, "--format", "json").stdout)
    impatient = json.loads(run_cli("analyze", CLEAN, "--format", "json", "--answer-timeout", "0.000001").stdout)
    assert "PW-PAIR-UNANSWERED" not in default["rule_counts"]
    assert impatient["rule_counts"].get("PW-PAIR-UNANSWERED", 0) > 0
    assert "PW-PAIR-UNSOLICITED" not in impatient["rule_counts"]  # late answers still pair
    lines = run_cli("cat", CLEAN, "--format", "jsonl", "--answer-timeout", "0.000001").stdout
    assert "PW-PAIR-UNANSWERED" in lines


def test_capture_on_an_interface_that_does_not_exist_is_one_line(tmp_path):
    result = run_cli("capture", "--iface", "nosuch0", "--port", "5000", "-o", tmp_path / "x.mcap")
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "cannot capture on nosuch0: no such interface" in result.stderr
