"""``whiztap analyze --format github``: GitHub Actions workflow commands, one
annotation per violation, escaped as the runner reads them back, capped, then
the verdict; on real recordings, and any text through the escaper."""

from __future__ import annotations

import functools
import json
import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.report.github import (
    MAX_ANNOTATIONS, escape_data, escape_property, render_github)
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.text import printable

from tests.cli_support import run_cli
from tests.test_analyze_middle import ANSWER_S
from tests.test_report_sarif import CLEAN, VIOLATIONS, VPN, record_injected, record_unlisted
from tests.tui_support import ROOT

COMMAND = {"error": "error", "warning": "warning", "info": "notice"}
# One workflow command as the runner splits it: no raw ':' or ',' inside a property, no line break anywhere.
LINE = re.compile(r"::(error|warning|notice)(?: file=(?P<file>[^,:\r\n]*),title=(?P<title>[^,:\r\n]*)"
                  r"| title=(?P<own>[^,:\r\n]*))::(?P<message>[^\r\n]*)")


def unescape(text: str) -> str:
    """What the runner makes of an escaped value (one pass, so '%250A' stays '%0A')."""
    return re.sub("%(25|0D|0A|3A|2C)", lambda m: {"25": "%", "0D": "\r", "0A": "\n", "3A": ":", "2C": ","}[m[1]],
                  text)


def analyze(*args: object, cwd: Path = ROOT) -> tuple[int, str]:
    done = run_cli("analyze", *args, cwd=cwd)
    assert done.returncode in (0, 1), done.stderr
    return done.returncode, done.stdout


@pytest.fixture(scope="module")
def injected(tmp_path_factory) -> Path:
    return record_injected(tmp_path_factory.mktemp("middle") / "injected.mcap")


@pytest.fixture(scope="module")
def unlisted(tmp_path_factory) -> Path:
    return record_unlisted(tmp_path_factory.mktemp("many") / "unsolicited.mcap")


@functools.cache
def violations_json() -> str:
    return analyze(VIOLATIONS, "--format", "json")[1]


def commands(text: str) -> list[re.Match[str]]:
    """Every line of ``text`` as a workflow command (a line that is none fails the test)."""
    assert text.endswith("\n")
    lines = text[:-1].split("\n")
    assert text.splitlines() == lines  # no other line break either (VT, FF, NEL, U+2028...)
    matches = [LINE.fullmatch(line) for line in lines]
    assert all(matches), [line for line, m in zip(lines, matches) if not m]
    return [m for m in matches if m]


def test_github_annotates_each_violation_then_says_the_verdict():
    code, out = analyze(VIOLATIONS, "--format", "github")
    report = json.loads(violations_json())
    assert code == 1 and len(report["violations"]) < MAX_ANNOTATIONS
    *lines, last = commands(out)
    assert len(lines) == len(report["violations"])
    for m, v in zip(lines, report["violations"]):
        assert m[1] == COMMAND[v["severity"]]
        assert unescape(m["file"]) == VIOLATIONS
        assert unescape(m["title"]) == f"{v['rule_id']} ({v['section']})" and v["rule_id"] in RULES
        message = unescape(m["message"])
        assert message.startswith(v["detail"]) and f"[conn {v['conn']}, {v['dir']}, item {v['index']}, " in message
    assert (last[1], last["own"]) == ("error", "whiztap verdict")
    assert unescape(last["message"]).startswith("FAIL: violations at or above error (40 errors, 6 warnings, 2 info)")
    code, out = analyze(CLEAN, "--format", "github")
    [verdict] = commands(out)
    assert code == 0 and verdict[1] == "notice" and verdict["message"].startswith("PASS: no violation at or above")


def test_the_exit_status_is_the_same_whatever_the_format(tmp_path):
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not a recording")
    for inputs, code in (([CLEAN], 0), ([VIOLATIONS], 1), ([CLEAN, VPN], 0), ([CLEAN, broken], 2)):
        for fmt in ("text", "json", "junit", "sarif", "github"):
            assert run_cli("analyze", *inputs, "--format", fmt, cwd=ROOT).returncode == code, (inputs, fmt)


def test_github_caps_its_annotations_and_counts_the_rest_by_severity(unlisted):
    """10,000 listed violations (and more counted): fifty lines, one notice
    on the rest by severity and on the unlisted ones, the verdict."""
    code, out = analyze(unlisted, "--format", "github")
    report = json.loads(analyze(unlisted, "--format", "json")[1])
    assert code == 1 and report["violations_not_listed"] > 0
    found = commands(out)
    assert len(found) == MAX_ANNOTATIONS + 2
    assert all(m["file"] for m in found[:MAX_ANNOTATIONS])
    more, verdict = found[-2:]
    assert (more[1], more["own"], verdict["own"]) == ("notice", "whiztap", "whiztap verdict")
    left = report["violations"][MAX_ANNOTATIONS:]
    by = {s: sum(v["severity"] == s for v in left) for s in ("error", "warning", "info")}
    assert by["error"] > 0 and sum(by.values()) == len(left)
    assert unescape(more["message"]).startswith(
        f"{len(left):,} more annotations not shown ({by['error']:,} errors, {by['warning']:,} warnings, "
        f"{by['info']:,} info); {report['violations_not_listed']:,} more violations counted but not listed")


def test_the_cap_counts_what_it_left_out_of_each_severity():
    """The sample's violations (every severity) over and over, as the
    renderer gets them: nothing said left out up to the cap, then each
    severity's count."""
    report = json.loads(violations_json())
    many = report["violations"] * 3
    report["violations"] = many[:MAX_ANNOTATIONS]
    assert len(commands(render_github(report))) == MAX_ANNOTATIONS + 1
    report["violations"] = many
    found = commands(render_github(report))
    assert len(found) == MAX_ANNOTATIONS + 2
    left = many[MAX_ANNOTATIONS:]
    by = {s: sum(v["severity"] == s for v in left) for s in ("error", "warning", "info")}
    assert all(by.values())
    assert unescape(found[-2]["message"]) == (
        f"{len(left)} more annotations not shown ({by['error']} errors, {by['warning']} warnings, {by['info']} info)"
        " (every listed one: --format json or html)")


@pytest.mark.parametrize("fail", [False, True], ids=["effects listed", "--fail-on-interventions"])
def test_an_effect_is_a_notice_marked_as_such_unless_it_fails_the_report(injected, fail):
    flags = ("--answer-timeout", ANSWER_S, *(("--fail-on-interventions",) * fail))
    code, out = analyze(injected, "--format", "github", *flags)
    report = json.loads(analyze(injected, "--format", "json", *flags)[1])
    effects = report["interventions"]["effects"]
    assert effects and code == int(fail)
    *lines, verdict = commands(out)
    assert len(lines) == len(report["violations"]) + len(effects)
    for m, effect in zip(lines[len(report["violations"]):], effects):
        assert m[1] == (COMMAND[effect["severity"]] if fail else "notice")
        assert unescape(m["title"]).endswith("effect of an intervention")
        assert f"follows from {effect['cause']}" in unescape(m["message"])
    assert verdict[1] == ("error" if fail else "notice")


def test_github_to_a_file_and_to_stdout_are_the_same(tmp_path):
    out = tmp_path / "annotations.txt"
    assert run_cli("analyze", VIOLATIONS, "--format", "github", "-o", out, cwd=ROOT).returncode == 1
    assert out.read_text() == analyze(VIOLATIONS, "--format", "github", "-o", "-")[1] \
        == analyze(VIOLATIONS, "--format", "github")[1]


@settings(max_examples=300, deadline=None)
@given(st.text())
def test_escaped_text_reads_back_and_never_breaks_its_line(text):
    data, prop = escape_data(text), escape_property(text)
    for escaped in (data, prop):
        assert "\n" not in escaped and "\r" not in escaped and unescape(escaped) == text
    assert ":" not in prop and "," not in prop


_WORDS = st.text(st.characters(codec="utf-8"), max_size=40)


@settings(max_examples=150, deadline=None)
@given(file=_WORDS, detail=_WORDS, frame=_WORDS, section=_WORDS)
def test_any_value_from_a_recording_stays_in_its_place(file, detail, frame, section):
    """A violation whose every text is drawn: its line is one command whose
    file, title and message read back as the value, made printable."""
    report = json.loads(violations_json())
    v = dict(report["violations"][0], file=file, detail=detail, frame=frame, section=section)
    first, _verdict = commands(render_github(dict(report, violations=[v])))
    assert unescape(first["file"]) == printable(file)
    assert unescape(first["title"]) == printable(f"PW-FRAME-GARBAGE ({section})")
    assert unescape(first["message"]).startswith(printable(f"{detail}: {frame} [conn "))
