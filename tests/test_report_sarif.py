"""``whiztap analyze --format sarif``: SARIF 2.1.0, validated against the
OASIS schema as Microsoft's @microsoft/jest-sarif ships it (rtm.5, installed
by .ci/install-test-deps into tests/mcap_check), formats included (the URIs:
GitHub's upload-sarif warns of every invalid one), on real recordings."""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from pathlib import Path
from urllib.parse import unquote, urlsplit

import jsonschema
import pytest

from whiztap.analyzer.analysis.report.sarif import FINGERPRINT, artifact_uri, render_sarif
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.text import printable
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.sim.client import Client

from tests.cli_support import run_cli
from tests.record_support import record_drawn
from tests.test_analyze_middle import ANSWER_S, NEVER, _record, _sensors
from tests.tui_support import ROOT

SCHEMA = ROOT / "tests/mcap_check/node_modules/@microsoft/jest-sarif/lib/schemas/sarif-2.1.0-rtm.5.json"
CLEAN, VIOLATIONS, VPN = "samples/clean-winsock.mcap", "samples/violations.mcap", "samples/vpn.mcap"
LEVEL = {"error": "error", "warning": "warning", "info": "note"}
UNSOLICITED = 10_050  # answers nobody asked for: past the 10,000 violations a report lists


@pytest.fixture(scope="module")
def validator() -> jsonschema.protocols.Validator:
    """The validator the schema names (draft-04), checking formats too."""
    if not SCHEMA.exists():
        pytest.skip(f"the SARIF 2.1.0 schema is not installed ({SCHEMA.relative_to(ROOT)}): "
                    "make test-deps (npm ci in tests/mcap_check)")
    schema = json.loads(SCHEMA.read_text())
    cls = jsonschema.validators.validator_for(schema)
    assert cls is jsonschema.Draft4Validator
    cls.check_schema(schema)
    return cls(schema, format_checker=jsonschema.FormatChecker())


def errors(validator: jsonschema.protocols.Validator, log: dict) -> list[str]:
    return [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(log)]


def analyze(*args: object, cwd: Path = ROOT, codes: tuple[int, ...] = (0, 1)) -> tuple[int, str]:
    done = run_cli("analyze", *args, cwd=cwd)
    assert done.returncode in codes, done.stderr
    return done.returncode, done.stdout


def sarif_and_json(*args: object, cwd: Path = ROOT, codes: tuple[int, ...] = (0, 1)) -> tuple[int, dict, dict]:
    """(exit status, SARIF log, JSON report) of the same run; the status is the same for both."""
    code, out = analyze(*args, "--format", "sarif", cwd=cwd, codes=codes)
    json_code, report = analyze(*args, "--format", "json", cwd=cwd, codes=codes)
    assert code == json_code
    return code, json.loads(out), json.loads(report)


def where(v: dict) -> tuple:
    return v["rule_id"], printable(v["file"]), v["conn"], v["dir"], v["index"]


def where_result(result: dict) -> tuple:
    p = result["properties"]
    return result["ruleId"], p["file"], p["conn"], p["direction"], p["item"]


def check_results(log: dict, report: dict) -> None:
    """Each listed violation, then each listed effect, is one result with its
    rule, place and level; every rule is the driver's; fingerprints are unique."""
    [run] = log["runs"]
    rules = run["tool"]["driver"]["rules"]
    assert [r["id"] for r in rules] == list(RULES)
    assert all(r["defaultConfiguration"]["level"] == LEVEL[str(RULES[r["id"]].severity)] for r in rules)
    effects = report.get("interventions", {}).get("effects", [])
    results = run["results"]
    assert Counter(map(where_result, results)) == Counter(map(where, report["violations"] + effects))
    assert len(results) == len(report["violations"]) + len(effects)
    for result, v in zip(results, report["violations"]):
        assert where_result(result) == where(v)
        assert rules[result["ruleIndex"]]["id"] == result["ruleId"]
        assert result["level"] == LEVEL[v["severity"]]
        assert "effect_of_intervention" not in result["properties"]
        [location] = result["locations"]
        assert location["physicalLocation"]["artifactLocation"]["uri"] == artifact_uri(v["file"])
        assert location["physicalLocation"]["region"] == {"startLine": 1}
        assert location["logicalLocations"][0]["fullyQualifiedName"].startswith(
            printable(f"{v['file']}/conn {v['conn']}/"))
        assert v["detail"] in result["message"]["text"]
    fingerprints = [r["partialFingerprints"][FINGERPRINT] for r in results]
    assert len(set(fingerprints)) == len(fingerprints)
    assert run["properties"]["passed"] == report["passed"]
    assert run["properties"]["rule_counts"] == report["rule_counts"]


@pytest.mark.parametrize("inputs", [[CLEAN], [VIOLATIONS], [CLEAN, VIOLATIONS, VPN]],
                         ids=["passing", "failing", "three files"])
def test_sarif_is_valid_and_holds_one_result_per_violation(validator, inputs):
    code, log, report = sarif_and_json(*inputs)
    assert errors(validator, log) == []
    check_results(log, report)
    assert (code == 0) == report["passed"] == (inputs == [CLEAN])
    [run] = log["runs"]
    assert [a["location"]["uri"] for a in run["artifacts"]] == inputs
    assert run["invocations"] == [{"executionSuccessful": True}]
    assert (run["results"] == []) == (inputs == [CLEAN])


def test_the_same_recording_gives_the_same_fingerprints_and_bytes():
    """GitHub follows an alert from run to run by its fingerprint; nothing in
    the log changes from one run to the next (no time, no host)."""
    assert analyze(VIOLATIONS, "--format", "sarif")[1] == analyze(VIOLATIONS, "--format", "sarif")[1]


def test_a_document_the_schema_refuses_is_refused(validator):
    log = json.loads(analyze(VIOLATIONS, "--format", "sarif")[1])
    del log["runs"][0]["results"][0]["message"]
    assert any("'message' is a required property" in e for e in errors(validator, log))
    log = json.loads(analyze(VIOLATIONS, "--format", "sarif")[1])
    log["runs"][0]["results"][0]["locations"][0]["physicalLocation"]["artifactLocation"]["uri"] = "a b#c#d"
    assert any("uri-reference" in e for e in errors(validator, log))  # formats are checked too


def test_file_names_are_uri_references_github_can_resolve(validator, tmp_path):
    """A relative name percent-encoded (a ':' must not read as a scheme, nor
    '#' as a fragment; a name that is not UTF-8 by its bytes), an absolute
    one a file: URI, a URL as it is."""
    name, raw = "odd: #1 50% ü.mcap", os.fsdecode(b"raw\xff.mcap")
    shutil.copy(ROOT / VIOLATIONS, tmp_path / name)
    shutil.copy(ROOT / CLEAN, tmp_path / raw)
    url = (ROOT / VPN).as_uri()
    _, log, report = sarif_and_json(name, tmp_path / name, url, raw, cwd=tmp_path)
    assert errors(validator, log) == []
    check_results(log, report)
    uris = [a["location"]["uri"] for a in log["runs"][0]["artifacts"]]
    assert uris == [artifact_uri(f) for f in report["files"]]
    relative, absolute = uris[report["files"].index(name)], uris[report["files"].index(str(tmp_path / name))]
    assert urlsplit(relative).scheme == "" and unquote(relative) == name and " " not in relative
    assert absolute == (tmp_path / name).as_uri()
    assert url in uris and "raw%FF.mcap" in uris


def record_injected(path: Path) -> Path:
    """Through the real proxy in front of the simulator, a request the proxy
    injected: its answer reaches the client unasked, an effect of the
    injection and no side's violation."""
    async def session(client: Client, rec) -> None:
        await _sensors(client, 1)
        rec.controller.inject(1, "c2s", "sensor 13")
        await client.sensor(12)

    return _record(path, (NEVER,), session)


@pytest.fixture(scope="module")
def injected(tmp_path_factory) -> Path:
    return record_injected(tmp_path_factory.mktemp("middle") / "injected.mcap")


@pytest.mark.parametrize("fail", [False, True], ids=["effects listed", "--fail-on-interventions"])
def test_an_effect_is_a_note_unless_it_fails_the_report(validator, injected, fail):
    flags = ("--answer-timeout", ANSWER_S, *(("--fail-on-interventions",) * fail))
    code, log, report = sarif_and_json(injected, *flags)
    assert errors(validator, log) == []
    check_results(log, report)
    [run] = log["runs"]
    section = report["interventions"]
    assert section["effects"] and report["passed"] is (not fail) and code == int(fail)
    effects = run["results"][len(report["violations"]):]
    assert len(effects) == len(section["effects"])
    for result, effect in zip(effects, section["effects"]):
        assert result["properties"]["effect_of_intervention"] is True
        assert result["properties"]["cause"] == effect["cause"] and "injection" in effect["cause"]
        assert result["level"] == (LEVEL[effect["severity"]] if fail else "note")
        assert result["properties"]["fails_the_report"] is (fail and effect["severity"] == "error")
        assert "neither side's doing" in result["message"]["text"]
    assert run["properties"]["fail_on_interventions"] is fail and run["properties"]["passed"] is (not fail)


def record_unlisted(path: Path) -> Path:
    """A recording of more violations than a report lists: a server that
    sends answers nobody asked for, one after the other."""
    ops = [("opened", 1, "c2s", b""), ("data", 1, "s2c", b"readytogo\r\n"),
           ("data", 1, "s2c", b"cr1-12--5--0-ss1" * UNSOLICITED), ("closed", 1, "c2s", b"")]
    record_drawn(Recorder(RecordingFile(str(path), {"session_id": "unsolicited"})), ops)
    return path


@pytest.fixture(scope="module")
def unlisted(tmp_path_factory) -> Path:
    return record_unlisted(tmp_path_factory.mktemp("many") / "unsolicited.mcap")


def test_violations_past_the_listed_ones_are_said(validator, unlisted):
    code, log, report = sarif_and_json(unlisted)
    assert code == 1 and report["violations_not_listed"] > 0
    assert errors(validator, log) == []
    check_results(log, report)
    [run] = log["runs"]
    assert run["properties"]["violations_not_listed"] == report["violations_not_listed"]
    assert sum(run["properties"]["rule_counts"].values()) == len(run["results"]) + report["violations_not_listed"]
    [invocation] = run["invocations"]
    [note] = invocation["toolExecutionNotifications"]
    assert note["level"] == "warning"
    assert note["message"]["text"].startswith(f"{report['violations_not_listed']} more violations counted but not")
    assert invocation["executionSuccessful"] is True  # violations fail the verdict, not the run


def test_an_input_that_could_not_be_read_is_said_and_the_run_did_not_succeed(validator, tmp_path):
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n" + b"not a recording")
    _, log, report = sarif_and_json(CLEAN, broken, codes=(2,))
    assert errors(validator, log) == []
    [run] = log["runs"]
    [invocation] = run["invocations"]
    assert invocation["executionSuccessful"] is False
    said = [n["message"]["text"] for n in invocation["toolExecutionNotifications"]]
    assert said == [f"not in this report: {u['error']}" for u in report["unreadable"]] and said
    assert run["properties"]["verdict"].startswith("INCOMPLETE: 1 input could not be read.")


def test_every_count_the_report_could_not_list_is_a_notification(validator):
    """Effects past the listed ones, and a report on nothing to judge (the
    renderer on the report as analyze builds it, the counts changed)."""
    report = json.loads(analyze(CLEAN, "--format", "json")[1])
    report["interventions"] = {"count": 1, "connections": 1, "causes": [], "effect_counts": {"PW-HS-ORDER": 3},
                               "effects": [], "effects_not_listed": 3, "effects_by_severity": {
                                   "error": 3, "warning": 0, "info": 0}, "fail_on_interventions": False}
    report["nothing_judged"], report["passed"] = "the server was never reached on any connection", False
    log = render_sarif(report)
    assert errors(validator, log) == []
    said = {n["message"]["text"]: n["level"] for n in log["runs"][0]["invocations"][0]["toolExecutionNotifications"]}
    assert said == {"3 more effects of the interventions counted but not listed": "warning",
                    "nothing to judge: the server was never reached on any connection": "error"}


def test_two_results_at_the_same_place_have_fingerprints_of_their_own():
    """The same rule broken twice on one item (the renderer on a report with
    a violation listed twice): the second is told apart, the first keeps its print."""
    report = json.loads(analyze(VIOLATIONS, "--format", "json")[1])
    once = render_sarif(report)["runs"][0]["results"]
    report["violations"].insert(1, report["violations"][0])
    twice = render_sarif(report)["runs"][0]["results"]
    prints = [r["partialFingerprints"][FINGERPRINT] for r in twice]
    assert len(set(prints)) == len(prints) == len(once) + 1
    assert prints[0] == once[0]["partialFingerprints"][FINGERPRINT]
