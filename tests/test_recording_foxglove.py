"""Recordings as the Foxglove app wants them (docs/recording-format.md, format
version 2): every violation also a ``foxglove.Log`` message on /log, one to one
with /violations; the plottable values on a topic per channel (/sensors/12),
defined on first use in each file, in every part of a split recording and in a
recovered .part; version 1 files still read by every reader; and the sample
layout names what a demo recording holds.  Real recordings through the real
Recorder and RecordingFile, read back with mcap's reader and with RecordingScan."""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import pytest
import jsonschema
import whiztap.analyzer.recording.scan as scan_module
from mcap.reader import make_reader
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode as encode_frame
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.encode import LOG_LEVELS
from whiztap.analyzer.recording.format import (
    CHANNEL_TOPICS,
    KNOWN_TOPICS,
    SCHEMAS,
    STREAM_TOPICS,
    TOPIC_LOG,
    TOPIC_VIOLATIONS,
    TOPICS,
    metadata_record,
)
from whiztap.analyzer.recording.info import set_info
from whiztap.analyzer.recording.recover import recover
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.cli_support import run_cli
from tests.record_support import read_all, tcp_reads
from tests.test_recording_format import FOXGLOVE_TOPIC, log_message

T0 = 1_700_000_000_000_000_000
C2S, S2C = Direction.C2S, Direction.S2C
ROOT = Path(__file__).parent.parent
V1_FILE = Path(__file__).parent / "data" / "format-v1-vpn.mcap"  # samples/vpn.mcap as format version 1 wrote it
# 24 channels: servos 0-7, switches 8-15, sensors 16-23 (as benchmarks/bench_core.py configures them)
CONFIG = encode_frame(m.ConfigurationSettings(tuple(
    m.ChannelConfig(0) if ch < 8 else m.ChannelConfig(1, 0, 1) if ch < 16 else m.ChannelConfig(2)
    for ch in range(24))))


def _recorder(path: Path, **file_options) -> Recorder:
    file = RecordingFile(str(path), metadata_record(source="test", session_id=path.stem), **file_options)
    rec = Recorder(file)
    rec.start(T0)
    return rec


def _configured(rec: Recorder, conn: int, t: int) -> int:
    rec.receive(Opened(conn, t, "127.0.0.1:5555", "127.0.0.1:5000"))
    rec.receive(Data(conn, C2S, t + 1, encode_frame(m.FetchConfiguration())))
    rec.receive(Data(conn, S2C, t + 2, CONFIG))
    return t + 3


def _poll(rec: Recorder, conn: int, t: int, answers: list[tuple[int, int]], servo: bool = False) -> int:
    """Requests for ``answers``' channels in one read, then the (channel, value) answers in one read."""
    request = m.ServoPositionRequest if servo else m.SensorRequest
    rec.receive(Data(conn, C2S, t, b"".join(encode_frame(request(ch)) for ch, _ in answers)))
    rec.receive(Data(conn, S2C, t + 1, b"".join(encode_frame(m.ChannelResponse(ch, v)) for ch, v in answers)))
    return t + 2


def _file_order(path: Path, topics: tuple[str, ...]) -> list[tuple[str, int, dict]]:
    """(topic, log time, message) of ``topics``, in file order, by mcap's reader."""
    with open(path, "rb") as f:
        return [(channel.topic, message.log_time, json.loads(message.data))
                for _, channel, message in make_reader(f, validate_crcs=True).iter_messages(
                    topics=list(topics), log_time_order=False)]


def _channels(path: Path) -> dict[str, int]:
    """Topic -> channel id, from the file's summary."""
    with open(path, "rb") as f:
        return {c.topic: c.id for c in make_reader(f).get_summary().channels.values()}


# -- /log: the violations for Foxglove's Log panel --------------------------------------------------


def test_every_violation_is_also_a_log_message_right_after_it_saying_the_same(tmp_path):
    """Frames breaking rules, a run of junk (one message per rule, with a
    count), a password, and requests found unanswered at the end (late)."""
    path = tmp_path / "log.mcap"
    rec = _recorder(path)
    rec.receive(Opened(1, T0 + 1, "127.0.0.1:5555", "127.0.0.1:5000"))
    steps = [(S2C, b"sendchkpass"), (C2S, b"secret"), (S2C, b"readytogo"), (C2S, b"rr1-24--0--0-ss1"),
             (S2C, CONFIG), (C2S, b"rr1-99--0--0-ss1rr1-016--0--0-ss1"), (C2S, b"junk\r\n" * 40),
             (C2S, b"rr1-16--0--0-ss1rr1-17--0--0-ss1")]
    for i, (d, data) in enumerate(steps):
        rec.receive(Data(1, d, T0 + 10 + i, data))
    rec.receive(Closed(1, T0 + 100, "client", "closed"))  # the last two requests: never answered
    summary = rec.stop(T0 + 101)
    by_topic = read_all(str(path))  # each message valid against its channel's schema in the file
    violations, logs = by_topic[TOPIC_VIOLATIONS], by_topic[TOPIC_LOG]
    assert len(violations) == len(logs) > 3
    assert sum(v.get("count", 1) for v in violations) == sum(summary.violations.values())
    assert any(v["late"] for v in violations) and any(v.get("count", 1) > 1 for v in violations)
    validator = jsonschema.Draft202012Validator(SCHEMAS["foxglove.Log"])
    for v, log in zip(violations, logs):
        validator.validate(log)
        assert log == log_message(v)
        assert log["name"] == v["rule_id"] and log["level"] == LOG_LEVELS[v["severity"]]
        assert log["timestamp"] == {"sec": v["t_ns"] // 10 ** 9, "nsec": v["t_ns"] % 10 ** 9}
        text = log["message"]
        assert text.startswith(f"{v['rule_id']}: {v['detail']} (conn {v['conn']}")
        if "dir" in v:
            assert f"conn {v['conn']} {v['dir']}" in text and log["file"] == f"conn-{v['conn']} {v['dir']}"
        if "frame_index" in v:
            assert f"frame {v['frame_index']}: {v['frame_text']}" in text and log["line"] == v["frame_index"]
    assert "secret" not in json.dumps(logs)
    # in the file, each /log message comes right after its /violations message, at the same log time
    pairs = _file_order(path, (TOPIC_VIOLATIONS, TOPIC_LOG))
    assert [topic for topic, _, _ in pairs] == [TOPIC_VIOLATIONS, TOPIC_LOG] * len(violations)
    assert all(pairs[i][1] == pairs[i + 1][1] for i in range(0, len(pairs), 2))
    with open(path, "rb") as f:  # whiztap's own reader gives the same, each checked against its schema
        assert [(topic, t, message) for topic, t, message in RecordingScan(f, (TOPIC_VIOLATIONS, TOPIC_LOG))
                .messages()] == pairs


# -- plot topics: one per channel -------------------------------------------------------------------------


def test_values_are_plotted_per_channel_on_topics_defined_on_first_use(tmp_path, monkeypatch):
    path = tmp_path / "plots.mcap"
    rec = _recorder(path, compression="")
    t = _configured(rec, 1, T0)
    sensors = [(16, 100), (17, 900), (16, 110), (17, 880), (16, 125)]
    t = _poll(rec, 1, t, sensors)
    rec.file.flush()  # /sensors/16 and /17 were defined after the first chunks: the servo's comes later still
    t = _poll(rec, 1, t, [(3, 4002)], servo=True)
    t = _poll(rec, 1, t, [(16, 130)])
    rec.receive(Data(1, C2S, t, encode_frame(m.NormalSend(3, 1500))))
    rec.receive(Data(1, S2C, t + 1, b"cr1-30--5--0-ss1"))  # an answer on no channel of the spec: unplotted, unpaired
    rec.stop(t + 2)
    by_topic = read_all(str(path))
    assert [(s["channel"], s["value"]) for s in by_topic["/sensors/16"]] == [(16, 100), (16, 110), (16, 125),
                                                                             (16, 130)]
    assert [s["value"] for s in by_topic["/sensors/17"]] == [900, 880]
    assert [(s["position"], s["data"]) for s in by_topic["/servos/3"]] == [(1000.5, 4002)]
    assert [s["value"] for s in by_topic["/sends/3"]] == [1500]
    for topic in ("/sensors/16", "/sensors/17", "/servos/3", "/sends/3"):  # "/sensors/16.value" plots as is
        assert FOXGLOVE_TOPIC.fullmatch(topic)
        for message in by_topic[topic]:
            field = "position" if topic.startswith("/servos") else "value"
            assert type(message[field]) in (int, float)
    # only the channels that occurred, no aggregated /sensors; defined before the chunks holding them
    assert set(_channels(path)) == set(TOPICS) | {"/sensors/16", "/sensors/17", "/servos/3", "/sends/3"}
    with open(path, "rb") as f:
        assert [d["value"] for _, _, d in RecordingScan(f, ("/sensors/16",)).messages()] == [100, 110, 125, 130]
    # a reader of streams still decompresses only the chunks of reads and events
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topic_of = {cid: c.topic for cid, c in summary.channels.items()}
    stream_chunks = sum(1 for c in summary.chunk_indexes
                        if {topic_of[cid] for cid in c.message_index_offsets} <= set(STREAM_TOPICS))
    opened = []
    real = scan_module.open_chunk
    monkeypatch.setattr(scan_module, "open_chunk", lambda *a: opened.append(a) or real(*a))
    with open(path, "rb") as f:
        assert len(list(tcp_reads(RecordingScan(f, STREAM_TOPICS)))) == 10
    assert len(opened) == stream_chunks < len(summary.chunk_indexes)


def test_a_channel_past_the_spec_is_plotted_on_the_other_topic(tmp_path):
    path = tmp_path / "other.mcap"
    rec = _recorder(path)
    t = _configured(rec, 1, T0)
    rec.receive(Data(1, C2S, t, b"rr1-16--0--0-ss1rr1-42--0--0-ss1"))
    rec.receive(Data(1, S2C, t + 1, b"cr1-16--7--0-ss1cr1-42--8--0-ss1"))
    rec.stop(t + 2)
    by_topic = read_all(str(path))
    assert [(s["channel"], s["value"]) for s in by_topic["/sensors/other"]] == [(42, 8)]
    assert set(_channels(path)) == set(TOPICS) | {"/sensors/16", "/sensors/other"}  # one topic for both past 23


@pytest.mark.slow
def test_each_part_of_a_split_recording_defines_the_channels_it_uses_with_the_same_ids(tmp_path):
    """Parts begin between reads and, for a read of thousands of frames, in the
    middle of its messages: the channels used after the cut are defined again
    in the new part, under the ids the messages were made with."""
    path = tmp_path / "split.mcap"
    rec = _recorder(path, split_size=64 << 10)
    t = _configured(rec, 1, T0)
    expected: dict[str, list[int]] = {"/sensors/16": [], "/sensors/17": [], "/sensors/18": []}
    for n in range(30):  # small reads: parts begin between them
        t = _poll(rec, 1, t, [(16, n), (17, 1000 - n)])
        expected["/sensors/16"].append(n)
        expected["/sensors/17"].append(1000 - n)
        rec.tick(t)
    big = [(16 + i % 3, i % 1024) for i in range(6000)]  # one read whose messages outgrow a part
    t = _poll(rec, 1, t, big)
    for ch, v in big:
        expected[f"/sensors/{ch}"].append(v)
    rec.receive(Closed(1, t, "client"))
    files = rec.stop(t + 1).files
    assert len(files) >= 3
    got: dict[str, list[int]] = {}
    ids: dict[str, int] = {}
    for part in files:
        by_topic = read_all(part)
        channels = _channels(Path(part))
        assert set(channels) - set(TOPICS) == {t for t in by_topic if t in CHANNEL_TOPICS}  # only those used
        for topic in expected:
            got.setdefault(topic, []).extend(s["value"] for s in by_topic.get(topic, []))
            if topic in channels:
                assert ids.setdefault(topic, channels[topic]) == channels[topic]
    assert got == expected
    assert sum(1 for part in files if "/sensors/18" in _channels(Path(part))) >= 2  # defined again after a cut
    info = set_info([Path(p) for p in files])
    assert {topic: info["topics"][topic] for topic in expected} == {k: len(v) for k, v in expected.items()}


def test_recovering_a_part_keeps_channels_defined_mid_file(tmp_path):
    path = tmp_path / "crash.mcap"
    rec = _recorder(path)
    t = _configured(rec, 1, T0)
    t = _poll(rec, 1, t, [(16, 1), (16, 2)])
    rec.file.flush()
    t = _poll(rec, 1, t, [(17, 3), (16, 4)])  # /sensors/17: defined after the first flush
    t = _poll(rec, 1, t, [(5, 400)], servo=True)
    rec.receive(Data(1, C2S, t, b"rr1-99--0--0-ss1"))  # a violation, and its /log message
    rec.file.flush()
    crashed = tmp_path / "crashed.mcap.part"
    crashed.write_bytes((tmp_path / "crash.mcap.part").read_bytes() + b"\x06half a chunk")  # as a kill leaves it
    rec.stop(t + 1)
    result = recover(str(crashed))
    assert result.output == str(tmp_path / "crashed.mcap") and result.cut_at is not None and not result.orphans
    by_topic = read_all(result.output)
    assert [s["value"] for s in by_topic["/sensors/16"]] == [1, 2, 4]
    assert [s["value"] for s in by_topic["/sensors/17"]] == [3]
    assert [s["data"] for s in by_topic["/servos/5"]] == [400]
    assert [log["name"] for log in by_topic[TOPIC_LOG]] == [v["rule_id"] for v in by_topic[TOPIC_VIOLATIONS]]
    assert len(by_topic[TOPIC_LOG]) >= 1
    with open(result.output, "rb") as f:
        assert [d["value"] for _, _, d in RecordingScan(f, ("/sensors/17",)).messages()] == [3]


# -- version 1 files ----------------------------------------------------------------------------------------


def test_a_version_1_file_reads_in_every_reader_with_its_aggregated_plot_topics(tmp_path):
    """Readers rebuild sessions from /tcp/reads: a file written before /log and
    the plot topics per channel analyses, lists and recovers as it always did."""
    v1 = tmp_path / "v1.mcap"
    shutil.copy(V1_FILE, v1)
    report = json.loads(run_cli("analyze", v1, "--format", "json").stdout)
    assert report["passed"] and report["rule_counts"] == {}
    lines = [json.loads(line) for line in run_cli("cat", v1, "--format", "jsonl").stdout.splitlines()]
    answers = [line for line in lines if line["kind"] == "response" and line["message"] == "Sensor/Servo Response"]
    info = json.loads(run_cli("info", v1, "--format", "json").stdout)
    assert info["format_version"] == "1" and info["topics"][TOPIC_LOG] == 0
    assert info["topics"]["/sensors"] + info["topics"]["/servos"] == len(answers) > 0
    with open(v1, "rb") as f:  # every message of every topic whiztap ever wrote, checked against its schema
        topics = {topic for topic, _, _ in RecordingScan(f, KNOWN_TOPICS).messages()}
    assert {"/sensors", "/servos", "/sends"} <= topics
    result = recover(str(v1), str(tmp_path / "again.mcap"))
    assert len(read_all(result.output)["/sensors"]) == info["topics"]["/sensors"]
    from whiztap.analyzer.analysis.exchanges import load_exchanges  # what replay and the stub read
    from whiztap.tui.data.model import TrafficModel
    from whiztap.tui.data.sources import FileSource

    assert load_exchanges(v1)
    model = TrafficModel(str(v1))
    FileSource(str(v1)).feed(model, threading.Event())
    assert model.store.count == len([line for line in lines if line["kind"] != "late_violation"])
    assert {key[0] for key in model.channel_values()} == {"sensor", "servo"}


# -- the sample layout -------------------------------------------------------------------------------------


def _leaves(node: object) -> list[str]:
    if isinstance(node, str):
        return [node]
    assert isinstance(node, dict) and node["direction"] in ("row", "column"), node
    return _leaves(node["first"]) + _leaves(node["second"])


@pytest.mark.slow
def test_the_sample_layout_shows_what_a_demo_recording_holds(tmp_path):
    layout = json.loads((ROOT / "samples" / "foxglove-layout.json").read_text())
    panels = layout["configById"]
    assert sorted(_leaves(layout["layout"])) == sorted(panels)
    assert {panel.split("!")[0] for panel in panels} == {"Plot", "Image", "RosOut", "RawMessages"}
    wanted: dict[str, str] = {}  # topic -> schema the panel needs
    for panel, config in panels.items():
        kind = panel.split("!")[0]
        if kind == "Plot":
            for path in config["paths"]:
                topic, field = path["value"].split(".")
                assert FOXGLOVE_TOPIC.fullmatch(topic) and topic in CHANNEL_TOPICS, topic
                assert SCHEMAS[CHANNEL_TOPICS[topic]]["properties"][field]["type"] in ("integer", "number")
                wanted[topic] = CHANNEL_TOPICS[topic]
        elif kind == "Image":
            wanted[config["imageMode"]["imageTopic"]] = "foxglove.CompressedImage"
        elif kind == "RosOut":
            wanted[config["topicToRender"]] = "foxglove.Log"
        else:
            wanted[config["topicPath"]] = TOPICS[config["topicPath"]]
    demo = tmp_path / "demo.mcap"
    result = run_cli("demo", "--headless", "--seconds", "2", "-o", demo, cwd=tmp_path)
    assert result.returncode in (0, 1) and demo.exists(), result.stdout + result.stderr
    by_topic = read_all(str(demo))
    for topic, schema in wanted.items():
        assert by_topic.get(topic) and KNOWN_TOPICS[topic] == schema, topic
