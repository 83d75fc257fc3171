"""SARIF 2.1.0: the report as static-analysis results, for GitHub code
scanning and the other tools that read SARIF.

One run; its driver lists every whiztap rule (a reportingDescriptor with its
spec section, summary and default level), so a result's ``ruleIndex`` always
finds its rule.  Each listed violation is a result: its level from the
rule's severity (error, warning, note), its message the detail and the
frame, its location the recording file (a physicalLocation on line 1:
GitHub shows only results with a file and a line, and a recording has no
lines) and, as a logical location, the connection, direction and item.  An
intervention's effect is a ``note`` marked as such in its properties, and
takes its rule's level only when ``--fail-on-interventions`` makes it count.
What the report leaves out (violations and effects past the listed ones,
files that could not be read, a recording with nothing to judge) is said in
the invocation's notifications; whether the report passed, in the run's
properties.  Text from a recording goes through ``printable`` (control
characters escaped, as in every other format), file names through
``artifact_uri`` (percent-encoded: GitHub's upload warns of every invalid URI).
No time or host goes in, so a run gives the same bytes wherever it runs.
The driver has no ``informationUri``: SARIF wants an absolute URI there and
whiztap has no public address; its properties name the docs instead.
"""

from __future__ import annotations

import hashlib
import re
from collections import Counter
from typing import Any
from urllib.parse import quote

from whiztap.analyzer import __version__
from whiztap.analyzer.analysis.report.words import side_words, verdict_words
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.text import plural, printable

SCHEMA = "https://json.schemastore.org/sarif-2.1.0.json"
LEVELS = {"error": "error", "warning": "warning", "info": "note"}
FINGERPRINT = "whiztapViolation/v1"  # the partialFingerprints key: a new version if what it hashes changes
FRAME_IN_MESSAGE = 120  # characters of the frame the message quotes (all of it is in the properties)
DOCS = "docs/analyze.md"
_RULE_INDEX = {rule_id: i for i, rule_id in enumerate(RULES)}
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://")
_URL_SAFE = ":/?#[]@!$&'()*+,;=%~"  # RFC 3986's reserved characters, and '%' of the escapes already in a URL


def artifact_uri(file: str) -> str:
    """A recording's name as the report gives it, as a URI reference: a URL
    (s3://, file://) as it is, an absolute path as a file: URI, a relative
    one percent-encoded relative reference (a ':' in it must not read as a
    scheme, nor '#' as a fragment), which GitHub resolves in the checkout.
    A name that is not UTF-8 keeps its bytes (surrogateescape)."""
    if _URL.match(file):
        return quote(file, safe=_URL_SAFE, errors="surrogateescape")
    encoded = quote(file, safe="/", errors="surrogateescape")
    return "file://" + encoded if file.startswith("/") else encoded


def _rules() -> list[dict[str, Any]]:
    return [{
        "id": rule.id, "name": rule.id.removeprefix("PW-").title().replace("-", ""),
        "shortDescription": {"text": rule.summary},
        "fullDescription": {"text": f"{rule.summary} (Progwhiz Robotics Server API Rev 1.8, {rule.section})."},
        "help": {"text": f"Spec section: {rule.section}. Severity in whiztap: {rule.severity}. "
                         f"'whiztap analyze --rules' lists every rule; {DOCS} tells how they are judged."},
        "defaultConfiguration": {"level": LEVELS[str(rule.severity)]},
        "properties": {"section": rule.section, "severity": str(rule.severity), "tags": ["conformance"]},
    } for rule in RULES.values()]


def _where(v: dict[str, Any]) -> str:
    """The violation's place: ``FILE/conn N/DIR/item I`` (no item when the index is not known)."""
    item = f"/item {v['index']}" if v.get("index", -1) >= 0 else ""
    return f"{v['file']}/conn {v['conn']}/{v['dir'] or 'both'}{item}"


def _fingerprint(v: dict[str, Any], seen: Counter[str]) -> str:
    """A hash of the rule, the place and the frame (not the time, which a cut
    recording moves), and how many results before had the same: stable from
    run to run of the same recording, and unique in the run."""
    key = f"{v['rule_id']}|{_where(v)}|{v['frame']}"
    seen[key] += 1
    return hashlib.sha256(f"{key}|{seen[key]}".encode(errors="surrogateescape")).hexdigest()[:32]


def _result(report: dict[str, Any], v: dict[str, Any], level: str, seen: Counter[str],
            effect: dict[str, Any] | None = None) -> dict[str, Any]:
    """``effect``: for an intervention's effect, the properties that say so."""
    frame = printable(v["frame"])
    quoted = frame if len(frame) <= FRAME_IN_MESSAGE else frame[:FRAME_IN_MESSAGE] + "…"
    properties: dict[str, Any] = {
        "file": printable(v["file"]), "conn": v["conn"], "direction": v["dir"], "item": v.get("index", -1),
        "t_rel_s": v["t_rel_s"], "section": printable(v["section"]), "frame": frame,
        "side": v.get("side") or v.get("seen_by", ""),
    }
    properties.update(effect or {})
    return {
        "ruleId": v["rule_id"], "ruleIndex": _RULE_INDEX[v["rule_id"]], "level": level,
        "message": {"text": printable(f"{v['detail']} (frame {quoted}){side_words(report, v)}")},
        "locations": [{
            "physicalLocation": {"artifactLocation": {"uri": artifact_uri(v["file"])}, "region": {"startLine": 1}},
            "logicalLocations": [{"name": f"conn {v['conn']}", "fullyQualifiedName": printable(_where(v)),
                                  "kind": "object"}],
        }],
        "partialFingerprints": {FINGERPRINT: _fingerprint(v, seen)},
        "properties": properties,
    }


def _results(report: dict[str, Any]) -> list[dict[str, Any]]:
    """A result per listed violation, then one per listed effect of the interventions."""
    seen: Counter[str] = Counter()
    results = [_result(report, v, LEVELS[v["severity"]], seen) for v in report["violations"]]
    section = report.get("interventions")
    if section is not None:
        ignored = set(report["ignored_rules"])
        threshold = Severity.parse(report["severity_threshold"])
        for v in section["effects"]:
            counts = section["fail_on_interventions"] and v["rule_id"] not in ignored
            results.append(_result(report, v, LEVELS[v["severity"]] if counts else "note", seen, {
                "effect_of_intervention": True, "cause": printable(v.get("cause", "")),
                "fails_the_report": counts and Severity.parse(v["severity"]) >= threshold}))
    return results


def _notifications(report: dict[str, Any]) -> list[dict[str, Any]]:
    """What the report could not say: each as a notification (level, text)."""
    said: list[tuple[str, str]] = []
    if report["violations_not_listed"]:
        said.append(("warning", f"{plural(report['violations_not_listed'], 'more violation')} "
                                "counted but not listed (each rule's count is in the run's properties)"))
    section = report.get("interventions")
    if section is not None and section["effects_not_listed"]:
        said.append(("warning", f"{plural(section['effects_not_listed'], 'more effect')} of the interventions "
                                "counted but not listed"))
    if report.get("nothing_judged"):
        said.append(("warning" if report["passed"] else "error", f"nothing to judge: {report['nothing_judged']}"))
    said += [("error", f"not in this report: {u['error']}") for u in report.get("unreadable", ())]
    return [{"level": level, "message": {"text": printable(text)}} for level, text in said]


def render_sarif(report: dict[str, Any]) -> dict[str, Any]:
    """The SARIF log (a JSON-ready dict) of ``report``.  The invocation was
    successful unless an input could not be read (analyze exits 2 then);
    violations make a run that failed its verdict, not one that failed to run."""
    invocation: dict[str, Any] = {"executionSuccessful": not report.get("unreadable")}
    notifications = _notifications(report)
    if notifications:
        invocation["toolExecutionNotifications"] = notifications
    properties: dict[str, Any] = {
        "passed": report["passed"], "verdict": printable(verdict_words(report)),
        "severity_threshold": report["severity_threshold"], "ignored_rules": report["ignored_rules"],
        "rule_counts": report["rule_counts"], "violations_not_listed": report["violations_not_listed"],
    }
    section = report.get("interventions")
    if section is not None:
        properties.update(effect_counts=section["effect_counts"], effects_not_listed=section["effects_not_listed"],
                          fail_on_interventions=section["fail_on_interventions"])
    return {
        "$schema": SCHEMA, "version": "2.1.0",
        "runs": [{
            "tool": {"driver": {"name": "whiztap", "version": __version__, "semanticVersion": __version__,
                                "rules": _rules(), "properties": {"documentation": DOCS}}},
            "invocations": [invocation],
            "artifacts": [{"location": {"uri": artifact_uri(f)}} for f in report["files"]],
            "results": _results(report),
            "properties": properties,
        }],
    }
