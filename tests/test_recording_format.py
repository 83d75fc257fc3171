"""The recording format: schemas, messages, the fast reader, the file writer and
the recorder, in process; and a second MCAP implementation reading our files."""

from __future__ import annotations

import base64
import errno
import io
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import jsonschema
import pytest
import whiztap.analyzer.recording.scan as scan_module
import whiztap.sniffer.record.recorder as recorder_module
import whiztap.sniffer.record.writer as writer_module
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.recording.encode import (
    FrameEncoder,
    cat_line,
    encode,
    encode_plots,
    encode_read,
    encode_violation,
    LOG_LEVELS,
    frame_static,
    plot_messages,
    read_message,
    violation_message,
)
from whiztap.analyzer.recording.format import (
    CHANNEL_TOPICS,
    FORMAT_VERSION,
    KNOWN_TOPICS,
    MIRROR_TOPICS,
    MITM_TOPICS,
    PLOT_TOPICS,
    SCHEMAS,
    STREAM_TOPICS,
    TOPIC_FRAMES,
    TOPIC_READS,
    TOPICS,
    metadata_record,
    schema_bytes,
)
from whiztap.analyzer.recording.scan import RecordingError, RecordingScan, read_metadata
from whiztap.analyzer.traffic import Closed, Data, Opened, UpstreamFailed
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError

from tests.record_support import read_all, rebuild_streams, stream_bytes, tcp_reads
from tests.streams import chunked, stream_pieces

T0 = 1_700_000_000_000_000_000
C2S, S2C = Direction.C2S, Direction.S2C
CHECK = Path(__file__).parent / "mcap_check"



def frame_message(conn: int, obs, offset: int, redact: bool) -> dict:
    """A /frames message built plainly, as a dict: what ``FrameEncoder`` must
    give byte for byte (docs/recording-format.md)."""
    item = obs.item
    return {
        "conn": conn, "dir": obs.direction.value, "index": obs.index,
        "t_start_ns": item.t_start_ns, "t_end_ns": item.t_end_ns, "offset": offset,
        "answers": obs.answers.index if obs.answers is not None else None, "latency_ns": obs.latency_ns,
        **frame_static(obs, redact),
    }

def log_message(violation: dict) -> dict:
    """A /log message built plainly, as a dict, from its /violations message:
    what ``encode_violation`` must give byte for byte (docs/recording-format.md, ``/log``)."""
    t, conn = violation["t_ns"], violation["conn"]
    where = f"conn {conn}" + (f" {violation['dir']}" if "dir" in violation else "")
    if "frame_index" in violation:
        where += f", frame {violation['frame_index']}: {violation['frame_text']}"
    if violation["late"]:
        where += ", found later"
    return {"timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000},
            "level": LOG_LEVELS[violation["severity"]],
            "message": f"{violation['rule_id']}: {violation['detail']} ({where})", "name": violation["rule_id"],
            "file": f"conn-{conn}" + (f" {violation['dir']}" if "dir" in violation else ""),
            "line": violation.get("frame_index", 0)}


def _recorder(path: Path, **kwargs) -> Recorder:
    metadata = metadata_record(source="test", listen="", upstream="")
    file = RecordingFile(str(path), metadata, **{k: kwargs.pop(k) for k in list(kwargs)
                                                 if k in ("split_size", "split_duration_ns", "compression")})
    rec = Recorder(file, **kwargs)
    rec.start(T0)
    return rec


def _session(rec: Recorder, conn: int = 1, t: int = T0) -> int:
    """A short winsock session with a password sent in three reads."""
    rec.receive(Opened(conn, t + 1, "127.0.0.1:5555", "127.0.0.1:5000"))
    steps = [(S2C, b"sendchkpass"), (C2S, b"pa"), (C2S, b"ss"), (C2S, b"wd"), (S2C, b"readytogo"),
             (C2S, b"rr1-24--0--0-ss1"), (S2C, b"sr1-\x03200000101-ss1"), (C2S, b"rr1-0--0--0-ss1"),
             (S2C, b"cr1-0--1000--0-ss1"), (C2S, b"rr1-1--0--2-ss1"), (S2C, b"cr1-1--4000--0-ss1"),
             (C2S, b"rr1-1--7--0-ss1rr1-2--1--0-ss1rr1-99--0--0-ss1")]
    for i, (d, data) in enumerate(steps):
        rec.receive(Data(conn, d, t + 10 + i, data))
    rec.receive(Closed(conn, t + 100, "client", "closed"))
    return t + 100


# -- schemas and topics ------------------------------------------------------------------------------


# A topic name as Foxglove's message-path grammar reads one unquoted: slash-separated
# ids of letters, digits, '_' and '-', so "/sensors/12.value" is topic "/sensors/12", field "value".
FOXGLOVE_TOPIC = re.compile(r"(/[A-Za-z0-9_-]+)+")


def test_every_schema_is_valid_json_schema_and_every_topic_is_foxglove_friendly():
    for name, schema in SCHEMAS.items():
        jsonschema.Draft202012Validator.check_schema(schema)
        assert json.loads(schema_bytes(name)) == schema
        assert "$ref" not in json.dumps(schema)  # Foxglove does not follow references
    for topic, schema in KNOWN_TOPICS.items():
        assert FOXGLOVE_TOPIC.fullmatch(topic) and schema in SCHEMAS, topic
    assert set(KNOWN_TOPICS) == {*TOPICS, *MITM_TOPICS, *MIRROR_TOPICS, *CHANNEL_TOPICS, *PLOT_TOPICS}
    assert len(CHANNEL_TOPICS) == 4 * 25 and "/sensors/12" in CHANNEL_TOPICS and "/sends/other" in CHANNEL_TOPICS
    image = SCHEMAS["foxglove.CompressedImage"]["properties"]
    assert set(image) == {"timestamp", "frame_id", "data", "format"}
    log = SCHEMAS["foxglove.Log"]
    assert set(log["properties"]) == set(log["required"]) == {"timestamp", "level", "message", "name", "file", "line"}
    assert [c["const"] for c in log["properties"]["level"]["oneOf"]] == [0, 1, 2, 3, 4, 5]


def test_a_recorded_session_has_every_channel_valid_and_plottable(tmp_path):
    path = tmp_path / "s.mcap"
    rec = _recorder(path)
    summary = rec.stop(_session(rec))
    assert summary.connections == 1 and summary.files == [str(path)]
    by_topic = read_all(str(path))  # schemas validated, CRCs checked, log_time monotonic
    assert [(m["channel"], m["value"]) for m in by_topic["/sensors/0"]] == [(0, 1000)]
    assert [(m["channel"], m["data"], m["position"]) for m in by_topic["/servos/1"]] == [(1, 4000, 1000.0)]
    assert [(m["channel"], m["value"]) for m in by_topic["/sends/1"]] == [(1, 7)]
    assert [(m["channel"], m["state"]) for m in by_topic["/switches/2"]] == [(2, 1)]
    assert all(isinstance(m["latency_ns"], int) for m in by_topic["/sensors/0"] + by_topic["/servos/1"])
    with open(path, "rb") as f:  # the channels that occurred, and no aggregated plot topic
        assert {c.topic for c in make_reader(f).get_summary().channels.values()} == set(TOPICS) | {
            "/sensors/0", "/servos/1", "/sends/1", "/switches/2"}
    violations = {v["rule_id"]: v for v in by_topic["/violations"]}
    assert violations["PW-RANGE-CHANNEL"]["level"] == 3 and violations["PW-RANGE-CHANNEL"]["frame_index"] > 0
    assert [m["name"] for m in by_topic["/log"]] == [v["rule_id"] for v in by_topic["/violations"]]
    meta = read_metadata(str(path))
    assert meta["format_version"] == FORMAT_VERSION == "4" and meta["spec_revision"] == "1.8" and meta["part"] == "1"
    assert meta["source"] == "test"


def test_a_request_to_a_server_never_reached_is_reported_as_such_live_and_in_the_report(tmp_path):
    path = tmp_path / "down.mcap"
    rec = _recorder(path)
    rec.receive(Opened(1, T0 + 1, "127.0.0.1:5555", "127.0.0.1:5000"))
    rec.receive(Data(1, C2S, T0 + 2, b"rr1-24--0--0-ss1"))  # sent while the proxy was still connecting
    rec.receive(UpstreamFailed(1, T0 + 3, "cannot connect to 127.0.0.1:5000: Connection refused"))
    rec.receive(Closed(1, T0 + 4, "server", "cannot connect to 127.0.0.1:5000: Connection refused"))
    rec.stop(T0 + 5)
    why = ("Fetch Configuration Settings: the server was never reached "
           "(cannot connect to 127.0.0.1:5000: Connection refused)")
    assert [(v["rule_id"], v["detail"]) for v in read_all(str(path))["/violations"]] == [("PW-PAIR-UNANSWERED", why)]
    from whiztap.analyzer.analysis.report.content import build
    from whiztap.analyzer.cli.analyze import analyse_file

    report = build(analyse_file(path, "dev-sum"))
    assert [(v["rule_id"], v["detail"]) for v in report["violations"]] == [("PW-PAIR-UNANSWERED", why)]


def test_password_is_masked_in_reads_and_frames_yet_streams_rebuild_the_same(tmp_path):
    path = tmp_path / "pw.mcap"
    rec = _recorder(path)
    rec.stop(_session(rec))
    by_topic = read_all(str(path))
    password = [f for f in by_topic["/frames"] if f["kind"] == "password"]
    assert len(password) == 1
    assert password[0]["text"] == "<redacted>" and password[0]["fields"] == {"message": "Password", "length": 6}
    assert base64.b64decode(password[0]["raw"]) == b"******"
    c2s_reads = [r for r in by_topic["/tcp/reads"] if r["dir"] == "c2s"][:3]
    assert [base64.b64decode(r["data"]) for r in c2s_reads] == [b"**", b"**", b"**"]
    assert all(r["redacted"] == [[0, 2]] for r in c2s_reads)
    reads, frames = rebuild_streams(str(path)), rebuild_streams(str(path), TOPIC_FRAMES)
    assert reads == frames
    assert stream_bytes(reads[(1, "c2s")]).startswith(b"******rr1-24")
    assert "passwd" not in json.dumps(by_topic)


def test_a_password_left_pending_is_masked_after_the_hold_limit(tmp_path, monkeypatch):
    monkeypatch.setattr(recorder_module, "HOLD_LIMIT_S", 0.0)
    path = tmp_path / "hold.mcap"
    rec = _recorder(path)
    rec.receive(Opened(1, T0 + 1, "a:1", "b:2"))
    rec.receive(Data(1, S2C, T0 + 2, b"sendchkpass"))
    rec.receive(Data(1, C2S, T0 + 3, b"topsecret"))  # no verdict yet: held
    rec.receive(Data(1, S2C, T0 + 4, b"cr1-0--1--0-ss1"))  # behind it in /tcp/reads order
    rec.tick(T0 + 5)  # the hold limit passed: masked and written
    rec.receive(Data(1, S2C, T0 + 6, b"readytogo"))
    rec.stop(T0 + 7)
    reads = read_all(str(path))["/tcp/reads"]
    assert [base64.b64decode(r["data"]) for r in reads] == [b"sendchkpass", b"*********", b"cr1-0--1--0-ss1",
                                                            b"readytogo"]


@settings(max_examples=60, deadline=None)
@given(pieces=stream_pieces(), answers=stream_pieces(), cuts=st.lists(st.integers(0, 2000), max_size=8),
       redact=st.booleans())
def test_the_fast_encoders_write_exactly_what_the_reference_dicts_say(pieces, answers, cuts, redact):
    """Frames, reads, plot and log messages are built by string templates and
    a cache on the hot path; they must equal the plain dict builders, encoded."""
    s = Session()
    encoder = FrameEncoder()
    events = s.receive(S2C, b"sendchkpass", 1) + s.receive(C2S, b"pw\r\nrr1-24--0--0-ss1", 2)
    events += s.receive(S2C, b"readytogosr1-\x03200000101-ss1", 3)
    events += s.receive(C2S, b"rr1-0--0--0-ss1rr1-1--0--2-ss1rr1-1--500--0-ss1rr1-2--1--0-ss1", 3)
    events += s.receive(S2C, b"cr1-0--7--0-ss1cr1-1--4000--0-ss1", 3)
    for t, chunk in enumerate(chunked(b"".join(pieces), cuts), start=4):
        events += s.receive(C2S, chunk, t)
        events += s.receive(S2C, b"".join(answers[:t % 4]) + b"cr1-0--7--0-ss1cr1-1--4000--0-ss1", t)
    events += s.close(99)
    offset = 0
    for obs in events:
        if not hasattr(obs, "item"):
            late = violation_message(3, obs.violation, obs.about, obs.t_ns, True, redact)
            assert encode_violation(3, obs.violation, obs.about, obs.t_ns, True, redact) == (
                encode(late), encode(log_message(late)))
            continue
        for v in obs.violations:
            count = len(obs.violations)
            found = violation_message(3, v, obs, obs.item.t_end_ns, False, redact, count)
            assert encode_violation(3, v, obs, obs.item.t_end_ns, False, redact, count) == (
                encode(found), encode(log_message(found)))
        for _ in range(2):  # a cache miss, then a hit
            assert encoder.encode(3, obs, offset, redact) == encode(frame_message(3, obs, offset, redact))
        assert encode_plots(3, obs) == [(topic, encode(m)) for topic, m in plot_messages(3, obs)]
        assert encode_read(3, obs.direction.value, obs.item.t_end_ns, offset, obs.item.raw) == encode(
            read_message(3, obs.direction.value, obs.item.t_end_ns, offset, obs.item.raw))
        offset += len(obs.item.raw)
    topics = {topic for obs in events if hasattr(obs, "item") for topic, _ in encode_plots(3, obs)}
    assert topics <= set(CHANNEL_TOPICS) | set(TOPICS)
    assert {topic.rsplit("/", 1)[0] for topic in topics} >= {"/sensors", "/servos", "/sends", "/switches"}


def test_cat_lines_and_frames_describe_an_item_alike_with_every_documented_key():
    """``whiztap cat --format jsonl`` and /frames share one description of an
    item; cat's keys are the documented ones, each with the value /frames
    gives (its bytes as raw_b64; the latency inside the fields, as cat always had)."""
    s = Session()
    events = s.receive(C2S, b"rr1-24--0--0-ss1", 1) + s.receive(S2C, b"sr1-\x03200000101-ss1", 2)
    events += s.receive(C2S, b"rr1-0--0--0-ss1junk", 3) + s.receive(S2C, b"cr1-0--7--0-ss1", 4) + s.close(5)
    observations = [e for e in events if hasattr(e, "item")]
    assert {o.item.kind.value for o in observations} >= {"command", "response", "config", "unframed"}
    section = (Path(__file__).parent.parent / "docs" / "recording-format.md").read_text()
    section = section.split("## `whiztap cat --format jsonl`")[1].split("\n## ")[0]
    documented = re.findall(r"^\| `(\w+)` \|", section, re.M)
    for obs in observations:
        line = cat_line(1, obs)
        assert list(line) == documented
        frame = frame_message(1, obs, 0, False)
        for key in set(line) - {"t_ns", "raw_b64", "fields"}:
            assert line[key] == frame[key], key
        assert line["raw_b64"] == frame["raw"] and line["t_ns"] == frame["t_end_ns"]
        assert line["fields"] == {**frame["fields"], **({"latency_ns": obs.latency_ns} if obs.latency_ns else {})}
    assert any(cat_line(1, o)["fields"].get("latency_ns") for o in observations)


# -- reading -------------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(reads=st.lists(st.tuples(st.integers(1, 4), st.sampled_from([C2S, S2C]), st.binary(min_size=1, max_size=300)),
                      max_size=60),
       compression=st.sampled_from(["zstd", "lz4", ""]))
def test_the_fast_reader_gives_back_every_read_exactly(tmp_path, reads, compression):
    path = tmp_path / f"fast-{compression or 'none'}.mcap"
    rec = _recorder(path, keep_secrets=True, compression=compression)
    expected: dict[tuple[int, str], bytes] = {}
    for conn in range(1, 5):
        rec.receive(Opened(conn, T0, "a:1", "b:2"))
    for i, (conn, d, data) in enumerate(reads):
        rec.receive(Data(conn, d, T0 + i, data))
        expected[(conn, d.value)] = expected.get((conn, d.value), b"") + data
    rec.stop(T0 + len(reads))
    with open(path, "rb") as f:
        scan = RecordingScan(f)
        got = [(r.conn, r.dir, r.data) for r in tcp_reads(scan)]
    assert got == [(c, d.value, data) for c, d, data in reads]
    assert not scan.truncated
    assert {k: stream_bytes(v) for k, v in rebuild_streams(str(path)).items()} == expected


def test_the_fast_reader_falls_back_for_another_key_order_and_checks_crcs(tmp_path):
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("whiztap.TcpRead", "jsonschema", schema_bytes("whiztap.TcpRead"))
        cid = w.register_channel(TOPIC_READS, "json", sid)
        ours = read_message(1, "c2s", 5, 0, b"abc")
        theirs = {"data": base64.b64encode(b"def").decode(), "size": 3, "offset": 3, "t_ns": 6, "dir": "c2s",
                  "conn": 1}
        w.add_message(cid, 5, json.dumps(ours, separators=(",", ":")).encode(), 5)
        w.add_message(cid, 6, json.dumps(theirs).encode(), 6)
        w.finish()
    assert [s.data for s in rebuild_streams(str(path))[(1, "c2s")]] == [b"abcdef"]
    data = bytearray(path.read_bytes())
    at = data.index(b"zstd") + 20  # inside the compressed chunk
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError):  # zstd error or CRC mismatch, never wrong bytes
        rebuild_streams(str(path))


def test_a_truncated_file_reads_up_to_its_last_complete_chunk(tmp_path):
    path = tmp_path / "cut.mcap"
    rec = _recorder(path, keep_secrets=True)
    rec.receive(Opened(1, T0, "a:1", "b:2"))
    rec.receive(Data(1, C2S, T0 + 1, b"first"))
    rec.file.flush()
    size = rec.file.size
    rec.receive(Data(1, C2S, T0 + 2, b"second"))
    rec.stop(T0 + 3)
    cut = tmp_path / "cut.mcap.part"
    cut.write_bytes(path.read_bytes()[:size + 30])
    with open(cut, "rb") as f:
        scan = RecordingScan(f)
        assert [r.data for r in tcp_reads(scan)] == [b"first"]
    assert scan.truncated
    with pytest.raises(RecordingError, match="not an MCAP file"):
        next(RecordingScan(io.BytesIO(b"nope")).records())


def test_a_reader_takes_the_limit_it_is_given_and_the_setting_only_without_one(tmp_path, monkeypatch):
    path = tmp_path / "limit.mcap"
    rec = _recorder(path, keep_secrets=True, compression="")
    _session(rec)
    rec.stop(T0 + 200)
    monkeypatch.setenv("WHIZTAP_MAX_CHUNK", "lots")  # not read when a limit is passed in
    with open(path, "rb") as f:
        assert list(RecordingScan(f, STREAM_TOPICS, max_chunk=1 << 20).traffic())
    with open(path, "rb") as f, pytest.raises(RecordingError, match="WHIZTAP_MAX_CHUNK: 'lots' is not a size"):
        list(RecordingScan(f, STREAM_TOPICS).traffic())
    with open(path, "rb") as f, pytest.raises(RecordingError, match=r"claims \d+ bytes.*WHIZTAP_MAX_CHUNK=1M lets"):
        list(RecordingScan(f, STREAM_TOPICS, max_chunk=100).traffic())


def test_read_metadata_walks_no_further_than_the_metadata(tmp_path):
    """read_metadata is the scan's walk, ended at the "whiztap" record: a
    damaged chunk after it (which the scan itself refuses) is never looked at."""
    path = tmp_path / "meta.mcap"
    rec = _recorder(path, keep_secrets=True, compression="")
    _session(rec)
    rec.stop(T0 + 200)
    data = bytearray(path.read_bytes())
    data[data.index(base64.b64encode(b"sendchkpass"))] ^= 0x01  # a read's bytes: its chunk's CRC no longer matches
    path.write_bytes(bytes(data))
    assert read_metadata(str(path))["source"] == "test"
    with open(path, "rb") as f, pytest.raises(RecordingError, match="CRC"):
        list(RecordingScan(f, STREAM_TOPICS).traffic())


def test_stream_topics_have_chunks_of_their_own_that_readers_of_streams_alone_decompress(tmp_path, monkeypatch):
    path = tmp_path / "grouped.mcap"
    rec = _recorder(path, compression="")
    t = T0
    for conn in range(1, 4):  # several flushes, so several chunks of each group
        t = _session(rec, conn, t)
        rec.file.flush()
    rec.stop(t + 1)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {cid: c.topic for cid, c in summary.channels.items()}
    in_file_order = sorted(summary.chunk_indexes, key=lambda chunk: chunk.chunk_start_offset)
    groups = [{topics[cid] for cid in chunk.message_index_offsets} for chunk in in_file_order]
    stream_chunks = [g for g in groups if g <= set(STREAM_TOPICS)]
    assert stream_chunks and all(g <= set(STREAM_TOPICS) or not g & set(STREAM_TOPICS) for g in groups)
    assert len(stream_chunks) < len(groups)  # the frames and the rest are elsewhere
    # each flush writes the reads first: a cut loses decoded frames before the reads
    # (the first flush, at the start, has only the start event; the next has both)
    assert [g <= set(STREAM_TOPICS) for g in groups[:3]] == [True, True, False]
    decompressed = []
    real = scan_module.open_chunk
    monkeypatch.setattr(scan_module, "open_chunk",
                        lambda *a: decompressed.append(a) or real(*a))
    with open(path, "rb") as f:
        got = list(tcp_reads(RecordingScan(f, STREAM_TOPICS)))
    assert len(decompressed) == len(stream_chunks)
    assert len(got) == 3 * 12 and {r.conn for r in got} == {1, 2, 3}


# -- the file ------------------------------------------------------------------------------------------


def test_split_by_duration_writes_numbered_files_that_continue_each_other(tmp_path):
    path = tmp_path / "d.mcap"
    rec = _recorder(path, keep_secrets=True, split_duration_ns=1000)
    rec.receive(Opened(1, T0, "a:1", "b:2"))
    sent = b""
    for i in range(10):
        data = b"rr1-%d--0--0-ss1" % i
        rec.receive(Data(1, C2S, T0 + i * 400, data))
        sent += data
        rec.tick(T0 + i * 400)
    summary = rec.stop(T0 + 5000)
    assert [Path(p).name for p in summary.files] == [f"d-{n:04d}.mcap" for n in range(1, len(summary.files) + 1)]
    assert len(summary.files) >= 3
    joined = b""
    for part in summary.files:
        read_all(part)
        for seg in rebuild_streams(part).get((1, "c2s"), []):
            assert seg.offset == len(joined)
            joined += seg.data
        assert read_metadata(part)["part"] == Path(part).stem[-4:].lstrip("0")
    assert joined == sent


def test_a_failing_disk_keeps_what_was_flushed_readable(tmp_path, monkeypatch):
    path = tmp_path / "full.mcap"
    rec = _recorder(path, keep_secrets=True)
    rec.receive(Opened(1, T0, "a:1", "b:2"))
    rec.receive(Data(1, C2S, T0 + 1, b"kept"))
    rec.file.flush()
    real_write = os.write

    def full(fd: int, data: bytes) -> int:
        if fd == rec.file._stream.fd:  # fail only the recording's writes
            real_write(fd, bytes(data)[:10])  # a partial write, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(fd, data)

    monkeypatch.setattr(writer_module.os, "write", full)
    rec.receive(Data(1, C2S, T0 + 2, os.urandom(3000)))
    with pytest.raises(RecordingWriteError, match=r"No space left on device; recording stopped, what was written"):
        rec.file.flush()
    monkeypatch.undo()
    assert path.exists() and not Path(str(path) + ".part").exists()
    with open(path, "rb") as f:
        scan = RecordingScan(f)
        assert [r.data for r in tcp_reads(scan)] == [b"kept"]
    assert not scan.truncated


def test_an_unwritable_path_fails_at_once(tmp_path):
    file = RecordingFile(str(tmp_path / "missing" / "x.mcap"), metadata_record())
    with pytest.raises(RecordingWriteError, match=r"cannot write .*x\.mcap\.part: No such file or directory"):
        file.open(T0)


# -- a second implementation ------------------------------------------------------------------------------


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
@pytest.mark.skipif(not (CHECK / "node_modules" / "@mcap" / "core").is_dir(),
                    reason="@mcap/core is not installed: run 'make test' (it runs npm ci in tests/mcap_check)")
def test_the_typescript_mcap_reader_reads_our_recordings_as_foxglove_would(tmp_path):
    path = tmp_path / "ts.mcap"
    rec = _recorder(path)
    rec.stop(_session(rec))
    result = subprocess.run(["node", str(CHECK / "check.mjs"), str(path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    python_side = read_all(str(path))
    assert report["perTopic"] == {topic: len(python_side.get(topic, [])) for topic in {*TOPICS, *python_side}}
    assert {"/log", "/sensors/0", "/servos/1"} <= set(report["perTopic"])  # a late channel, read by topic
    assert report["indexedCount"] == report["streamCount"] == report["statistics"] > 0
    assert report["backwards"] == 0 and report["done"]
    assert report["metadata"]["format_version"] == FORMAT_VERSION
    for topic, info in report["topics"].items():
        assert (info["schema"], info["schemaEncoding"], info["messageEncoding"]) == (KNOWN_TOPICS[topic],
                                                                                   "jsonschema", "json")


def test_the_format_page_shows_every_topic_and_schema_as_they_are():
    page = (Path(__file__).parent.parent / "docs" / "recording-format.md").read_text()
    assert f'The format version is the string `"{FORMAT_VERSION}"`' in page
    for topic, name in TOPICS.items():
        assert f"| `{topic}` | `{name}` |" in page, topic
    for base, name in PLOT_TOPICS.items():
        assert f"| `{base}/N` | `{name}` |" in page, base
    for name, schema in SCHEMAS.items():
        assert json.dumps(schema, indent=1) in page, name
