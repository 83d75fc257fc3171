"""A stated channel map (issue 29, item 6): ``--channels`` and ``--assume-config``.

Until the server announces its configuration, ``rr1-N--0--0-ss1`` may be a
Sensor Request, a Switch off or a Normal Send, and an ambiguous request is
never reported unanswered.  A client that never fetches the configuration,
talking to a server that stops answering (``blackhole dir:s2c``), used to
PASS; with the map stated, its unanswered requests are reported and the
report says the map was assumed.
"""

from __future__ import annotations

import asyncio
import json
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from whiztap.analyzer.analysis.report.schema import REPORT_SCHEMA
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.channels import parse_channels
from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.recording.format import metadata_record
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.replay.stub import Stub
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import Ran, run_cli
from tests.record_support import read_all, recording

T0 = 1_700_000_000_000_000_000
MAP = "servo:0-5,switch:6-8,switch1:9-11,sensor:12-23"
CONFIG_BYTES = b"sr1-\x18" + b"000" * 6 + b"100" * 3 + b"101" * 3 + b"200" * 12 + b"-ss1"  # MAP, as a server says it
CONFIG = escape(CONFIG_BYTES)


def _blackholed(path: Path, fetch_config: bool = False) -> Path:
    """A winsock session: two sensor requests answered, then two the server
    never answered (its answers blackholed), the client never having fetched
    the configuration (unless ``fetch_config``)."""
    rec = Recorder(RecordingFile(str(path), metadata_record(source="test", listen="", upstream="")))
    rec.start(T0)
    rec.receive(Opened(1, T0 + 1, "127.0.0.1:5555", "127.0.0.1:5000"))
    t = T0 + 10
    steps = [(Direction.S2C, b"sendchkpass"), (Direction.C2S, b"secret"), (Direction.S2C, b"readytogo")]
    if fetch_config:
        steps += [(Direction.C2S, b"rr1-0--0--0-ss1"), (Direction.S2C, CONFIG_BYTES)]
    steps += [(Direction.C2S, b"rr1-12--0--0-ss1"), (Direction.S2C, b"cr1-12--512--0-ss1"),
              (Direction.C2S, b"rr1-13--0--0-ss1"), (Direction.S2C, b"cr1-13--600--0-ss1"),
              (Direction.C2S, b"rr1-14--0--0-ss1"), (Direction.C2S, b"rr1-15--0--0-ss1")]
    for direction, data in steps:
        rec.receive(Data(1, direction, t, data))
        t += 1_000_000
    rec.receive(Closed(1, t + 10_000_000_000, "client", "closed"))
    rec.stop(t + 10_000_000_001)
    return path


def _report(*args: object) -> tuple[int, dict]:
    ran = run_cli("analyze", "--format", "json", "-q", *args)
    return ran.returncode, json.loads(ran.stdout)


def test_without_a_map_the_ambiguous_requests_go_unreported(tmp_path: Path) -> None:
    status, report = _report(_blackholed(tmp_path / "s.mcap"))
    assert "PW-PAIR-UNANSWERED" not in json.dumps(report)
    assert not any("assumed" in n for c in report["connections"] for n in c["notes"])
    assert "assumed_channels" not in report
    assert status == 0


@pytest.mark.parametrize("option", [("--channels", MAP), ("--assume-config", CONFIG), ("--assume-config", "FILE")])
def test_a_stated_map_reports_the_unanswered_requests(tmp_path: Path, option: tuple[str, str]) -> None:
    name, value = option
    if value == "FILE":
        (tmp_path / "config.txt").write_text(CONFIG + "\n")
        value = str(tmp_path / "config.txt")
    status, report = _report(_blackholed(tmp_path / "s.mcap"), name, value)
    assert status == 1
    unanswered = [v for v in report["violations"] if v["rule_id"] == "PW-PAIR-UNANSWERED"]
    assert [v["frame"] for v in unanswered] == ["rr1-14--0--0-ss1", "rr1-15--0--0-ss1"]
    notes = [n for c in report["connections"] for n in c["notes"]]
    assert any(f"channel map assumed (--channels {MAP})" in n for n in notes), notes
    assert "PW-AMBIGUOUS" not in json.dumps(report["violations"])
    assert report["assumed_channels"] == MAP
    jsonschema.validate(report, REPORT_SCHEMA)
    for fmt in ("text", "markdown", "html", "junit"):
        rendered = run_cli("analyze", "-q", "--format", fmt, tmp_path / "s.mcap", name, value).stdout
        assert f"Channel map assumed where the server never announced one: --channels {MAP}" in rendered \
            or f'name="assumed_channels" value="{MAP}"' in rendered, (fmt, rendered)


def test_the_servers_own_map_wins_and_the_note_goes(tmp_path: Path) -> None:
    status, report = _report(_blackholed(tmp_path / "s.mcap", fetch_config=True), "--channels", "servo:0-23")
    assert not any("assumed" in n for c in report["connections"] for n in c["notes"])
    assert "assumed_channels" not in report
    assert "PW-UNIT-MISMATCH" not in json.dumps(report["violations"])
    assert status == 1  # the two unanswered requests, resolved by the server's own map


def test_cat_reads_with_the_stated_map(tmp_path: Path) -> None:
    path = _blackholed(tmp_path / "s.mcap")
    assert "PW-AMBIGUOUS" in run_cli("cat", path).stdout
    ran = run_cli("cat", path, "--channels", MAP)
    assert ran.returncode == 0
    assert "PW-AMBIGUOUS" not in ran.stdout and "PW-PAIR-UNANSWERED" in ran.stdout


@pytest.mark.parametrize(("args", "words"), [
    (("--channels", "servo:0-5,sensor:7"), "channel 6 has no unit"),
    (("--channels", "motor:0-3"), "bad channel group"),
    (("--assume-config", "rr1-12--0--0-ss1"), "is not a usable configuration"),
    (("--assume-config", "sr1-\\x03000-ss1"), "is not a usable configuration"),
    (("--channels", MAP, "--assume-config", CONFIG), "give one"),
])
def test_a_bad_map_is_one_line(tmp_path: Path, args: tuple[str, ...], words: str) -> None:
    for command in ("analyze", "cat", "stub", "replay"):
        ran = run_cli(command, _blackholed(tmp_path / f"{command}.mcap"), *args)
        assert ran.returncode == 2, ran
        assert words in ran.stderr and len(ran.stderr.strip().splitlines()) == 1, ran.stderr
        assert "Traceback" not in ran.stderr


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=st.text(max_size=40), option=st.sampled_from(["--channels", "--assume-config"]))
def test_any_stated_map_is_taken_or_refused_in_one_line(tmp_path: Path, value: str, option: str) -> None:
    """Whatever text the user gives, a report or one line with exit 2."""
    path = tmp_path / "s.mcap"
    if not path.exists():
        _blackholed(path)
    ran = run_cli("analyze", "-q", path, option, value)
    assert ran.returncode in (0, 1, 2), ran
    if ran.returncode == 2:
        assert len(ran.stderr.strip().splitlines()) == 1 and "Traceback" not in ran.stderr, ran.stderr


# -- whiztap client fetches the configuration first ----------------------------------------------


def _client_through_the_proxy(path: Path, *client_args: str, **options: Any) -> Ran:
    """``whiztap client`` (in this process) against the real simulator behind
    the recording proxy (``options``: its settings), both on an event loop of
    their own in a thread."""
    port: Future[int] = Future()
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()

    async def serve() -> None:
        async with Simulator(port=0, mode="winsock", password="hunter2", seed=3) as sim, \
                recording(sim.port, str(path), **options) as rec:
            port.set_result(rec.proxy.port)
            await stop.wait()
            await rec.stop()

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),))
    thread.start()
    try:
        ran = run_cli("client", f"127.0.0.1:{port.result(20)}", "-p", "hunter2", *client_args)
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(20)
        loop.close()
    return ran


@pytest.mark.parametrize(("args", "config_first"), [((), True), (("--no-config",), False)])
def test_client_fetches_the_configuration_first(tmp_path: Path, args: tuple[str, ...], config_first: bool) -> None:
    path = tmp_path / "client.mcap"
    ran = _client_through_the_proxy(path, "sensor", "12", *args)
    assert ran.returncode == 0, ran
    assert ran.stdout.startswith("sensor 12 = "), ran.stdout
    report = _report(path)[1]
    rules = {v["rule_id"] for v in report["violations"]}
    assert ("PW-WINSOCK-CONFIG-FIRST" not in rules) is config_first, rules
    assert ("PW-AMBIGUOUS" not in rules) is config_first, rules
    assert report["summary"]["frames_by_kind"]["s2c"].get("config", 0) == int(config_first), report["summary"]


def test_tui_refuses_a_bad_map_in_one_line(tmp_path: Path) -> None:
    ran = run_cli("tui", _blackholed(tmp_path / "s.mcap"), "--channels", "motor:0-3")
    assert ran.returncode == 2 and "bad channel group" in ran.stderr, ran
    assert len(ran.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(("assumed", "missing"), [((), 0), (parse_channels(MAP), 2)])
async def test_stub_with_a_stated_map_counts_the_requests_it_cannot_answer(
        tmp_path: Path, assumed: tuple[ChannelConfig, ...], missing: int) -> None:
    """The recorded server never answered rr1-14 and rr1-15: without a map they
    only may have asked (no miss); with one they are Sensor Requests without
    a recorded answer, as ``stub --strict`` needs to know."""
    recorded = load_exchanges(_blackholed(tmp_path / "s.mcap"), assumed_channels=assumed)
    async with Stub(recorded, unmatched="ignore", assumed_channels=assumed) as stub:
        async with await Client.connect("127.0.0.1", stub.port, password="secret") as client:
            assert await client.sensor(12) == 512
            await client.send_raw(b"rr1-14--0--0-ss1")
            await client.send_raw(b"rr1-15--0--0-ss1")
            assert await client.sensor(13) == 600  # both requests were read before this answer came
        await asyncio.wait_for(stub.finished.wait(), 20)
    assert len(stub.unanswered) == missing, stub.unanswered


@pytest.mark.parametrize(("limits", "meaning"), [
    (Limits(), "Sensor Request ch 12 / Switch ch 12 off / Normal Send ch 12 = 0 (ambiguous)"),
    (Limits(assumed_channels=parse_channels(MAP)), "Sensor Request ch 12")])
def test_record_decodes_live_with_the_stated_map(tmp_path: Path, limits: Limits, meaning: str) -> None:
    """The recorder's writer process (which decodes /frames) gets the map
    through its configuration (``Limits.as_dict``)."""
    path = tmp_path / "r.mcap"
    ran = _client_through_the_proxy(path, "sensor", "12", "--no-config", limits=limits)
    assert ran.returncode == 0, ran
    frames = read_all(str(path))["/frames"]
    assert [f["meaning"] for f in frames if f["dir"] == "c2s" and f["kind"] == "command"] == [meaning]


def test_record_refuses_a_bad_map_in_one_line(tmp_path: Path) -> None:
    ran = run_cli("record", "--upstream", "127.0.0.1:1", "-o", tmp_path / "r.mcap", "--channels", "motor:0")
    assert ran.returncode == 2 and "bad channel group" in ran.stderr, ran
    assert len(ran.stderr.strip().splitlines()) == 1
