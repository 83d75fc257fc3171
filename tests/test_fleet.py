"""Fleet reports (docs/fleet.md): ``record --meta``, ``analyze --group-by`` in
every format, merging that is exact, and recordings named by URL.  The runs
on a Dask cluster are tests/test_fleet_dask.py."""

from __future__ import annotations

import io
import json
import pickle
import random
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import jsonschema
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rich.console import Console

from tests.report_page import page_data, sections, table_rows
from tests.cli_support import run_cli
from tests.fleet_support import FLEET, write_fleet
from whiztap.analyzer.analysis.report.text import render_text
from whiztap.analyzer.analysis.report.words import group_name, rule_counts_each, rules_since_each
from whiztap.analyzer.cli.analyze import UNWRAPPED
from whiztap.analyzer.analysis.merge import DuplicateResult, Merger
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.report.schema import REPORT_SCHEMA
from whiztap.analyzer.cli.analyze import analyse_file
from whiztap.analyzer.protocol import session as session_module
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.recording.scan import read_metadata

def report(*args: object) -> dict:
    done = run_cli("analyze", "--format", "json", *args)
    assert done.returncode in (0, 1), done.stderr
    data = json.loads(done.stdout)
    jsonschema.validate(data, REPORT_SCHEMA)
    return data


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return write_fleet(tmp_path_factory.mktemp("fleet"))


# -- record --meta ---------------------------------------------------------------------------------


@pytest.mark.parametrize("meta, why", [
    ("robot", "expected KEY=VALUE"),
    ("middle=yes", "a key whiztap writes itself"),
    ("9lives=1", "is not a key"),
    ("ro bot=1", "is not a key"),
])
def test_record_refuses_a_meta_it_cannot_write(tmp_path: Path, meta: str, why: str) -> None:
    done = run_cli("record", "--upstream", "127.0.0.1:1", "--listen", "127.0.0.1:0", "-o", tmp_path / "x.mcap",
               "--meta", meta)
    assert done.returncode == 2 and why in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    assert not list(tmp_path.iterdir())


def test_record_refuses_a_key_given_twice(tmp_path: Path) -> None:
    done = run_cli("record", "--upstream", "127.0.0.1:1", "-o", tmp_path / "x.mcap", "--meta", "robot=a",
               "--meta", "robot=b")
    assert done.returncode == 2 and "given twice" in done.stderr


def test_the_fleet_recordings_carry_their_keys(fleet: list[Path]) -> None:
    meta = read_metadata(fleet[0])
    assert (meta["robot"], meta["firmware"], meta["start_time"]) == ("r1", "1.0", "2026-03-01T09:00:00+00:00")
    assert "robot" not in read_metadata(fleet[-1])


# -- the fleet tables --------------------------------------------------------------------------------


def _groups(data: dict, index: int = 0) -> dict[str, dict]:
    table = data["fleet"][index]
    return {" / ".join(str(v) for v in g["group"].values()): g for g in table["groups"]}


def test_a_fleet_table_groups_by_robot_and_by_day(fleet: list[Path]) -> None:
    data = report(*fleet, "--group-by", "robot")
    [table] = data["fleet"]
    assert table["group_by"] == ["robot"] and table["day_of"] == "start_time"
    groups = _groups(data)
    assert list(groups) == ["r1", "r2", "r3", "None"]  # a recording without the key last
    r1, _r2, r3, bare = groups.values()
    assert [g["recordings"] for g in groups.values()] == [2, 2, 1, 1]
    assert [d["day"] for d in r1["days"]] == ["2026-03-01", "2026-03-02"]
    assert r1["days"][0]["violations"] == 0 and r1["days"][1]["violations"] == r1["violations"] > 0
    assert not r1["passed"] and bare["passed"] and bare["rules"] == []
    assert {r["since"] for r in r1["rules"]} == {"2026-03-02"} and {r["since"] for r in r3["rules"]} == {"2026-03-03"}
    # the groups add up to the whole report, rule by rule
    totals: dict[str, int] = {}
    for g in groups.values():
        for r in g["rules"]:
            totals[r["rule_id"]] = totals.get(r["rule_id"], 0) + r["count"]
    assert totals == data["rule_counts"]
    assert sum(g["frames"] for g in groups.values()) == data["summary"]["frames"]


def test_the_middle_recording_is_judged_as_analyze_judges_it_alone(fleet: list[Path]) -> None:
    """r2's second day was recorded with the proxy in the middle: each side
    judged by what it did, in the fleet table as in its own report."""
    middle = fleet[3]
    alone = build(analyse_file(middle, "dev-sum"))
    assert any("the proxy stood in the middle" in n for c in alone["connections"] for n in c["notes"])
    data = report(*fleet, "--group-by", "robot")
    [day2] = [d for d in _groups(data)["r2"]["days"] if d["day"] == "2026-03-02"]
    assert day2["rule_counts"] == alone["rule_counts"] and day2["violations"] > 0


@pytest.mark.slow
def test_group_by_several_keys_together(fleet: list[Path]) -> None:
    data = report(*fleet, "--group-by", "firmware,robot", "--group-by", "firmware")
    assert list(_groups(data, 0)) == ["1.0 / r1", "1.1 / r2", "1.1 / r3", "None / None"]
    assert {k: g["recordings"] for k, g in _groups(data, 1).items()} == {"1.0": 2, "1.1": 3, "None": 1}


def test_a_key_no_recording_carries_is_said(fleet: list[Path]) -> None:
    done = run_cli("analyze", *fleet, "--group-by", "site", "--format", "json")
    assert done.returncode == 1 and "no recording carries the metadata key site" in done.stderr
    assert [g["group"] for g in json.loads(done.stdout)["fleet"][0]["groups"]] == [{"site": None}]


def test_ignore_and_threshold_apply_to_the_groups(fleet: list[Path]) -> None:
    data = report(*fleet[2:4], "--group-by", "robot", "--ignore", "PW-PAIR-UNANSWERED",
                  "--ignore", "PW-PAIR-UNSOLICITED")
    [r2] = data["fleet"][0]["groups"]
    assert r2["violations"] == 0 and r2["passed"]


@pytest.mark.parametrize("value", ["", "robot,,firmware", "robot,robot", "ro bot"])
def test_a_group_by_that_is_no_key_is_refused(fleet: list[Path], value: str) -> None:
    done = run_cli("analyze", fleet[0], "--group-by", value)
    assert done.returncode == 2 and "--group-by" in done.stderr and len(done.stderr.splitlines()) == 1


@pytest.mark.slow
def test_the_fleet_table_is_in_every_format(fleet: list[Path], tmp_path: Path) -> None:
    args = [*fleet, "--group-by", "robot", "-o"]
    text = tmp_path / "r.txt"
    run_cli("analyze", *args, text)
    assert "Fleet by robot" in text.read_text() and "PW-PAIR-UNANSWERED 7 since 2026-03-02" in text.read_text()
    md = tmp_path / "r.md"
    run_cli("analyze", *args, md, "--format", "markdown")
    lines = md.read_text().splitlines()
    assert "## Fleet by robot" in lines and "| r2 | 2026-03-02 | 1 | 1 | PW-PAIR-UNANSWERED 1 |" in lines
    junit = tmp_path / "r.xml"
    run_cli("analyze", *args, junit, "--format", "junit")
    suites = ET.parse(junit).getroot()
    [suite] = [s for s in suites if s.get("name") == "whiztap fleet by robot"]
    cases = {c.get("name"): c for c in suite}
    assert list(cases) == ["robot r1", "robot r2", "robot r3", "robot (none)"]
    assert [c.find("failure") is not None for c in cases.values()] == [True, True, True, False]
    assert int(suites.get("tests")) == sum(int(s.get("tests")) for s in suites)
    html = tmp_path / "r.html"
    run_cli("analyze", *args, html, "--format", "html")
    found = sections(page_data(html.read_text()))
    assert found["fleet0"]["title"] == "Fleet by robot"
    assert found["fleet0-days"]["title"] == "Violations by robot and day (UTC; the day each recording began)"
    groups = table_rows(found["fleet0"])
    assert [g["robot"] for g in groups] == ["r1", "r2", "r3", "(none)"]
    assert groups[0]["rules broken (count, since)"].startswith(
        "PW-FRAME-GARBAGE 2 since 2026-03-02; PW-FRAME-TRUNCATED 1 since 2026-03-02")
    assert [found[f"fleet0-{i}"]["title"] for i in range(4)] == ["robot r1", "robot r2", "robot r3", "robot (none)"]


def _fleet_lines(data: dict, width: int) -> list[str]:
    """The text report's fleet tables as a terminal ``width`` wide shows them."""
    console = Console(width=width, record=True, file=io.StringIO(), force_terminal=False)
    render_text(data, console)
    lines = console.export_text().splitlines()
    return lines[lines.index(next(line for line in lines if line.startswith("Fleet by"))):
                 lines.index(next(line for line in lines if line.startswith("Connections")))]


@pytest.mark.slow
@pytest.mark.parametrize("width", [80, 120, UNWRAPPED])
def test_long_fleet_cells_wrap_between_rules_never_inside_one(fleet: list[Path], width: int) -> None:
    """A group that broke 38 rules had them in one cell: folded inside rule
    ids on a terminal (PW-FRAME-GARB / AGE), a row 2,000 characters wide
    (every other row padded to it) in a file."""
    data = report(*fleet, "--group-by", "robot,firmware")
    lines = _fleet_lines(data, width)
    table = data["fleet"][0]
    for g in table["groups"]:
        assert any(line.startswith(group_name(table, g) + " ") for line in lines)
        for entry in rules_since_each(g) + [e for d in g["days"] for e in rule_counts_each(d["rule_counts"])]:
            assert any(entry in line.split("  ") or line.rstrip().endswith(" " + entry) for line in lines), entry
    assert max(len(line.rstrip()) for line in lines) <= min(width, 160)


# -- merging is exact --------------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.integers(0, 10**12), max_size=60), min_size=1, max_size=6))
def test_latency_stats_merge_exactly(parts: list[list[int]]) -> None:
    """Merged from histograms, the statistics are those of every latency in one stream."""
    whole = LatencyStats()
    whole.add_many([ns for part in parts for ns in part])
    merged = LatencyStats()
    for part in parts:
        one = LatencyStats()
        for ns in part:
            one.add(ns)
        merged.merge(pickle.loads(pickle.dumps(one)))  # as it comes back from a worker
    assert (merged.count, merged.total, merged.min, merged.max) == (whole.count, whole.total, whole.min, whole.max)
    assert merged.histogram() == whole.histogram()
    assert [merged.percentile(p) for p in (1, 50, 95, 99, 100)] == [whole.percentile(p) for p in (1, 50, 95, 99, 100)]


def test_merged_percentiles_are_those_of_every_latency(fleet: list[Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """Each file analysed on its own, then merged: the report's latency rows
    equal those of one LatencyStats fed every latency of every file (not an
    average of the files' percentiles)."""
    raw: dict[str, list[int]] = {}

    class Logged(dict):
        def __missing__(self, title: str) -> LatencyStats:
            stats = self[title] = _LoggingStats(raw.setdefault(title, []))
            return stats

    original = session_module.Session.__init__

    def init(self, *args, **kwargs) -> None:
        original(self, *args, **kwargs)
        self.latencies = Logged()

    monkeypatch.setattr(session_module.Session, "__init__", init)
    plain = [p for p, (*_, middle) in zip(fleet, FLEET) if not middle]  # one session per connection
    merger = Merger([str(p) for p in plain])
    for i, path in enumerate(plain):
        merger.add(i, analyse_file(path, "dev-sum"))
    merged, _ = merger.finish()
    rows = build(merged)["latency"]
    assert {r["request"] for r in rows} == set(raw) and len(rows) >= 3
    for row in rows:
        whole = LatencyStats()
        whole.add_many(raw[row["request"]])
        assert (row["count"], row["p50_ns"], row["p95_ns"], row["p99_ns"], row["max_ns"]) == (
            whole.count, whole.percentile(50), whole.percentile(95), whole.percentile(99), whole.max)
        assert row["mean_ns"] == round(whole.mean)


class _LoggingStats(LatencyStats):
    """LatencyStats that also keep every latency they were given (the test's reference)."""

    __slots__ = ("log",)

    def __init__(self, log: list[int]) -> None:
        super().__init__()
        self.log = log

    def add_many(self, latencies: list[int]) -> None:
        self.log.extend(latencies)
        super().add_many(latencies)


def test_results_merge_the_same_in_any_order(fleet: list[Path]) -> None:
    """Results come back from workers in any order; the report is the one of input order."""
    names = [str(p) for p in fleet]
    results = [pickle.dumps(analyse_file(p, "dev-sum")) for p in fleet]
    results[4] = pickle.dumps("r3-d3.mcap: cannot read (pretend)")  # an unreadable one keeps its place too
    expected = None
    for seed in range(4):
        order = list(range(len(fleet)))
        random.Random(seed).shuffle(order)
        merger = Merger(names)
        for i in order:
            merger.add(i, pickle.loads(results[i]))
        merged, unreadable = merger.finish()
        got = json.dumps(build(merged, unreadable=unreadable, group_by=[("robot",)]))
        assert expected is None or got == expected
        expected = got
        with pytest.raises(DuplicateResult):
            merger.add(order[0], pickle.loads(results[order[0]]))


def test_a_result_missing_is_never_a_report(fleet: list[Path]) -> None:
    merger = Merger(["a", "b"])
    merger.add(1, analyse_file(fleet[0], "dev-sum"))
    with pytest.raises(RuntimeError, match="no result for a"):
        merger.finish()


# -- recordings named by URL -----------------------------------------------------------------------------


@pytest.mark.slow
def test_file_urls_read_as_the_files_do(fleet: list[Path]) -> None:
    folder = fleet[0].parent
    by_path = report(*fleet, "--group-by", "robot")
    by_url = report(f"file://{folder}", "--group-by", "robot")
    by_glob = report(f"file://{folder}/r*.mcap", "--group-by", "robot")
    assert by_url["files"] == sorted(f"file://{p}" for p in fleet)
    normal = json.loads(json.dumps(by_url).replace(f"file://{folder}/", f"{folder}/"))
    assert normal["rule_counts"] == by_path["rule_counts"] and normal["latency"] == by_path["latency"]
    assert normal["fleet"] == by_path["fleet"]
    assert len(by_glob["files"]) == 5 and all(f.startswith(f"file://{folder}/r") for f in by_glob["files"])


@pytest.mark.parametrize("url, why", [
    ("file:///nowhere/at/all.mcap", "no such file"),
    ("nosuchscheme://bucket/x.mcap", "nosuchscheme"),
    ("s3://bucket/x.mcap", "s3fs"),
])
def test_a_url_that_names_nothing_readable_is_one_line(url: str, why: str) -> None:
    done = run_cli("analyze", url)
    assert done.returncode == 2 and why in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr


def test_the_progress_bar_counts_a_url_read_in_this_process(fleet: list[Path],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """One process, a bar on a terminal: each part is read through the bar,
    a URL's as a file's."""
    from whiztap.analyzer.cli import analyze as analyze_cli
    from whiztap.analyzer.cli.progress import ByteProgress
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.recording.sets import find_recordings

    monkeypatch.setattr(ByteProgress, "THRESHOLD", 0)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    found = find_recordings([f"file://{fleet[0].parent}"], urls=True)
    parts = [p for r in found for p in r.parts]
    with ByteProgress(parts, enabled=True) as progress:
        analysis, unreadable = analyze_cli._analyse_all(found, "dev-sum", Limits(), 1, progress)
        done = progress.bar.tasks[0].completed
    assert unreadable == [] and len(analysis.files) == len(fleet)
    assert done == sum(p.stat().st_size for p in fleet)


def test_a_split_recording_named_by_url_is_one_recording(tmp_path: Path) -> None:
    """Its parts found beside the one named, grouped by their metadata, judged as one session."""
    from tests.test_split_recordings import split_vpn_session

    files = split_vpn_session(tmp_path / "s.mcap")
    for name in (f"file://{files[1]}", f"file://{tmp_path}", f"file://{tmp_path}/s-*.mcap"):
        data = report(name)
        assert data["files"] == [f"file://{files[0]}"] and data["rule_counts"] == {}, name
        assert len(data["connections"]) == 1
        assert {r["request"]: r["count"] for r in data["latency"]}["Sensor Request"] == 2
