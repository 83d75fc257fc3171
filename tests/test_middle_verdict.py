"""One verdict, and both latencies, for traffic the proxy stood in the middle of.

``Judge`` (analyzer/analysis/verdict.py) is fed the traffic events live, as
the real proxy tells its consumers while it records in front of the real
simulator; what it says must be what ``whiztap analyze`` says of the file the
same proxy wrote.  And when the proxy changed the timing, every report names
the server's latency and the client's.
"""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import jsonschema
import pytest

from tests.report_page import page_data
from tests.cli_support import run_cli
from tests.test_analyze_middle import ANSWER_S, NEVER, _record, _sensors
from whiztap.analyzer.analysis.report.schema import REPORT_SCHEMA
from whiztap.analyzer.analysis.verdict import Judge
from whiztap.analyzer.cli.reading import scan_recording
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.protocol.session import Limits
from whiztap.sniffer.sim.client import Client

MS = 1_000_000
DELAY_MS = 300


def _judge(**options: object) -> Judge:
    return Judge(limits=Limits(answer_timeout_ns=int(ANSWER_S * 1e9)), middle=True, **options)


def _analyze(path: Path, *args: str, fmt: str = "json") -> tuple[int, str]:
    result = run_cli("analyze", "--format", fmt, *args, path)
    return result.returncode, result.stdout


# -- one verdict ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_judge_fed_live_says_what_analyze_says_of_the_file(tmp_path):
    """A dropped answer (the client's experience, an error) and an injected
    one (an effect, no side's violation): live, the injection is an effect
    while the connection is still open; at the end the judge and analyze
    agree on every count, with and without --fail-on-interventions."""
    live, strict = _judge(), _judge(fail_on_interventions=True)
    seen: list = []

    async def session(client: Client, rec) -> None:
        await _sensors(client, 1)
        rec.controller.inject(1, "s2c", "cr1-12--5--0-ss1")
        for _ in range(300):
            if live.verdict().effects:
                break
            await asyncio.sleep(0.01)
        seen.append(live.verdict())
        await _sensors(client, 3)

    path = _record(tmp_path / "live.mcap", ("drop dir:s2c kind:response ch:12 nth:2",), session,
                   consumers=(live, strict))
    [during] = seen
    assert (during.passed, during.effects, during.violations) == (True, 1, 0)
    for judge, args in ((live, ()), (strict, ("--fail-on-interventions",))):
        code, output = _analyze(path, "--answer-timeout", str(ANSWER_S), *args)
        report = json.loads(output)
        verdict = judge.finish()
        assert verdict.passed == report["passed"] is False and code == 1
        assert verdict.by_severity == report["summary"]["violations_by_severity"] == {"error": 1, "warning": 0,
                                                                                         "info": 0}
        assert verdict.by_side == {"client": 1, "server": 0}
        assert verdict.by_rule == report["rule_counts"] == {"PW-PAIR-UNANSWERED": 1}
        assert verdict.effects_by_severity == report["interventions"]["effects_by_severity"]
        assert verdict.effects == 1 and verdict.failing == "violations"


def test_a_judge_reading_the_file_agrees_and_effects_alone_fail_only_when_asked(tmp_path):
    async def session(client: Client, rec) -> None:
        await _sensors(client, 1)
        rec.controller.inject(1, "c2s", "sensor 13")
        await client.sensor(12)

    path = _record(tmp_path / "injected.mcap", (NEVER,), session)
    for fail_on, code in ((False, 0), (True, 1)):
        judge = _judge(fail_on_interventions=fail_on)
        for event in scan_recording(path):
            judge.receive(event)
        verdict = judge.finish()
        assert (verdict.passed, verdict.effects, verdict.violations) == (not fail_on, 1, 0)
        assert verdict.failing == ("effects" if fail_on else "")
        got, text = _analyze(path, "--answer-timeout", str(ANSWER_S), *(("--fail-on-interventions",) * fail_on),
                             fmt="text")
        assert got == code
        assert text.splitlines()[-1] == (
            "FAIL: effects of the interventions at or above error, --fail-on-interventions "
            "(0 errors, 0 warnings, 0 info; 1 effect of the interventions)" if fail_on else
            "PASS: no violation at or above error (0 errors, 0 warnings, 0 info; 1 effect of the interventions)")
    judge = _judge(threshold=Severity.ERROR, ignore=frozenset({"PW-PAIR-UNSOLICITED"}), fail_on_interventions=True)
    for event in scan_recording(path):
        judge.receive(event)
    assert judge.finish().passed  # an ignored rule fails nothing, effects included


# -- both latencies -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def slowed(tmp_path_factory) -> dict[str, Path]:
    """The same session with every answer (s2c) or every request (c2s) held
    DELAY_MS by the proxy; the client waits longer than that."""
    folder = tmp_path_factory.mktemp("latency")
    return {d: _record(folder / f"{d}.mcap", (f"delay:{DELAY_MS}ms dir:{d}",),
                       lambda client, rec: _sensors(client, 2), wait=2.0) for d in ("s2c", "c2s")}


def _rows(report: dict, key: str) -> dict[str, dict]:
    return {row["request"]: row for row in report[key]}


@pytest.mark.slow
@pytest.mark.parametrize("direction", ["s2c", "c2s"])
def test_the_json_report_has_the_servers_latency_and_the_clients(slowed, direction):
    code, output = _analyze(slowed[direction])
    report = json.loads(output)
    jsonschema.validate(report, REPORT_SCHEMA)
    assert code == 0
    server, client = _rows(report, "latency"), _rows(report, "client_latency")
    assert set(server) == set(client) == {"Fetch Configuration Settings", "Sensor Request"}
    for title in server:
        assert server[title]["count"] == client[title]["count"]
        assert server[title]["max_ns"] < 100 * MS  # the server answered at once
        assert client[title]["p50_ns"] >= DELAY_MS * MS  # the client waited for the proxy's delay too


@pytest.mark.slow
def test_every_format_names_both_latencies(slowed):
    labels = ("the server's: from the request as it received it to the answer it sent",
              "the client's: from the request as it sent it to the answer as it received it")
    path = slowed["s2c"]
    _, text = _analyze(path, fmt="text")
    for label in labels:
        assert f"Latency by request, {label}" in text
    client_table = text[text.index(labels[1]):]
    assert re.search(r"Sensor Request\s+2\s+3\d\d\.\d\d ms", client_table), client_table
    _, markdown = _analyze(path, fmt="markdown")
    assert all(f"## Latency, {label}" in markdown for label in labels)
    _, html = _analyze(path, fmt="html")
    titles = [s["title"] for s in page_data(html)["sections"]]
    assert all(f"Latency, {label}" in titles for label in labels)
    _, junit = _analyze(path, fmt="junit")
    assert all(f"Latency by request, {label}" in junit for label in labels)
    assert re.search(r"Sensor Request: 2 answers, p50 3\d\d\.\d{3} ms", junit)


def test_the_live_judge_has_both_latencies_too(slowed):
    judge = _judge()
    for event in scan_recording(slowed["c2s"]):
        judge.receive(event)
        server, client = judge.latencies()
    assert server["Sensor Request"].max < 100 * MS and client["Sensor Request"].min >= DELAY_MS * MS
    judge.finish()
    assert judge.latencies()[1]["Sensor Request"].count == 2


def test_without_the_middle_there_is_one_latency_unlabelled():
    _code, output = _analyze(Path(__file__).parent.parent / "samples/vpn.mcap")
    report = json.loads(output)
    assert "client_latency" not in report and report["latency"]
    _, text = _analyze(Path(__file__).parent.parent / "samples/vpn.mcap", fmt="text")
    assert "Latency by request\n" in text and "the client's" not in text


# -- cat: both latencies on each answer's line --------------------------------------------------------------


def _cat(path: Path, *args: str) -> list[str]:
    result = run_cli("cat", *args, path)
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


@pytest.mark.parametrize("direction", ["s2c", "c2s"])
def test_cat_shows_both_latencies_on_each_answer(slowed, direction):
    lines = _cat(slowed[direction])
    answers = [line for line in lines if " s2c response " in line or " s2c config " in line]
    assert len(answers) == 3
    for line in answers:
        found = re.search(r"\[latency: server (\d+\.\d{3}) ms, client (\d+\.\d{3}) ms\]$", line)
        assert found, line
        assert float(found[1]) < 100 and float(found[2]) >= DELAY_MS
    times = [float(line.split()[0]) for line in lines]
    assert times == sorted(times)  # lines that waited for the client's latency kept their place
    rows = [json.loads(line) for line in _cat(slowed[direction], "--format", "jsonl")]
    answered = [r for r in rows if r["kind"] in ("response", "config")]
    assert all(r["server_latency_ns"] < 100 * MS <= DELAY_MS * MS <= r["client_latency_ns"] for r in answered)


@pytest.mark.slow
def test_cat_says_the_client_had_no_answer_where_the_proxy_dropped_it(tmp_path):
    path = _record(tmp_path / "dropped.mcap", ("drop dir:s2c kind:response ch:12 every:2",),
                   lambda client, rec: _sensors(client))
    lines = _cat(path, "--answer-timeout", str(ANSWER_S), "--interventions", "show")
    for n, line in enumerate(lines):
        if " ~ #" in line:  # the answer the proxy dropped is the line before its drop
            assert re.search(r"\[latency: server \d+\.\d{3} ms, client none\]$", lines[n - 1]), lines[n - 1]
    kept = [line for line in lines if " s2c response " in line and "client none" not in line]
    assert len(kept) == 2 and all(re.search(r"client \d+\.\d{3} ms\]$", line) for line in kept)


def test_cat_without_the_middle_shows_no_latency():
    assert not [line for line in _cat(Path(__file__).parent.parent / "samples/vpn.mcap") if "[latency:" in line]


def test_a_connection_is_open_until_its_close_even_before_its_first_delivery():
    """In the middle a read waits for its delivery before a session takes it:
    until then the connection has no session, yet it is open (``/state``'s
    ``open``, the TUI's row), and the verdict's count must not say it closed
    (a view waiting for "no connection open" stopped before the traffic)."""
    from whiztap.analyzer.protocol.observations import Direction
    from whiztap.analyzer.traffic import Closed, Data, Opened
    from whiztap.sniffer.record.summary import verdict_dict

    judge = _judge()
    analyzer = judge.analyzer
    judge.receive(Opened(1, 1))
    judge.receive(Data(1, Direction.C2S, 2, b"rr1-12--0--0-ss1"))  # sent, not delivered yet
    assert not analyzer.sessions and analyzer.open_connections == 1
    assert verdict_dict(judge.verdict(), analyzer.open_connections, 0)["open"] == 1
    judge.receive(Closed(1, 3, "client"))
    assert analyzer.open_connections == 0
