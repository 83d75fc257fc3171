"""SARIF 2.1.0: the report as static-analysis results, for GitHub code
scanning and the other tools that read SARIF.

One run; its driver lists every whiztap rule (a reportingDescriptor with its
spec section, summary and default level), so a result's ``ruleIndex`` always
finds its rule.  Each listed violation is a result: its level from the
rule's severity (error, warning, note), its message the detail and the
frame, its location the recording file (a physicalLocation: GitHub requires
one) and, as a logical location, the connection, direction and item.  An
intervention's effect is a ``note`` marked as such in its properties, and an
``error`` only under ``--fail-on-interventions``.  What the report leaves out
(violations past the listed ones, files that could not be read) is said in
the invocation's notifications; whether the report passed, in the run's
properties.  Every value goes through ``printable``: control characters
escaped as in every other format.
"""

from __future__ import annotations

import hashlib
from typing import Any
from urllib.parse import quote

from whiztap.analyzer import __version__
from whiztap.analyzer.analysis.report.text import verdict
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.text import plural, printable

SCHEMA = "https://json.schemastore.org/sarif-2.1.0.json"
LEVELS = {"error": "error", "warning": "warning", "info": "note"}
_RULE_INDEX = {rule_id: i for i, rule_id in enumerate(RULES)}


def _rules() -> list[dict[str, Any]]:
    return [{
        "id": rule.id, "name": rule.id.removeprefix("PW-").title().replace("-", ""),
        "shortDescription": {"text": rule.summary},
        "fullDescription": {"text": f"{rule.summary} (Progwhiz Robotics Server API Rev 1.8, {rule.section})."},
        "help": {"text": f"Spec section: {rule.section}. 'whiztap analyze --rules' lists every rule."},
        "defaultConfiguration": {"level": LEVELS[str(rule.severity)]},
        "properties": {"section": rule.section, "severity": str(rule.severity)},
    } for rule in RULES.values()]


def _result(v: dict[str, Any], effect: bool, failing: bool) -> dict[str, Any]:
    where = f"{v['file']}/conn {v['conn']}/{v['dir'] or 'both'}/item {v.get('index', -1)}"
    level = LEVELS[v["severity"]] if not effect or failing else "note"
    frame = printable(v["frame"])
    fingerprint = hashlib.sha256(f"{v['rule_id']}|{where}|{frame}".encode()).hexdigest()[:32]
    result: dict[str, Any] = {
        "ruleId": v["rule_id"], "ruleIndex": _RULE_INDEX[v["rule_id"]], "level": level,
        "message": {"text": printable(f"{v['detail']} (frame {v['frame'][:120]})")},
        "locations": [{
            "physicalLocation": {"artifactLocation": {"uri": quote(v["file"], safe="/:")},
                                 "region": {"startLine": 1}},
            "logicalLocations": [{"name": f"item {v.get('index', -1)}", "fullyQualifiedName": printable(where),
                                  "kind": "object"}],
        }],
        "partialFingerprints": {"whiztapViolation/v1": fingerprint},
        "properties": {"conn": v["conn"], "direction": v["dir"], "item": v.get("index", -1),
                       "t_rel_s": v["t_rel_s"], "section": v["section"], "side": v.get("side") or v.get("seen_by", ""),
                       "frame": frame},
    }
    if effect:
        result["properties"]["effect_of_intervention"] = True
    return result


def render_sarif(report: dict[str, Any]) -> dict[str, Any]:
    """The SARIF log (a JSON-ready dict) of ``report``."""
    results = [_result(v, False, True) for v in report["violations"]]
    section = report.get("interventions")
    notes = []
    if section is not None:
        failing = section.get("fail_on_interventions", False)
        results += [_result(v, True, failing) for v in section["effects"]]
    if report["violations_not_listed"]:
        notes.append(f"{plural(report['violations_not_listed'], 'more violation')} counted but not listed")
    notes += [f"not in this report: {u['error']}" for u in report.get("unreadable", ())]
    invocation: dict[str, Any] = {"executionSuccessful": not report.get("unreadable")}
    if notes:
        invocation["toolExecutionNotifications"] = [{"level": "warning", "message": {"text": printable(n)}}
                                                    for n in notes]
    return {
        "$schema": SCHEMA, "version": "2.1.0",
        "runs": [{
            "tool": {"driver": {"name": "whiztap", "version": __version__, "semanticVersion": __version__,
                                "rules": _rules()}},
            "invocations": [invocation],
            "artifacts": [{"location": {"uri": quote(f, safe="/:")}} for f in report["files"]],
            "results": results,
            "properties": {"passed": report["passed"], "verdict": printable(verdict(report)),
                           "violations_not_listed": report["violations_not_listed"],
                           "rule_counts": report["rule_counts"]},
        }],
    }
