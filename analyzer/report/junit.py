"""JUnit XML: one test case per rule, each violation a failure, so CI shows them.

Violations of rules below the severity threshold do not fail their test case
(the report passes with them); they are listed in its system-out instead.
Inputs that could not be read make one more test case, in error.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any

from analyzer.rules import RULES, Severity


def render_junit(report: dict[str, Any]) -> str:
    by_rule: dict[str, list[dict[str, Any]]] = {rule_id: [] for rule_id in RULES}
    for v in report["violations"]:
        by_rule[v["rule_id"]].append(v)
    ignored = set(report["ignored_rules"])
    threshold = Severity.parse(report["severity_threshold"])
    failing = {r for r, n in report["rule_counts"].items() if n and RULES[r].severity >= threshold}
    failing_cases = len(failing)
    unreadable = report.get("unreadable", [])
    tests, errors = str(len(RULES) + bool(unreadable)), str(int(bool(unreadable)))
    suites = ET.Element("testsuites", name="whiztap", tests=tests, failures=str(failing_cases), errors=errors)
    suite = ET.SubElement(suites, "testsuite", name="whiztap conformance", tests=tests,
                          failures=str(failing_cases), skipped=str(len(ignored)), errors=errors,
                          timestamp="", hostname="")
    props = ET.SubElement(suite, "properties")
    for name, value in (("files", " ".join(report["files"])), ("checksum_rule", report["checksum_rule"]["name"]),
                        ("severity_threshold", report["severity_threshold"])):
        ET.SubElement(props, "property", name=name, value=value)
    for rule_id, rule in RULES.items():
        case = ET.SubElement(suite, "testcase", classname=f"whiztap.{rule.section}", name=f"{rule_id}: {rule.summary}")
        if rule_id in ignored:
            ET.SubElement(case, "skipped", message="ignored by --ignore")
            continue
        texts = [f"{v['file']} conn {v['conn']} {v['dir'] or ''} at +{v['t_rel_s']:.6f}s\n"
                 f"frame: {v['frame']}\n{v['detail']}" for v in by_rule[rule_id]]
        if rule_id not in failing:
            if texts:
                ET.SubElement(case, "system-out").text = "\n\n".join(texts)
            continue
        for v, text in zip(by_rule[rule_id], texts):
            ET.SubElement(case, "failure", type=v["severity"], message=v["detail"]).text = text
        extra = report["rule_counts"].get(rule_id, 0) - len(by_rule[rule_id])
        if extra > 0:
            ET.SubElement(case, "failure", type=str(rule.severity), message=f"{extra} more not listed")
    if unreadable:
        case = ET.SubElement(suite, "testcase", classname="whiztap.input", name="every recording could be read")
        for u in unreadable:
            ET.SubElement(case, "error", type="unreadable", message=u["error"]).text = u["file"]
    ET.indent(suites)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(suites, encoding="unicode") + "\n"
