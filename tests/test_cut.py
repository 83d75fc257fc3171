"""``whiztap cut``: a recording cut to some connections is a recording every
reader opens, and tells each kept connection's story as the original did."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.cli_support import run_cli
from tests.record_support import read_all, record_drawn
from tests.test_readers_property import MS, T0, traffic

SAMPLE = Path(__file__).parent.parent / "samples" / "violations.mcap"


def _record(ops: list, path: Path, split_size: int | None = None) -> None:
    """Drawn traffic through the real Recorder, as the proxy drives it."""
    metadata = {"robot": "r1", "session_id": path.stem, "split_size": str(split_size or "")}
    recorder = Recorder(RecordingFile(str(path), metadata, split_size=split_size))
    record_drawn(recorder, ops)


def _analysis(*paths: Path) -> tuple[dict[int, dict], list[dict]]:
    """Each connection's row and every violation of ``analyze --format json``,
    less the file's name and the times counted from the file's first traffic
    (``t_rel_s``), which a cut moves."""
    ran = run_cli("analyze", *map(str, paths), "--format", "json", "--allow-empty")
    assert ran.returncode in (0, 1), ran.stderr
    report = json.loads(ran.stdout)
    rows = {c["conn"]: {k: v for k, v in c.items() if k != "file"} for c in report["connections"]}
    found = [{k: v for k, v in v.items() if k not in ("file", "t_rel_s")} for v in report["violations"]]
    return rows, found


@pytest.mark.slow
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=traffic(any_order=False), wanted=st.sets(st.integers(1, 3), min_size=1), split=st.booleans(),
       words=st.sampled_from(["", "kind:response", "violations", "ch:12", "dir:s2c kind:config", "readytogo"]))
def test_analyze_of_a_cut_is_analyze_of_the_original_restricted_to_its_connections(tmp_path, ops, wanted, split,
                                                                                   words):
    """Restricted: the kept connections' rows (mode, handshake, frames, rules
    broken, channel map, who closed) and their violations, unchanged; kept:
    those of --conn with a line in ``cat --filter WORDS`` (all of them for no words)."""
    original = tmp_path / "in.mcap"
    out = tmp_path / "out.mcap"
    for p in tmp_path.iterdir():
        p.unlink()
    _record(ops, original, split_size=600 if split else None)
    inputs = sorted(tmp_path.glob("in*.mcap"))
    rows, violations = _analysis(*inputs)
    ran = run_cli("cut", *map(str, inputs), "-o", out, "--conn", ",".join(map(str, sorted(wanted))),
                  "--filter", words)
    shown = run_cli("cat", *map(str, inputs), "--format", "jsonl", "--filter", words).stdout.splitlines()
    kept = wanted & ({json.loads(line)["conn"] for line in shown} if words else set(rows))
    if not kept:
        assert ran.returncode == 1 and not out.exists(), ran.stderr
        return
    assert ran.returncode == 0, ran.stderr
    cut_rows, cut_violations = _analysis(out)
    assert cut_rows == {c: row for c, row in rows.items() if c in kept}
    assert cut_violations == [v for v in violations if v["conn"] in kept]
    read_all(str(out))  # the mcap library's reader, CRCs checked, every message fits its schema
    assert run_cli("info", out, "--format", "json").returncode == 0
    assert _tui_items(out) == sum(row["frames"] for row in cut_rows.values())


def _tui_items(path: Path) -> int:
    """The items the TUI's file source shows for a recording."""
    import threading

    from whiztap.analyzer.recording.sets import find_one
    from whiztap.tui.data.model import TrafficModel
    from whiztap.tui.data.sources import FileSource

    model = TrafficModel(str(path))
    source = FileSource(find_one([str(path)]))
    source.feed(model, threading.Event())
    assert not source.note, source.note
    return model.store.count


def test_a_filter_keeps_the_connections_cat_shows_for_it_whole(tmp_path):
    """The filter words are cat's: the connections cut keeps are those with a
    line in ``cat --filter``, and each is kept whole (its handshake and
    configuration exchange come along, though the filter asked for neither)."""
    words = "kind:response ch:3"
    shown = run_cli("cat", SAMPLE, "--format", "jsonl", "--filter", words)
    conns = {json.loads(line)["conn"] for line in shown.stdout.splitlines()}
    assert conns and len(conns) < 38
    out = tmp_path / "out.mcap"
    ran = run_cli("cut", SAMPLE, "-o", out, "--filter", words)
    assert ran.returncode == 0, ran.stderr
    rows, _ = _analysis(out)
    assert set(rows) == conns
    original, _ = _analysis(SAMPLE)
    assert rows == {c: original[c] for c in conns}
    kinds = {json.loads(line)["kind"] for line in run_cli("cat", out, "--format", "jsonl").stdout.splitlines()}
    assert "config" in kinds and "command" in kinds


def test_the_time_window_counts_from_the_first_traffic_or_takes_an_iso_time(tmp_path):
    """``--start 10ms`` and the same moment as an ISO time keep the same connections."""
    from datetime import UTC, datetime

    lines = [json.loads(line) for line in run_cli("cat", SAMPLE, "--format", "jsonl").stdout.splitlines()]
    first = min(line["t_ns"] for line in lines)
    iso = datetime.fromtimestamp((first + 10 * MS) / 1e9, UTC).isoformat()
    later = {line["conn"] for line in lines if line["t_ns"] >= first + 10 * MS}
    assert later and later != {line["conn"] for line in lines}
    for start in ("10ms", iso):
        out = tmp_path / f"out-{len(start)}.mcap"
        ran = run_cli("cut", SAMPLE, "-o", out, "--start", start)
        assert ran.returncode == 0, ran.stderr
        assert set(_analysis(out)[0]) == later


def test_every_message_of_the_cut_is_a_message_of_the_original(tmp_path):
    """Nothing is re-encoded: what was masked stays masked (the secrets
    invariant), and a reader sees the original's bytes."""
    out = tmp_path / "out.mcap"
    assert run_cli("cut", SAMPLE, "-o", out, "--conn", "2,5").returncode == 0
    original = {t: [json.dumps(m, sort_keys=True) for m in ms] for t, ms in read_all(str(SAMPLE)).items()}
    for topic, messages in read_all(str(out)).items():
        for m in messages:
            assert json.dumps(m, sort_keys=True) in original[topic], topic
    assert {m["conn"] for m in read_all(str(out))["/tcp/reads"]} == {2, 5}


@pytest.mark.parametrize(("args", "says"), [
    (("-o", "-"), "not to standard output"),
    (("-o", str(SAMPLE)), "is an input"),
    (("-o", "x.mcap", "--start", "soon"), "--start: wants seconds"),
    (("-o", "x.mcap", "--conn", "two"), "--conn: wants connection numbers"),
    (("-o", "x.mcap", "--filter", "kind:nope"), "--filter: kind:"),
    (("-o", "x.mcap", "--filter", "since:1e300"), "--filter: wants seconds"),
    (("-o", "x.mcap", "--end", "1e300s"), "--end: wants seconds"),
])
def test_bad_arguments_are_one_line_and_status_2(tmp_path, args, says):
    ran = run_cli("cut", SAMPLE, *args, cwd=tmp_path)
    assert ran.returncode == 2 and says in ran.stderr and len(ran.stderr.strip().splitlines()) == 1, ran.stderr
    assert not (tmp_path / "x.mcap").exists()


def test_an_output_that_cannot_be_written_is_one_line_and_leaves_nothing(tmp_path):
    """A folder that is a file: the writer's own error, as one line."""
    (tmp_path / "file").write_bytes(b"")
    ran = run_cli("cut", SAMPLE, "-o", tmp_path / "file" / "out.mcap")
    assert ran.returncode == 2 and "cannot write" in ran.stderr and len(ran.stderr.splitlines()) == 1, ran.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_nothing_matching_writes_nothing_and_exits_1(tmp_path):
    out = tmp_path / "out.mcap"
    ran = run_cli("cut", SAMPLE, "-o", out, "--conn", "99")
    assert ran.returncode == 1 and "nothing" in ran.stderr and not out.exists()
    assert not list(tmp_path.iterdir())


@given(st.text(max_size=30) | st.floats(allow_nan=True).map(str) | st.datetimes().map(lambda d: d.isoformat()))
def test_any_time_given_is_a_bound_or_one_clear_refusal(text):
    """``--start``/``--end`` take text from the user: a bound, or ValueError saying what is wanted."""
    from whiztap.sniffer.record.cut import parse_bound

    try:
        bound = parse_bound(text)
    except ValueError as e:
        assert "wants seconds" in str(e)
    else:
        assert isinstance(bound.at(T0), int)


def test_a_time_with_a_unit_is_seconds_after_the_first_traffic():
    from whiztap.sniffer.record.cut import parse_bound

    assert [parse_bound(t).at(0) for t in ("2.5", "2.5s", "250ms", "1m", "-1s")] == [
        2_500 * MS, 2_500 * MS, 250 * MS, 60_000 * MS, -1_000 * MS]
    assert parse_bound("1970-01-01T00:00:01+00:00").at(T0) == 1_000 * MS


def test_a_log_line_goes_with_its_connection_whatever_its_text_quotes(tmp_path):
    """A /log line's text quotes the peer's bytes: a frame saying ``(conn 1``
    on connection 2 does not make its line connection 1's."""
    original, out = tmp_path / "in.mcap", tmp_path / "out.mcap"
    _record([("opened", 1, "", b""), ("data", 1, "c2s", b"rr1-24--0--0-ss1"), ("closed", 1, "", b""),
             ("opened", 2, "", b""), ("data", 2, "c2s", b"rr1-(conn 1)--0-ss1"), ("closed", 2, "", b"")], original)
    logs = read_all(str(original))["/log"]
    assert any("(conn 1" in m["message"] and m["file"].startswith("conn-2") for m in logs)
    assert run_cli("cut", original, "-o", out, "--conn", "1").returncode == 0
    kept = read_all(str(out)).get("/log", [])
    assert kept == [m for m in logs if m["file"].split()[0] == "conn-1"]


def test_a_cut_of_a_split_recording_is_one_file_never_taken_for_one_of_its_parts(tmp_path):
    """Written beside the parts under a part's name, the cut is its own recording."""
    ops = [("opened", 1, "", b""), *[("data", 1, "c2s", b"rr1-24--0--0-ss1" * 8)] * 40, ("closed", 1, "", b"")]
    _record(ops, tmp_path / "in.mcap", split_size=600)
    parts = sorted(tmp_path.glob("in-*.mcap"))
    assert len(parts) > 1
    before = _analysis(parts[0])
    out = tmp_path / f"in-{len(parts) + 1:04d}.mcap"
    assert run_cli("cut", *parts, "-o", out).returncode == 0
    assert _analysis(parts[0]) == before
    assert _analysis(out) == before


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, SAMPLE.stat().st_size - 1), st.integers(1, 255)),
                      min_size=1, max_size=4), cut_at=st.none() | st.integers(0, SAMPLE.stat().st_size))
def test_a_damaged_recording_is_cut_or_refused_in_one_line(tmp_path, flips, cut_at):
    """Recordings come from outside: bytes changed or the file cut short give
    a cut every reader opens, or one line and status 2, never a traceback."""
    data = bytearray(SAMPLE.read_bytes())
    for at, xor in flips:
        data[at] ^= xor
    damaged, out = tmp_path / "damaged.mcap", tmp_path / "out.mcap"
    out.unlink(missing_ok=True)
    damaged.write_bytes(bytes(data[:cut_at]))
    ran = run_cli("cut", damaged, "-o", out)
    assert ran.returncode in (0, 1, 2), ran.stderr
    if ran.returncode == 0:
        read_all(str(out))
    else:
        assert len(ran.stderr.strip().splitlines()) == 1 and "unexpected error" not in ran.stderr, ran.stderr
        assert not out.exists() and not (tmp_path / "out.mcap.part").exists()
