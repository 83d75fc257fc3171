"""whiztap analyze, cat and info on the sample recordings, as a user runs them."""

import base64
import json
import shutil
import sys
from itertools import pairwise
from pathlib import Path

import jsonschema
import pytest
from junitparser import Error, Failure, JUnitXml, Skipped

from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.cli.analyze import scan_recording
from tests.cli_support import run_cli
from tests.report_page import page_data, sections
from tests.record_support import rebuild_streams, stream_bytes
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.report.schema import REPORT_SCHEMA
from whiztap.analyzer.analysis.report.text import md_text
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.text import shorten

SAMPLES = Path(__file__).parent.parent / "samples"
CLEAN, VPN, FAILED, VIOLATIONS = (SAMPLES / f"{n}.mcap" for n in ("clean-winsock", "vpn", "failed-password",
                                                                    "violations"))


def report(*args):
    result = run_cli("analyze", "--format", "json", *args)
    assert result.returncode in (0, 1), result.stderr
    data = json.loads(result.stdout)
    jsonschema.validate(data, REPORT_SCHEMA)
    return result.returncode, data


# -- reports on the samples ----------------------------------------------------------------


@pytest.mark.parametrize("sample", [CLEAN, VPN, FAILED])
def test_clean_samples_pass_with_nothing_to_report(sample):
    code, data = report(sample)
    assert code == 0 and data["passed"]
    assert data["rule_counts"] == {} and data["violations"] == []


@pytest.mark.parametrize("sample", [CLEAN, VPN, FAILED, VIOLATIONS])
def test_a_report_is_the_same_whether_clean_commands_come_out_as_events_or_not(sample):
    """analyze leaves them out for speed (Analyzer(every_event=False)); cat and the TUI do not."""
    def report_data(every_event: bool) -> dict:
        analyzer = Analyzer(str(sample), every_event=every_event)
        for event in scan_recording(sample):
            analyzer.receive(event)
        return build(analyzer.finish())

    assert report_data(every_event=False) == report_data(every_event=True)


def test_clean_winsock_summary():
    _, data = report(CLEAN)
    [conn] = data["connections"]
    assert (conn["mode"], conn["handshake"]) == ("winsock", "readytogo")
    assert conn["channel_map"]["12"]["unit_type"] == 2
    kinds = data["summary"]["frames_by_kind"]
    assert kinds["c2s"]["command"] > 20 and kinds["s2c"]["image"] == 1 and kinds["c2s"]["set_config"] == 1
    latency = {row["request"]: row for row in data["latency"]}
    assert {"Sensor Request", "Servo Position Request", "Fetch Configuration Settings",
            "Fetch Camera Image"} <= set(latency)
    assert all(0 < r["p50_ns"] <= r["p99_ns"] <= r["max_ns"] for r in data["latency"])
    [setcfg] = data["set_configurations"]
    assert setcfg["ok"] and setcfg["checksum"] == 72 and "dev-sum" in setcfg["satisfies"]


def test_failed_password_outcome():
    _, data = report(FAILED)
    assert [c["handshake"] for c in data["connections"]] == ["failed validation"]


def test_every_rule_fires_on_the_violations_sample():
    code, data = report(VIOLATIONS)
    assert code == 1 and not data["passed"]
    assert set(data["rule_counts"]) == set(RULES)
    for v in data["violations"]:  # a rule that holds in several messages cites the message's section
        assert v["detail"] and (v["section"] == RULES[v["rule_id"]].section
                                or v["rule_id"] in ("PW-FIXED-FIELD", "PW-RANGE-CHANNEL"))


def test_ignore_and_threshold_change_the_verdict():
    errors = [r for r, rule in RULES.items() if rule.severity == 3]
    args = [VIOLATIONS] + [a for r in errors for a in ("--ignore", r)]
    code, data = report(*args)
    assert code == 0 and data["passed"] and data["summary"]["violations_by_severity"]["error"] == 0
    code, _ = report(*args, "--severity-threshold", "warning")
    assert code == 1


def test_checksum_rule_is_named_and_applied():
    _, data = report(CLEAN, "--checksum-rule", "dev-unit-sum")
    assert data["checksum_rule"]["name"] == "dev-unit-sum"
    assert data["set_configurations"][0]["satisfies"] == ["dev-sum", "dev-unit-sum", "dev-sum-7bit"]


def test_several_files_and_a_folder(tmp_path):
    for f in (CLEAN, VPN):
        shutil.copy(f, tmp_path / f.name)
    _, serial = report(tmp_path, "--jobs", "1")
    _, parallel = report(tmp_path, "--jobs", "2")
    assert [row["file"] for row in serial["per_file"]] == [str(tmp_path / "clean-winsock.mcap"),
                                                            str(tmp_path / "vpn.mcap")]
    assert serial["summary"] == parallel["summary"]
    assert serial["summary"]["connections"] == 2


@pytest.mark.slow
def test_a_report_on_several_files_names_the_file_of_each_connection_and_violation(tmp_path):
    """Each file numbers its connections from 1: 'conn 3' alone said which of
    several it was no more than a page number without its book."""
    first, second = tmp_path / "monday.mcap", tmp_path / "tuesday.mcap"
    shutil.copy(VIOLATIONS, first)
    shutil.copy(VIOLATIONS, second)
    _, data = report(first, second)
    per_file = len(data["violations"]) // 2
    text = run_cli("analyze", first, second).stdout.splitlines()
    lines = [line for line in text if line.startswith("PW-")]
    assert len(lines) == 2 * per_file and per_file > 30
    assert all(f" {first} conn " in line or f" {second} conn " in line for line in lines)
    assert sum(f" {first} conn " in line for line in lines) == per_file
    header = text.index("Connections") + 1
    assert text[header].split()[:2] == ["file", "conn"]
    rows = text[header + 1:header + 1 + len(data["connections"])]
    assert all(row.split()[0] in (str(first), str(second)) for row in rows)
    assert sum(line.startswith((f"  {first} conn 1: ", f"  {first} conn 1 channels: ")) for line in text) >= 1
    markdown = run_cli("analyze", "--format", "markdown", first, second).stdout
    assert markdown.count(f"| {md_text(second)} |") >= per_file  # its connections' and violations' rows
    alone = run_cli("analyze", VIOLATIONS).stdout
    assert str(VIOLATIONS) not in alone and "] conn 1 c2s" in alone  # one file: nothing to tell apart


def test_text_report_to_a_pipe_is_never_wrapped():
    """Each escaped frame stays on one line, whole, for grep."""
    result = run_cli("analyze", VIOLATIONS)
    assert result.returncode == 1
    assert "FAIL" in result.stdout and "PW-SETCFG-CHECKSUM" in result.stdout
    _, data = report(VIOLATIONS)
    lines = result.stdout.splitlines()
    for v in data["violations"]:
        frame = shorten(v["frame"], 160)  # a long one says it is cut
        assert any(f"    {frame}   (" in line for line in lines), frame[:80]


def test_junit_has_a_case_per_rule_per_connection_that_broke_it(tmp_path):
    out = tmp_path / "report.xml"
    assert run_cli("analyze", VIOLATIONS, "--format", "junit", "-o", out).returncode == 1
    xml = JUnitXml.fromfile(str(out))
    [suite] = list(xml)
    assert suite.timestamp and suite.hostname  # CI shows when and where
    cases = list(suite)
    _, data = report(VIOLATIONS)
    broken = {(r, c["conn"]) for c in data["connections"] for r in c["violations"]}
    clean_rules = set(RULES) - {r for r, _ in broken}
    assert len(cases) == len(broken) + len(clean_rules)  # a clean rule still has its one case
    failing = [c for c in cases if any(isinstance(r, Failure) for r in c.result)]
    assert {(c.name.split(":")[0], int(c.name.rsplit(" conn ", 1)[1].rstrip("]"))) for c in failing} == {
        (r, conn) for r, conn in broken if RULES[r].severity == 3}
    run_cli("analyze", VIOLATIONS, "--format", "junit", "-o", out, "--force", "--ignore", "PW-DIRECTION")
    skipped = [c for suite in JUnitXml.fromfile(str(out)) for c in suite
               if any(isinstance(r, Skipped) for r in c.result)]
    assert [c.name.split(":")[0] for c in skipped] == ["PW-DIRECTION"]


def test_html_is_one_self_contained_page_with_its_plots_and_frames(tmp_path):
    out = tmp_path / "report.html"
    assert run_cli("analyze", CLEAN, VIOLATIONS, "--format", "html", "-o", out).returncode == 1
    page = out.read_text()
    assert "<script src" not in page and "<link" not in page and "http://" not in page.split("<script>")[0]
    data = page_data(page)
    assert [s["id"] for s in data["sections"]][:2] == ["violations", "plots"]  # what a CI reader came for, first
    plots = {p["id"] for p in sections(data)["plots"]["plots"]}
    assert {"items", "violations", "latency", "sensor", "servo"} <= plots
    table = sections(data)["violations"]["table"]
    labels = [c["label"] for c in table["columns"]]
    assert table["rows"] and all("f" in r for r in table["rows"])  # every violation links to its frames
    for r in table["rows"]:
        cells = dict(zip(labels, r["c"]))
        [hit] = [f for f in data["frames"][r["f"]]["rows"] if f["i"] == r["h"]]
        assert hit["text"][:100] == cells["frame"][:100]  # the very item, among the frames around it


def test_html_is_complete_without_matplotlib(tmp_path, monkeypatch):
    """The plots are the page's own: nothing optional is needed (it was a
    report without plots, and a warning, without the html extra)."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # 'import matplotlib' fails, as when it is not installed
    out = tmp_path / "report.html"
    result = run_cli("analyze", VIOLATIONS, "--format", "html", "-o", out, "-q", "--group-by", "robot")
    assert result.returncode == 1 and "matplotlib" not in result.stderr and "plots" not in result.stderr
    found = sections(page_data(out.read_text()))
    assert {"violations", "plots", "fleet0", "connections"} <= set(found)


def test_markdown(tmp_path):
    out = tmp_path / "report.md"
    run_cli("analyze", VIOLATIONS, "--format", "markdown", "-o", out)
    text = out.read_text()
    assert text.startswith("# whiztap conformance report") and "| `PW-RANGE-CHANNEL` |" in text


# -- unreadable input ---------------------------------------------------------------------


def one_line_error(result):
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    return result.stderr


def test_missing_file():
    assert "no such file" in one_line_error(run_cli("analyze", "/nonexistent/x.mcap"))


def test_not_a_recording(tmp_path):
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("hello")
    assert "not an MCAP file" in one_line_error(run_cli("analyze", bogus))


@pytest.mark.parametrize("command", ["analyze", "cat"])
def test_truncated_part_file_names_recover(tmp_path, command):
    part = tmp_path / "session.mcap.part"
    data = CLEAN.read_bytes()
    part.write_bytes(data[: len(data) // 2])
    assert f"whiztap recover {part}" in one_line_error(run_cli(command, part))


@pytest.mark.slow
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_an_unreadable_file_among_others_costs_only_itself(tmp_path, jobs):
    shutil.copy(CLEAN, tmp_path / CLEAN.name)
    cut = tmp_path / "cut-short.mcap"
    cut.write_bytes(VPN.read_bytes()[:len(VPN.read_bytes()) // 2])
    result = run_cli("analyze", "--format", "json", "--jobs", jobs, tmp_path)
    assert result.returncode == 2  # an input could not be read, even though a report was made
    assert result.stderr.strip().splitlines() == [
        f"whiztap: {cut}: the file is truncated (no footer); it looks like a recording that was cut short; "
        f"to turn it into a complete file: whiztap recover {cut}"]
    data = json.loads(result.stdout)
    jsonschema.validate(data, REPORT_SCHEMA)
    assert data["files"] == [str(tmp_path / CLEAN.name)]
    assert data["unreadable"] == [{"file": str(cut), "error": result.stderr.strip().removeprefix("whiztap: ")}]
    _, alone = report(tmp_path / CLEAN.name)
    assert data["summary"] == alone["summary"] and "unreadable" not in alone

    text = run_cli("analyze", "--jobs", jobs, tmp_path).stdout
    assert "INCOMPLETE: 1 input could not be read. PASS" in text and "cut-short.mcap" in text
    out = tmp_path / "report.xml"
    assert run_cli("analyze", "--format", "junit", "-o", out, tmp_path).returncode == 2
    cases = [case for suite in JUnitXml.fromfile(str(out)) for case in suite]
    assert len(cases) == len(RULES) + 1
    [broken] = [c for c in cases if any(isinstance(r, Error) for r in c.result)]
    assert broken.result[0].text == str(cut)
    for fmt, heading, shown in (("markdown", "## Not in this report", md_text),
                                ("html", "Not in this report (could not be read)", str)):
        page = run_cli("analyze", "--format", fmt, tmp_path).stdout
        assert heading in page and shown(f"{cut}: the file is truncated") in page, fmt


def test_unknown_rule_in_ignore():
    assert "--rules" in one_line_error(run_cli("analyze", CLEAN, "--ignore", "PW-NOPE"))


def test_rules_listing():
    result = run_cli("analyze", "--rules")
    assert result.returncode == 0 and len(result.stdout.splitlines()) == len(RULES)


# -- cat -------------------------------------------------------------------------------------


def cat_jsonl(*args):
    result = run_cli("cat", "--format", "jsonl", *args)
    assert result.returncode == 0, result.stderr
    return [json.loads(line) for line in result.stdout.splitlines()]


def test_cat_is_lossless_and_in_time_order():
    rows = [r for r in cat_jsonl(CLEAN) if r["kind"] != "late_violation"]
    assert all(a["t_ns"] <= b["t_ns"] for a, b in pairwise(rows))
    rebuilt: dict = {}
    for r in rows:
        rebuilt.setdefault((r["conn"], r["dir"]), bytearray()).extend(base64.b64decode(r["raw_b64"]))
    recorded = {key: stream_bytes(seg) for key, seg in rebuild_streams(str(CLEAN)).items()}
    assert {k: bytes(v) for k, v in rebuilt.items()} == recorded


def test_cat_fields():
    rows = cat_jsonl(CLEAN, "--kind", "response", "--channel", "12")
    assert rows and all(r["kind"] == "response" and r["fields"]["channel"] == 12 for r in rows)
    assert all("sensor_value" in r["fields"] and r["violations"] == [] for r in rows)
    assert {"t_ns", "conn", "dir", "kind", "raw_b64", "fields", "violations"} <= set(rows[0])


def test_cat_filters():
    assert all(r["violations"] for r in cat_jsonl(VIOLATIONS, "--violations-only"))
    assert {r["dir"] for r in cat_jsonl(CLEAN, "--dir", "s2c")} == {"s2c"}
    assert {r["conn"] for r in cat_jsonl(VIOLATIONS, "--conn", "3")} == {3}
    everything = cat_jsonl(VPN)
    start = everything[0]["t_ns"]
    window = cat_jsonl(VPN, "--since", "0.2", "--until", "0.5")
    assert window and all(0.2 <= (r["t_ns"] - start) / 1e9 < 0.5 for r in window)


def test_cat_text_marks_violations():
    result = run_cli("cat", VIOLATIONS, "--violations-only")
    assert result.returncode == 0 and "! PW-" in result.stdout


# -- info ------------------------------------------------------------------------------------


def test_info_on_a_complete_recording():
    result = run_cli("info", CLEAN, "--format", "json")
    info = json.loads(result.stdout)
    assert info["complete"] and info["format_version"] == "3" and info["connections"] == 1
    assert info["topics"]["/tcp/reads"] > 0 and info["duration_s"] > 0


def test_info_on_a_crash_leftover(tmp_path):
    part = tmp_path / "x.mcap.part"
    data = CLEAN.read_bytes()
    part.write_bytes(data[: len(data) * 2 // 3])
    result = run_cli("info", part)
    assert result.returncode == 0
    assert "NO: truncated" in result.stdout and "whiztap recover" in result.stdout


def _damaged(tmp_path, how):
    data = bytearray(CLEAN.read_bytes())
    if how == "chunk":
        at = data.index(b"zstd") + 40  # inside the first compressed chunk's bytes
        data[at:at + 16] = b"\xa5" * 16
    else:  # a record whose length field is absurd, right after the magic
        data[9:17] = (2**62).to_bytes(8, "little")
    path = tmp_path / f"damaged-{how}.mcap"
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("how", ["chunk", "length"])
@pytest.mark.parametrize("command", ["analyze", "cat", "info"])
def test_damaged_files_are_one_line_errors(tmp_path, how, command):
    assert "damaged" in one_line_error(run_cli(command, _damaged(tmp_path, how)))


def test_counts_over_time_draw_every_bin_and_group_a_long_span():
    """A quiet stretch is drawn at 0, never bridged by a line (it was: seconds
    with nothing in them were left out), and a long span is grouped into bins."""
    from collections import Counter

    from whiztap.analyzer.analysis.report.html import PLOT_BINS, _counts_plot

    plot = _counts_plot("v", "title", "violations", {"error": Counter({0: 2, 3: 1})})
    assert plot["series"][0]["points"] == [[0, 2], [1, 0], [2, 0], [3, 1]]
    assert plot["y_label"] == "violations per second"
    day = _counts_plot("v", "title", "items", {"command": Counter({0: 1, 86_399: 5})})
    points = day["series"][0]["points"]
    assert len(points) <= PLOT_BINS and sum(n for _, n in points) == 6 and day["y_label"] == "items per 44 s"
