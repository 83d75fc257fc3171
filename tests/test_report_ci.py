"""The CI formats of ``whiztap analyze``: SARIF 2.1.0 (validated against the
OASIS schema as Microsoft's @microsoft/jest-sarif ships it, installed by
.ci/install-test-deps) and GitHub Actions workflow commands."""

from __future__ import annotations

import json
import re

import jsonschema
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.report.github import MAX_ANNOTATIONS, escape_data, escape_property, render_github
from whiztap.analyzer.analysis.report.sarif import render_sarif
from whiztap.analyzer.protocol.rules import RULES

from tests.cli_support import run_cli
from tests.tui_support import ROOT, SAMPLES

SCHEMA = ROOT / "tests/mcap_check/node_modules/@microsoft/jest-sarif/lib/schemas/sarif-2.1.0-rtm.5.json"
VIOLATIONS = "samples/violations.mcap"


@pytest.fixture(scope="module")
def validator() -> jsonschema.protocols.Validator:
    if not SCHEMA.exists():
        pytest.skip("the SARIF schema is not installed: make test-deps (npm ci in tests/mcap_check)")
    schema = json.loads(SCHEMA.read_text())
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def analyze(*args: object) -> tuple[int, str]:
    done = run_cli("analyze", *args, cwd=ROOT)
    assert done.returncode in (0, 1), done.stderr
    return done.returncode, done.stdout


def errors(validator, log: dict) -> list[str]:
    return [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(log)]


@pytest.mark.parametrize("inputs", [["samples/clean-winsock.mcap"], [VIOLATIONS],
                                    ["samples/clean-winsock.mcap", VIOLATIONS, "samples/vpn.mcap"]])
def test_sarif_is_valid_and_holds_one_result_per_violation(validator, inputs):
    code, out = analyze(*inputs, "--format", "sarif")
    log = json.loads(out)
    assert errors(validator, log) == []
    [run] = log["runs"]
    report = json.loads(analyze(*inputs, "--format", "json")[1])
    assert run["properties"]["passed"] == report["passed"] == (code == 0)
    rules = run["tool"]["driver"]["rules"]
    assert [r["id"] for r in rules] == list(RULES)
    results = run["results"]
    assert len(results) == len(report["violations"])
    for result, v in zip(results, report["violations"]):
        assert rules[result["ruleIndex"]]["id"] == result["ruleId"] == v["rule_id"]
        assert result["level"] == {"error": "error", "warning": "warning", "info": "note"}[v["severity"]]
        [location] = result["locations"]
        assert location["physicalLocation"]["artifactLocation"]["uri"] == v["file"]
        assert (result["properties"]["conn"], result["properties"]["item"]) == (v["conn"], v["index"])
        assert f"conn {v['conn']}" in location["logicalLocations"][0]["fullyQualifiedName"]
    assert len({r["partialFingerprints"]["whiztapViolation/v1"] for r in results}) == len(results)


def test_a_document_the_schema_refuses_is_refused(validator):
    log = json.loads(analyze(VIOLATIONS, "--format", "sarif")[1])
    del log["runs"][0]["results"][0]["message"]
    assert any("message" in e for e in errors(validator, log))


def test_sarif_says_what_was_left_out(validator, tmp_path):
    report = json.loads(analyze(VIOLATIONS, "--format", "json")[1])
    report["violations_not_listed"] = 7
    report["unreadable"] = [{"file": "cut.mcap", "error": "cut.mcap: the file is truncated"}]
    log = render_sarif(report)
    assert errors(validator, log) == []
    [invocation] = log["runs"][0]["invocations"]
    said = [n["message"]["text"] for n in invocation["toolExecutionNotifications"]]
    assert said == ["7 more violations counted but not listed",
                    "not in this report: cut.mcap: the file is truncated"]
    assert invocation["executionSuccessful"] is False


def _with_effect(report: dict, fail: bool) -> dict:
    """The report as if its first violation had been an intervention's effect."""
    effect = dict(report["violations"].pop(0))
    effect["seen_by"] = effect.pop("side")
    effect["cause"] = "fault f: corrupt dir:c2s"
    report["interventions"] = {"effects": [effect], "effects_not_listed": 0, "fail_on_interventions": fail,
                               "effects_by_severity": {effect["severity"]: 1}}
    return report


@pytest.mark.parametrize("fail", [False, True])
def test_an_effect_is_a_note_unless_it_fails_the_report(validator, fail):
    report = _with_effect(json.loads(analyze(VIOLATIONS, "--format", "json")[1]), fail)
    log = render_sarif(report)
    assert errors(validator, log) == []
    effect = log["runs"][0]["results"][-1]
    assert effect["properties"]["effect_of_intervention"] is True
    assert effect["level"] == ("error" if fail else "note")
    line = render_github(report).splitlines()[len(report["violations"])]
    assert line.startswith("::error " if fail else "::notice ") and "effect of an intervention" in line


# -- GitHub workflow commands --------------------------------------------------------------------------

_COMMAND = re.compile(r"^::(error|warning|notice) (?:file=(?P<file>[^,:]*),)?title=(?P<title>[^,:]*)::(?P<message>.*)$")


def unescape(text: str) -> str:
    return text.replace("%0A", "\n").replace("%0D", "\r").replace("%3A", ":").replace("%2C", ",").replace("%25", "%")


def test_github_annotates_each_violation_then_says_the_verdict():
    code, out = analyze(VIOLATIONS, "--format", "github")
    report = json.loads(analyze(VIOLATIONS, "--format", "json")[1])
    lines = out.splitlines()
    assert code == 1 and len(lines) == len(report["violations"]) + 1
    for line, v in zip(lines, report["violations"]):
        m = _COMMAND.match(line)
        assert m, line
        assert m[1] == {"error": "error", "warning": "warning", "info": "notice"}[v["severity"]]
        assert unescape(m["file"]) == VIOLATIONS and unescape(m["title"]).startswith(v["rule_id"])
        assert f"conn {v['conn']}," in m["message"]
    assert lines[-1].startswith("::error title=whiztap verdict::FAIL")
    assert run_cli("analyze", SAMPLES / "clean-winsock.mcap", "--format", "github").stdout.startswith(
        "::notice title=whiztap verdict::PASS")


def test_github_caps_its_annotations_and_counts_the_rest(tmp_path):
    report = json.loads(analyze(VIOLATIONS, "--format", "json")[1])
    report["violations"] = report["violations"] * 3  # 144: past the cap
    report["violations_not_listed"] = 5
    lines = render_github(report).splitlines()
    assert len(lines) == MAX_ANNOTATIONS + 2
    left = len(report["violations"]) - MAX_ANNOTATIONS
    assert lines[-2].startswith("::notice title=whiztap::") and "5 more violations counted but not listed" in lines[-2]
    counted = sum(int(n.replace(",", "")) for n in re.findall(r"([\d,]+) (?:error|warning|notice)", lines[-2]))
    assert counted == left


def test_github_to_a_file_and_to_stdout_are_the_same(tmp_path):
    out = tmp_path / "annotations.txt"
    assert run_cli("analyze", VIOLATIONS, "--format", "github", "-o", out, cwd=ROOT).returncode == 1
    assert out.read_text() == analyze(VIOLATIONS, "--format", "github", "-o", "-")[1]


@settings(max_examples=300, deadline=None)
@given(st.text())
def test_escaped_text_reads_back_and_never_breaks_its_line(text):
    for escaped in (escape_data(text), escape_property(text)):
        assert "\n" not in escaped and "\r" not in escaped and unescape(escaped) == text
    assert ":" not in escape_property(text) and "," not in escape_property(text)

