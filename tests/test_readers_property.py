"""Every reader of a recording survives any traffic, and they all agree.

Hypothesis makes traffic the way a hostile or broken peer would: protocol
fragments and random bytes in both directions, cut anywhere into reads, with
opens, half-closes, gaps and closes in any order.  It is written two ways: by
the real ``Recorder`` (the proxy's order of events, with and without password
redaction), and by a writer that puts messages in the file in any order at all
(another tool, an older whiztap).  Then every reader runs over the file: the
report (``analyze``), ``cat``'s item stream, the TUI's frame store, replay
planning and ``info``.  None may raise, and the totals they show must agree.

Rendering the report as text, Markdown, JUnit and HTML is not what these
properties check (it made each example cost a second, matplotlib's plots
above all): each format is rendered once, below, on a recording holding every
hostile piece the strategies draw from.
"""

from __future__ import annotations

import json
import threading
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.encode import encode, encode_read
from whiztap.analyzer.recording.format import TOPIC_EVENTS, TOPIC_READS
from whiztap.analyzer.recording.info import set_info
from whiztap.analyzer.recording.scan import RecordingError
from whiztap.analyzer.recording.sets import find_one
from whiztap.analyzer.traffic import Closed, Gap, HalfClosed, Opened, to_json
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.replay.plan import Selection, dry_run_lines, plan
from whiztap.tui.data.model import TrafficModel
from whiztap.tui.data.sources import FileSource

from tests.cli_support import Ran, run_cli
from tests.record_support import DRAWN_STEP, DRAWN_T0, record_drawn

# Pieces that reach the interesting states of the session model: frames of
# every kind (valid and not), handshake words, line breaks, image markers.
TOKENS = [
    b"rr1-24--0--0-ss1", b"rr1-29--0--0-ss1", b"rr1-12--0--0-ss1", b"rr1-3--0--2-ss1",
    b"rr1-2--1--0-ss1", b"rr1-0--0--120-ss1", b"rr1-99--0--0-ss1", b"rr1-1--x--0-ss1",
    b"cr1-12--100--0-ss1", b"cr1-3--7000--0-ss1", b"cr1-12--9999--0-ss1", b"cr1--ss1",
    b"cr1-5-ss1", b"cr1-\x01\x02--0--0-ss1", b"rr1-", b"cr1-", b"-ss1", b"--",
    b"sr1-\x02000200-ss1", b"sr1-\x18" + b"200" * 24 + b"-ss1",
    b"sr1-25--\x0c\x00\x00\x0c\x01\x02\x18--0-ss1", b"sr1-25--\x0c\x00\x00\x07--0-ss1",
    b"sendchkpass", b"readytogo", b"Failed Validation", b"progwhiz", b"secret",
    b"\r\n", b"\n", b"\r", b" ",
    b"\xff\xd8\xff\xe0\x00\x04ab\xff\xd9", b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n",
]
token = st.one_of(st.sampled_from(TOKENS), st.binary(min_size=1, max_size=12))
stream = st.lists(token, max_size=12).map(b"".join)

T0, MS = DRAWN_T0, DRAWN_STEP  # record_drawn's clock, for the tests that write events by hand


@st.composite
def traffic(draw, any_order: bool):
    """A list of (op, conn, direction, payload) over one to three connections."""
    conns = draw(st.integers(1, 3))
    ops: list[tuple[str, int, str, bytes | int]] = []
    for conn in range(1, conns + 1):
        mine: list[tuple[str, int, str, bytes | int]] = []
        for d in ("c2s", "s2c"):
            data = draw(stream)
            cuts = sorted(draw(st.lists(st.integers(0, max(len(data), 1)), max_size=6)))
            pieces = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)]) if b > a]
            mine += [("data", conn, d, p) for p in pieces]
            if draw(st.booleans()):
                mine.append(("half", conn, d, b""))
        if draw(st.booleans()):
            mine.append(("gap", conn, draw(st.sampled_from(["c2s", "s2c"])), draw(st.integers(1, 50))))
        # Interleave the two directions (and the gap) in any order, keeping each
        # direction's own reads in order.
        order = draw(st.permutations(range(len(mine))))
        by_dir: dict[str, list] = {"c2s": [], "s2c": []}
        for op in mine:
            by_dir[op[2]].append(op)
        picks = [mine[i][2] for i in order]
        body = [by_dir[d].pop(0) for d in picks]
        lifecycle = [("opened", conn, "", b""), *body, ("closed", conn, "", b"")]
        if draw(st.booleans()):
            lifecycle.pop()  # still open when the recording stops
        ops.append(lifecycle)
    # Connections interleave too.
    merged: list = []
    queues = [list(q) for q in ops]
    while any(queues):
        live = [q for q in queues if q]
        merged.append(live[draw(st.integers(0, len(live) - 1))].pop(0))
    if any_order:
        merged = draw(st.permutations(merged))
    return merged


def _record(ops, path: Path, keep_secrets: bool, split_size: int | None) -> None:
    """Through the real Recorder, as the proxy drives it."""
    metadata = {"session_id": path.stem, "split_size": str(split_size)} if split_size else {}
    file = RecordingFile(str(path), metadata, split_size=split_size)
    recorder = Recorder(file, keep_secrets=keep_secrets)
    record_drawn(recorder, ops)


def _write_any_order(ops, path: Path) -> None:
    """Messages as another writer might leave them: any order, any repetition."""
    file = RecordingFile(str(path), {})
    file.open(T0)
    t = T0
    offsets: Counter = Counter()
    for op, conn, d, payload in ops:
        t += MS
        if op == "data":
            file.write(TOPIC_READS, t, encode_read(conn, d, t, offsets[conn, d], payload))
            offsets[conn, d] += len(payload)
            continue
        if op == "opened":
            event = Opened(conn, t, client="c", upstream="u")
        elif op == "half":
            event = HalfClosed(conn, t, Direction(d))
        elif op == "gap":
            event = Gap(conn, t, Direction(d), offset=offsets[conn, d], length=payload)
        else:
            event = Closed(conn, t, by="client")
        file.write(TOPIC_EVENTS, t, encode(to_json(event)))
    file.finish()


def _parts(path: Path) -> list[Path]:
    found = sorted(path.parent.glob(path.stem + "*.mcap"))
    assert found, "the recording left no file"
    return found


def _run(*args: str) -> Ran:
    """A command in this process; it may fail a gate (exit 1), never crash."""
    result = run_cli(*args)
    assert result.returncode in (0, 1), result.stderr
    return result


def _read_everything(path: Path) -> dict:
    """Every reader over one file; their totals must agree."""
    report = _run("analyze", str(path), "--format", "json", "--severity-threshold", "info")
    facts = json.loads(report.stdout)
    catted = _run("cat", str(path), "--format", "jsonl")
    lines = [json.loads(line) for line in catted.stdout.splitlines()]
    items = [line for line in lines if line["kind"] != "late_violation"]
    cat_violations = Counter(rule for line in lines for rule in line["violations"])

    model = TrafficModel(str(path))
    source = FileSource(find_one([str(path)]))
    source.feed(model, threading.Event())
    assert not source.note, source.note
    store = model.store

    assert facts["summary"]["frames"] == len(items) == store.count
    assert Counter(facts["rule_counts"]) == cat_violations

    sessions = load_exchanges(find_one([str(path)]))
    for segments in (False, True):
        plans = plan(sessions, Selection(), segments)
        dry_run_lines(plans, sessions.start_ns)
    set_info(list(find_one([str(path)]).parts))
    return facts


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["text", "markdown", "junit", "html"])
def test_every_report_format_renders_hostile_traffic(tmp_path, fmt):
    """Every token the strategies use, in both directions of two connections, one
    of them still open; the report in each format is written without a crash."""
    ops: list = [("opened", 1, "", b""), ("opened", 2, "", b"")]
    for conn in (1, 2):
        ops += [("data", conn, d, piece) for piece in TOKENS for d in ("c2s", "s2c")]
    ops += [("gap", 1, "s2c", 7), ("half", 2, "c2s", b""), ("closed", 1, "", b"")]
    path = tmp_path / "r.mcap"
    _record(ops, path, keep_secrets=False, split_size=None)
    out = tmp_path / f"report.{fmt}"
    _run("analyze", str(path), "--format", fmt, "-o", str(out))
    assert out.stat().st_size > 0


settings_ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                           HealthCheck.function_scoped_fixture])


@pytest.mark.slow
@settings_
@given(ops=traffic(any_order=False), keep_secrets=st.booleans())
def test_recorded_traffic_reads_the_same_everywhere(tmp_path_factory, ops, keep_secrets):
    path = tmp_path_factory.mktemp("rec") / "r.mcap"
    _record(ops, path, keep_secrets, None)
    _read_everything(path)


@pytest.mark.slow
@settings_
@given(ops=traffic(any_order=False), keep_secrets=st.booleans(), split_size=st.sampled_from([1, 600, 3000]))
def test_a_recording_split_anywhere_reads_as_the_whole(tmp_path_factory, ops, keep_secrets, split_size):
    """Parts split at any point read as one recording: the same report as unsplit."""
    whole, parts = tmp_path_factory.mktemp("whole") / "r.mcap", tmp_path_factory.mktemp("parts") / "r.mcap"
    _record(ops, whole, keep_secrets, None)
    _record(ops, parts, keep_secrets, split_size)
    one, split = _read_everything(whole), _read_everything(Path(f"{parts.parent}/r-0001.mcap"))
    assert split["summary"]["frames"] == one["summary"]["frames"]
    assert split["rule_counts"] == one["rule_counts"]
    assert len(split["connections"]) == len(one["connections"])


@pytest.mark.slow
@settings_
@given(ops=traffic(any_order=True))
def test_a_file_in_any_order_reads_the_same_everywhere(tmp_path_factory, ops):
    path = tmp_path_factory.mktemp("any") / "r.mcap"
    _write_any_order(ops, path)
    try:
        _read_everything(path)
    except RecordingError:
        pass  # a reader may refuse such a file, with one line; it may not crash
