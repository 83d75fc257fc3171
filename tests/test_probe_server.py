"""``whiztap probe server``: the catalogue against the real simulator over real sockets.

The clean simulator passes every case in both modes; every planted server bug
(``sniffer/sim/bugs.py``) fails at least one case with the rule the bug says
catches it; the command's exit statuses, ``--cases``, ``--list``, ``--record``
(a normal recording, a connection per case) and every report format; no
output shows the password; and the judging takes any bytes a server sends.
"""

from __future__ import annotations

import asyncio
import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from whiztap.analyzer.probe.judging import PROBE_RULES, Trace, judge
from whiztap.analyzer.probe.model import CaseResult, Outcome, ProbeReport
from whiztap.analyzer.analysis.frame_context import read_frames
from whiztap.analyzer.probe.report import FORMATS, render
from whiztap.analyzer.probe.server_cases import catalogue, select
from whiztap.analyzer.probe.server_plan import Mode, Target
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.rules import RULES
from whiztap.sniffer.probe.server_run import ProbeSettings, probe_server
from whiztap.sniffer.sim.bugs import BUGS
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, parse_channels
from whiztap.sniffer.sim.simulator import Simulator

from tests.report_page import page_data, sections
from tests.cli_support import run_cli
from tests.outputs import SECRET, assert_no_leak, topics_text

PASSWORD = b"progwhiz"
QUICK_WAIT = 0.3  # each wait of a case against a server that may never answer (the bugs)
DOCS = Path(__file__).resolve().parent.parent / "docs" / "probe.md"
# What catches a bug whose CAUGHT_BY is no rule id: its first word, as the probe names it.
PROBE_CATCHES = {"crash": "PROBE-DOWN", "answers": "PROBE-ORDER", "Failed": "PROBE-WRONG-VERDICT"}


async def _probe(sim: Simulator, patterns: tuple[str, ...] = (), **options) -> ProbeReport:
    password = sim.password if sim.mode == "winsock" else None
    return await probe_server(ProbeSettings("127.0.0.1", sim.port, password, **options), select(catalogue(), patterns))


async def _cli(*args: str, env: dict[str, str] | None = None):
    return await asyncio.to_thread(run_cli, "probe", "server", *args, env=env)


# -- the simulator, clean and with its planted bugs ------------------------------------------------------


@pytest.mark.parametrize("mode", ["winsock", "vpn"])
async def test_the_clean_simulator_passes_every_case(mode):
    async with Simulator(mode=mode) as sim:
        report = await _probe(sim)
    assert report.mode == mode
    assert [c.id for c in report.cases] == [c.id for c in catalogue()]
    failed = {c.id: c.findings for c in report.cases if c.verdict is Outcome.FAIL}
    assert not failed
    assert report.passed > 60
    for case in report.cases:  # a skip always says why, and only for a case the mode or the spec leaves out
        assert (case.verdict is Outcome.SKIP) == bool(case.reason), case


def _rule_for(caught_by: str) -> str:
    first = caught_by.split()[0]
    return first if first.startswith("PW-") else PROBE_CATCHES[first]


@pytest.mark.slow
@pytest.mark.parametrize("bug", sorted(BUGS))
async def test_every_planted_bug_is_caught_with_its_rule(bug):
    mode = BUGS[bug].needs or "winsock"
    async with Simulator(mode=mode, bugs=(bug,)) as sim:
        report = await _probe(sim, wait_s=QUICK_WAIT)
    rules = {f.rule for c in report.cases if c.verdict is Outcome.FAIL for f in c.findings}
    assert report.exit_status == 1
    assert _rule_for(BUGS[bug].caught_by) in rules, (bug, rules)


async def test_a_crash_fails_the_case_that_caused_it_and_skips_the_rest():
    async with Simulator(bugs=("crash-on-frame",)) as sim:
        report = await _probe(sim, ("malformed.width.*", "answer.sensor-request"), wait_s=QUICK_WAIT)
    verdicts = {c.id: c for c in report.cases}
    crashed = verdicts["malformed.width.data2.3-digits"]
    assert crashed.verdict is Outcome.FAIL and "PROBE-DOWN" in {f.rule for f in crashed.findings}
    after = report.cases[report.cases.index(crashed) + 1:]
    assert after and all(c.verdict is Outcome.SKIP and c.reason.startswith("not run:") for c in after)
    assert all(c.verdict is Outcome.PASS for c in report.cases[:report.cases.index(crashed)])


# -- the command ---------------------------------------------------------------------------------------


async def test_exit_status_0_when_every_case_passed_1_when_one_failed():
    async with Simulator() as clean, Simulator(bugs=("out-of-range",)) as buggy:
        passed = await _cli(f"127.0.0.1:{clean.port}", "-p", "progwhiz", "--cases", "answer.*")
        failed = await _cli(f"127.0.0.1:{buggy.port}", "-p", "progwhiz", "--cases", "answer.sensor-request")
    assert passed.returncode == 0, passed.stderr
    assert "PASS: 12 passed, 0 failed, 0 skipped of 12 cases" in passed.stdout
    assert failed.returncode == 1, failed.stderr
    assert "PW-RANGE-SENSOR" in failed.stdout and "FAIL" in failed.stdout


@pytest.mark.parametrize(("args", "words"), [
    (("127.0.0.1:1",), "cannot connect to 127.0.0.1:1"),
    (("127.0.0.1:1", "--cases", "no-such-*"), "matches no case"),
    ((), "give the server's address"),
    (("--list", "--format", "junit"), "--list prints"),
])
async def test_a_run_that_cannot_happen_is_one_line_and_exit_status_2(args, words):
    done = await _cli(*args)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and words in done.stderr and "Traceback" not in done.stderr


async def test_a_winsock_server_without_a_password_or_with_a_wrong_one_is_exit_status_2():
    async with Simulator() as sim:
        bare = await _cli(f"127.0.0.1:{sim.port}")
        wrong = await _cli(f"127.0.0.1:{sim.port}", "-p", "nope")
    assert bare.returncode == wrong.returncode == 2
    assert "give it with --password" in bare.stderr and "refused the password" in wrong.stderr
    assert bare.stderr.count("\n") == wrong.stderr.count("\n") == 1


def test_cases_takes_globs_and_list_prints_the_catalogue_without_a_server():
    done = run_cli("probe", "server", "--list", "--format", "json", "--cases", "split.*", "--cases", "handshake.vpn")
    assert done.returncode == 0, done.stderr
    ids = [c["id"] for c in json.loads(done.stdout)]
    assert ids == [c.id for c in catalogue() if c.id.startswith("split.") or c.id == "handshake.vpn"]
    assert "split.every-field" in ids and "handshake.vpn" in ids


def test_the_catalogue_in_the_docs_is_the_one_the_code_lists():
    listed = run_cli("probe", "server", "--list", "--format", "markdown").stdout
    text = DOCS.read_text()
    start = text.index("| case | spec section |")
    assert text[start:start + len(listed)] == listed, "paste `whiztap probe server --list --format markdown` there"


def test_case_ids_are_unique_and_one_past_a_range_is_out_of_it():
    ids = [c.id for c in catalogue()]
    assert len(ids) == len(set(ids))
    target = Target(Mode.VPN, b"", parse_channels(DEFAULT_CHANNELS))
    sent = {c.id: c.plan(target) for c in catalogue()}
    # channel 24 is Fetch Configuration's code, so one past the channels is 25 (a Servo Position Request can be 24)
    assert b"rr1-25--0--0-ss1" in [s.data for s in sent["range.sensor-request.channel.above"] if hasattr(s, "data")]
    assert b"rr1-24--0--2-ss1" in [s.data for s in sent["range.servo-position-request.channel.above"]
                                   if hasattr(s, "data")]
    assert b"rr1-0--0--268-ss1" in [s.data for s in sent["range.internal-script.above"] if hasattr(s, "data")]


# -- --record ------------------------------------------------------------------------------------------


async def test_record_writes_one_recording_a_connection_per_case_that_analyze_reads(tmp_path):
    async with Simulator() as sim:
        report = await _probe(sim, ("split.*", "answer.sensor-request", "many.connections"),
                              record_dir=str(tmp_path / "run"))
    path = tmp_path / "run" / "probe-server.mcap"
    assert report.recording == str(path) and path.exists()
    frames = read_frames(str(path))
    conns = [c.conn for c in report.cases]
    assert conns == sorted(conns) and len(set(conns)) == len(conns) and 1 not in conns  # 1: the discovery
    assert len(frames) == 1 + len(report.cases) - 1 + 16  # the discovery, a connection each, many's 16
    meanings = {c.id: [f.meaning for f in frames[c.conn] if f.direction == "c2s"] for c in report.cases}
    assert "Sensor Request ch 12" in meanings["split.bytes"]  # each case's own frames on its connection
    assert any(what.startswith("Set Configuration") for what in meanings["split.set-configuration"])
    assert not any(what.startswith("Set Configuration") for what in meanings["split.bytes"])
    analyzed = await asyncio.to_thread(run_cli, "analyze", str(path), "--format", "json")
    assert analyzed.returncode in (0, 1), analyzed.stderr
    assert len(json.loads(analyzed.stdout)["connections"]) == len(frames)


async def test_record_refuses_a_directory_that_holds_a_recording_already(tmp_path):
    (tmp_path / "probe-server.mcap").write_bytes(b"")
    async with Simulator() as sim:
        done = await _cli(f"127.0.0.1:{sim.port}", "-p", "progwhiz", "--record", str(tmp_path))
    assert done.returncode == 2 and "exists already" in done.stderr


# -- reports -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def failing_report(tmp_path_factory) -> ProbeReport:
    """A recorded run with a pass, a failure and a skip."""
    async def run() -> ProbeReport:
        async with Simulator(bugs=("out-of-range",)) as sim:
            return await _probe(sim, ("answer.sensor-request", "answer.servo-position-request", "handshake.vpn"),
                                record_dir=str(tmp_path_factory.mktemp("rec")))
    return asyncio.run(run())


def test_json_is_the_issue_shape(failing_report):
    out = json.loads(render(failing_report, "json"))
    assert {"target", "cases", "passed", "failed", "skipped"} <= set(out)
    assert (out["passed"], out["failed"], out["skipped"]) == (1, 1, 1)
    for case in out["cases"]:
        assert {"id", "title", "spec", "verdict", "violations"} <= set(case)
        assert case["verdict"] in ("pass", "fail", "skip")
        assert all(set(v) == {"rule", "detail"} for v in case["violations"])
    failed = next(c for c in out["cases"] if c["verdict"] == "fail")
    assert failed["id"] == "answer.sensor-request" and failed["violations"][0]["rule"] == "PW-RANGE-SENSOR"


def test_junit_has_a_testcase_per_case_classed_by_spec_section(failing_report):
    root = ET.fromstring(render(failing_report, "junit"))
    cases = root.findall(".//testcase")
    assert [c.get("name") for c in cases] == [c.id for c in failing_report.cases]
    assert [c.get("classname") for c in cases] == [c.spec for c in failing_report.cases]
    by_name = {c.get("name"): c for c in cases}
    assert "PW-RANGE-SENSOR" in by_name["answer.sensor-request"].find("failure").text
    assert by_name["handshake.vpn"].find("skipped").get("message")
    assert root.find("testsuite").get("failures") == "1"


@pytest.mark.parametrize("fmt", ["text", "markdown", "html"])
def test_text_markdown_and_html_group_cases_by_spec_section(failing_report, fmt):
    out = render(failing_report, fmt)
    for section in ("Sensor Request", "Servo Position Request", "Functional Flow"):
        assert section in out
    assert "PW-RANGE-SENSOR" in out and "answer.servo-position-request" in out
    assert "\x1b[" not in out


def test_html_links_each_case_to_its_decoded_frames(failing_report):
    out = render(failing_report, "html")
    data = page_data(out)
    sensor = next(c for c in failing_report.cases if c.id == "answer.sensor-request")
    [linked] = [r for r in sections(data)["index"]["table"]["rows"] if r["id"] == "case-answer.sensor-request"]
    assert linked["f"] == f"conn-{sensor.conn}"
    assert any(f["meaning"] == "Sensor Request ch 12" for f in data["frames"][linked["f"]]["rows"])  # decoded
    assert [r["id"] for r in sections(data)["failures"]["table"]["rows"]] == ["case-answer.sensor-request"]
    assert "<script src" not in out and "<link" not in out  # self-contained


async def test_no_output_shows_the_password(tmp_path):
    """The password through every format, the progress lines and the recording."""
    async with Simulator(password=SECRET) as sim:
        outs = []
        for fmt in FORMATS:
            done = await _cli(f"127.0.0.1:{sim.port}", "--cases", "handshake.*", "--cases", "answer.sensor-request",
                              "--format", fmt, "-v", *(("--record", str(tmp_path / "rec")) if fmt == "html" else ()),
                              env={"WHIZTAP_PASSWORD": SECRET.decode()})
            assert done.returncode == 0, done.stderr
            outs.append(done.stdout + done.stderr)
    for fmt, out in zip(FORMATS, outs):
        assert_no_leak(f"probe server --format {fmt}", out)
    assert_no_leak("the probe's recording", topics_text(tmp_path / "rec" / "probe-server.mcap"))


# -- the judging takes any bytes a server sends ----------------------------------------------------------

_SERVER_BYTES = st.lists(st.one_of(st.binary(max_size=40), st.sampled_from(
    [b"sendchkpass", b"readytogo", b"Failed Validation", b"cr1-12--5--0-ss1", b"cr1-12--9999--0-ss1", b"sr1-\x01",
     b"200-ss1", b"\xff\xd8\xff\xe0\x00\x10", b"-ss1", b"\r\n"])), max_size=12)


@settings(max_examples=150, deadline=None)
@given(server=_SERVER_BYTES, closed=st.booleans(), case=st.sampled_from(catalogue()))
def test_any_server_bytes_give_a_verdict_with_known_rules_and_every_format_renders(server, closed, case):
    target = Target(Mode.WINSOCK, PASSWORD, parse_channels(DEFAULT_CHANNELS))
    plan = case.plan(target)
    sent = [] if isinstance(plan, str) else [s.data for s in plan if hasattr(s, "data")]
    trace = Trace(closed_early=closed, how="closed" if closed else "")
    t = 0
    for i in range(max(len(sent), len(server))):  # the probe's frames and the server's bytes, interleaved
        for direction, chunks in ((Direction.C2S, sent), (Direction.S2C, server)):
            if i < len(chunks):
                t += 1000
                trace.events.append((direction, chunks[i], t))
    trace.end_ns = t + 1000
    verdict, findings, reason = judge(case, target, [trace])
    assert verdict in Outcome
    assert all(f.rule in RULES or f.rule in PROBE_RULES for f in findings)
    assert (verdict is Outcome.FAIL) == bool(findings)
    assert (verdict is Outcome.SKIP) == bool(reason)
    report = ProbeReport("127.0.0.1:1", "server", [])
    report.cases.append(CaseResult(case.id, case.title, case.spec, verdict, findings, reason))
    ET.fromstring(render(report, "junit"))
    json.loads(render(report, "json"))
    for fmt in ("text", "markdown", "html"):
        assert not re.search(r"[\x00-\x08\x0b-\x1f]", render(report, fmt))  # control bytes are shown escaped
