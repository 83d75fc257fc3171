"""``whiztap wireshark-dissector``: the Lua dissector, run by the real tshark
on recordings exported to pcapng, says what whiztap's analyzer says: the same
items with the same meanings, fields and rule violations (as expert info)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import pytest

from whiztap.analyzer.protocol.checksum import CHECKSUM_RULES
from whiztap.analyzer.protocol import messages
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.analyzer.recording.sets import find_one
from whiztap.analyzer.traffic import Closed, Data, Opened, UpstreamConnected
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.wireshark.dissector import generate, tables
from whiztap.sniffer.wireshark.export import export_pcapng
from tests.cli_support import run_cli

TSHARK = shutil.which("tshark")
pytestmark = pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (make test installs it with apt-get "
                                                       "as root: the Makefile's test-deps)")
ROOT = Path(__file__).parent.parent
SAMPLES = ROOT / "samples"
C, S = Direction.C2S, Direction.S2C
T0, MS = 1_700_000_000_000_000_000, 1_000_000
SEVERITY = {"error": 0x00800000, "warning": 0x00600000, "info": 0x00400000}  # Wireshark's PI_ERROR, PI_WARN, PI_NOTE


@pytest.fixture(scope="module")
def lua(tmp_path_factory) -> Path:
    """The dissector, written by the command as a user runs it."""
    path = tmp_path_factory.mktemp("lua") / "progwhiz.lua"
    done = run_cli("wireshark-dissector", "-o", path)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    return path


def _pcap(recording: Path, tmp_path: Path) -> Path:
    out = tmp_path / (recording.stem + ".pcapng")
    with open(out, "wb") as f:
        export_pcapng(find_one([str(recording)]), f)
    return out


def _tshark(pcap: Path, lua: Path, *fields: str, args: tuple[str, ...] = ()) -> list[list[str]]:
    """One row per packet that has Progwhiz items: each field's values (comma-separated by tshark)."""
    command = [TSHARK, "-r", str(pcap), "-X", f"lua_script:{lua}", *args, "-T", "fields",
               "-E", "occurrence=a", "-E", "aggregator=\x1f"]
    for field in ("tcp.stream", *fields):
        command += ["-e", field]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    errors = [line for line in done.stderr.splitlines() if "Running as user" not in line and line.strip()]
    assert done.returncode == 0 and not errors, done.stderr
    return [line.split("\t") for line in done.stdout.splitlines()]


def _analyzer_items(recording: Path, *args: str) -> list[dict]:
    done = run_cli("cat", recording, "--format", "jsonl", *args)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def _rules_by_connection(rows: list[list[str]]) -> dict[int, Counter]:
    out: dict[int, Counter] = defaultdict(Counter)
    for stream, rules in rows:
        out[int(stream) + 1].update(filter(None, rules.split("\x1f")))
    return {conn: counts for conn, counts in out.items() if counts}


def _analyzer_rules(recording: Path, *args: str) -> dict[int, Counter]:
    out: dict[int, Counter] = defaultdict(Counter)
    for item in _analyzer_items(recording, *args):
        out[item["conn"]].update(item["violations"])
    return {conn: counts for conn, counts in out.items() if counts}


@pytest.mark.slow
def test_every_violation_of_the_sample_is_expert_info_with_its_rule_id(lua, tmp_path):
    recording = SAMPLES / "violations.mcap"
    pcap = _pcap(recording, tmp_path)
    expected = _analyzer_rules(recording)
    assert set().union(*expected.values()) == set(RULES)  # the sample breaks every rule
    # one pass: all but a request never answered, which only the end of the file tells
    later = Counter({"PW-PAIR-UNANSWERED": 1_000})
    one_pass = {conn: left for conn, counts in expected.items() if (left := counts - later)}
    assert _rules_by_connection(_tshark(pcap, lua, "progwhiz.rule")) == one_pass
    # two passes (-R: the first builds the tree the dissector reads TCP's fields from): every one
    rows = _tshark(pcap, lua, "progwhiz.rule", "_ws.expert.message", "_ws.expert.severity", args=("-2", "-R", "tcp"))
    assert _rules_by_connection([row[:2] for row in rows]) == expected
    experts = {(m.split(":")[0], int(s)) for row in rows
               for m, s in zip(row[2].split("\x1f"), row[3].split("\x1f")) if m.startswith("PW-")}
    assert experts == {(rule.id, SEVERITY[str(rule.severity)]) for rule in RULES.values()}


@pytest.mark.slow
@pytest.mark.parametrize("sample", ["clean-winsock", "vpn", "failed-password", "violations"])
def test_items_and_their_meanings_are_the_analyzers(lua, tmp_path, sample):
    recording = SAMPLES / f"{sample}.mcap"
    rows = _tshark(_pcap(recording, tmp_path), lua, "progwhiz.direction", "progwhiz.kind", "progwhiz.meaning",
                   args=("-2", "-R", "tcp"))
    seen: dict[tuple[int, str], list[tuple[str, str]]] = defaultdict(list)
    for stream, directions, kinds, meanings in rows:
        for d, k, m in zip(directions.split("\x1f"), kinds.split("\x1f"), meanings.split("\x1f")):
            if d:
                seen[(int(stream) + 1, d)].append((k, m))
    expected: dict[tuple[int, str], list[tuple[str, str]]] = defaultdict(list)
    for item in _analyzer_items(recording):
        if item["kind"] != "late_violation":
            expected[(item["conn"], item["dir"])].append((item["kind"], item["meaning"]))
    assert dict(seen) == dict(expected)


@pytest.mark.slow
def test_fields_are_filterable_by_name(lua, tmp_path):
    recording = SAMPLES / "clean-winsock.mcap"
    pcap = _pcap(recording, tmp_path)
    sensors = [item["fields"]["sensor_value"] for item in _analyzer_items(recording)
               if item["fields"].get("sensor_value") is not None and item["fields"]["channel"] == 12]
    rows = _tshark(pcap, lua, "progwhiz.sensor_value", "progwhiz.request_in", "progwhiz.latency",
                   args=("-Y", "progwhiz.channel == 12 && progwhiz.kind == \"response\""))
    assert [int(row[1]) for row in rows] == sensors
    assert all(int(row[2]) > 0 and float(row[3]) > 0 for row in rows)  # each answers its request, after a while
    positions = _tshark(pcap, lua, "progwhiz.servo_position", args=("-Y", "progwhiz.servo_position"))
    assert [float(row[1]) for row in positions] == [item["fields"]["servo_position"] for item in _analyzer_items(
        recording) if "servo_position" in item["fields"]]
    titles = _tshark(pcap, lua, "progwhiz.message")
    assert {t for row in titles for t in row[1].split("\x1f") if t} >= {
        "Sensor Request", "Sensor/Servo Response", "Configuration Settings", "Set Configuration Settings",
        "Camera Image", "sendchkpass", "Password", "readytogo", "Play Internal Script"}
    assert _tshark(pcap, lua, "progwhiz.rule", args=("-Y", "progwhiz.rule")) == []  # a clean session


@pytest.mark.slow
def test_frames_split_across_segments_are_reassembled(lua, tmp_path):
    stream = (b"rr1-24--0--0-ss1", b"sr1-\x04000000101200-ss1", b"rr1-3--0--0-ss1", b"cr1-3--1000--0-ss1",
              b"rr1-0--0--2-ss1", b"cr1-0--4000--0-ss1", b"sr1-25--\x0c\x03\x00\x0c--0-ss1", b"rr1-3--0--0-ss1")
    events: list = [Opened(1, T0, "192.0.2.7:40001", "192.0.2.1:5000"), UpstreamConnected(1, T0 + MS)]
    t = T0 + 2 * MS
    for frame in stream:  # every frame in pieces of 5 bytes
        for i in range(0, len(frame), 5):
            t += MS
            events.append(Data(1, C if frame[:1] == b"r" or frame[:6] == b"sr1-25" else S, t, frame[i:i + 5]))
    events.append(Closed(1, t + MS, "client", "closed"))
    path = tmp_path / "pieces.mcap"
    recorder = Recorder(RecordingFile(str(path), {"source": "test"}))
    recorder.start(T0)
    for event in events:
        recorder.receive(event)
    recorder.stop(t + 2 * MS)
    rows = _tshark(_pcap(path, tmp_path), lua, "progwhiz.meaning", "progwhiz.data_from")
    meanings = [m for row in rows for m in row[1].split("\x1f") if m]
    assert meanings == [item["meaning"] for item in _analyzer_items(path)] == [
        "Fetch Configuration Settings", "Configuration Settings: 4 channels (2 servo, 1 switch, 1 sensor)",
        "Sensor Request ch 3", "Sensor value ch 3 = 1000", "Servo Position Request ch 0", "Servo 0 position 1000",
        "Set Configuration: 1 entry, checksum 12",
        "Normal Send ch 3 = 0"]  # channel 3 is a servo now: the channel map decides what the frame means
    assert [f for row in rows for f in row[2].split("\x1f") if f] == [
        "sensor data, by the request in frame 15", "servo data, by the request in frame 22"]


@pytest.mark.slow
def test_the_checksum_rule_is_a_preference(lua, tmp_path):
    recording = SAMPLES / "clean-winsock.mcap"  # its Set Configuration's checksum is dev-sum's
    pcap = _pcap(recording, tmp_path)
    for rule in CHECKSUM_RULES:
        rows = _tshark(pcap, lua, "progwhiz.rule", args=("-o", f"progwhiz.checksum_rule:{rule}"))
        assert _rules_by_connection(rows) == _analyzer_rules(recording, "--checksum-rule", rule)


@pytest.mark.slow
def test_the_port_preference_and_the_heuristic(lua, tmp_path):
    recording = SAMPLES / "vpn.mcap"
    pcap = _pcap(recording, tmp_path)
    port = read_metadata(str(recording))["upstream"].rpartition(":")[2]
    count = len(_analyzer_items(recording))

    def items(*args: str) -> int:
        rows = _tshark(pcap, lua, "progwhiz.kind", args=args)
        return sum(len([k for k in row[1].split("\x1f") if k]) for row in rows)

    assert items() == count  # found on a port nobody told it of
    assert items("--disable-heuristic", "progwhiz_tcp") == 0
    assert items("--disable-heuristic", "progwhiz_tcp", "-o", f"progwhiz.port:{port}") == count


def test_the_dissector_is_generated_from_the_analyzers_tables():
    data = tables()
    assert [r["id"] for r in data["rules"]] == list(RULES)
    titles = {cls.title for cls in vars(messages).values()
              if isinstance(cls, type) and issubclass(cls, messages.Message) and cls.title}
    assert {m["title"] for m in data["messages"].values()} == titles
    text = generate(6000, "dev-unit-sum", 2500)
    assert '["port"] = 6000' in text and '["checksum_rule"] = "dev-unit-sum"' in text
    assert all(rule in text for rule in RULES)


def test_the_command_refuses_what_it_should_and_helps(tmp_path):
    printed = run_cli("wireshark-dissector")
    assert printed.returncode == 0 and printed.stdout.startswith("-- Progwhiz Robotics Server API dissector")
    taken = tmp_path / "progwhiz.lua"
    taken.write_text("mine")
    for args, says in ((["-o", str(taken)], "exists; use --force"), (["--checksum-rule", "nope"], "nope")):
        refused = run_cli("wireshark-dissector", *args)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and says in refused.stderr
    assert taken.read_text() == "mine"
    helped = run_cli("wireshark-dissector", "--help")
    assert helped.returncode == 0 and "progwhiz.channel == 12" in helped.stdout


def _doc_commands() -> list[str]:
    text = (ROOT / "docs" / "wireshark.md").read_text()
    block = text.split("## Try it", 1)[1].split("```", 2)[1]
    return [line.split("  #")[0].strip() for line in block.splitlines()[1:] if line.strip()]


@pytest.mark.slow
def test_the_docs_commands_work_as_written(tmp_path):
    """Each command of docs/wireshark.md's walk-through, in order, in a shell,
    from a folder with the samples, as a person would type them."""
    (tmp_path / "samples").symlink_to(SAMPLES)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    outputs = []
    for command in _doc_commands():
        done = subprocess.run(command, shell=True, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, f"{command}: {done.stderr}"
        outputs.append(done.stdout)
    said = "\n".join(outputs)
    assert re.search(r"PW-RANGE-CHANNEL", said) and "Sensor value ch 3 = 1500" in said
