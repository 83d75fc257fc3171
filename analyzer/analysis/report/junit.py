"""JUnit XML: a test case per rule per connection, each violation a failure,
so CI shows which rule broke where.

Each rule has one case per connection that broke it (named ``RULE: summary
[file conn N]``), and one case for the whole recording when nothing broke it,
so a clean run still lists every rule.  Violations of rules below the severity
threshold do not fail their case (the report passes with them); they are
listed in its system-out instead.  When the proxy stood in the middle, each
violation says whose side it is about, and the suite's properties and
system-out list the interventions, their effects and both latencies (the
server's and the client's), and one more case, "the interventions' effects",
fails only with ``--fail-on-interventions`` (one failure per effect at or
above the threshold).  Inputs that could not be read make one more
case, in error; a report on nothing to judge makes one more failing case.
"""

from __future__ import annotations

import datetime
import socket
import xml.etree.ElementTree as ET
from collections import Counter, defaultdict
from typing import Any

from whiztap.analyzer.analysis.report.words import (
    EFFECTS_HEADING,
    fleet_headings,
    fleet_key,
    group_name,
    intervention_lines,
    latency_tables,
    rule_counts_words,
    rules_since,
    side_words,
)
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.text import plural
# XML 1.0 forbids most control characters; terminals obey them
from whiztap.analyzer.protocol.text import printable as _x


def render_junit(report: dict[str, Any]) -> str:
    """Every value from the report goes through ``_x`` (ElementTree escapes
    markup, but writes control characters as they are: invalid XML)."""
    suites = ET.Element("testsuites", name="whiztap")
    suite = ET.SubElement(suites, "testsuite", name="whiztap conformance",
                          timestamp=_timestamp(report), hostname=socket.gethostname())
    props = ET.SubElement(suite, "properties")
    for name, value in (("files", " ".join(report["files"])), ("checksum_rule", report["checksum_rule"]["name"]),
                        ("severity_threshold", report["severity_threshold"])):
        ET.SubElement(props, "property", name=name, value=_x(value))
    if "assumed_channels" in report:
        ET.SubElement(props, "property", name="assumed_channels", value=_x(report["assumed_channels"]))
    if "interventions" in report:
        ET.SubElement(props, "property", name="interventions", value=str(report["interventions"]["count"]))
    tally: Counter[str] = Counter()  # tests, failures, errors, skipped
    _rule_cases(suite, report, tally)
    if "interventions" in report:
        _effects_case(suite, report, tally)
    _input_cases(suite, report, tally)
    if "interventions" in report:
        ET.SubElement(suite, "system-out").text = _interventions_text(report)
    _set_tally(suite, tally)
    total = Counter(tally)
    for table in report.get("fleet", ()):
        total.update(_fleet_suite(suites, report, table))
    _set_tally(suites, total)
    ET.indent(suites)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(suites, encoding="unicode") + "\n"


def _set_tally(element: ET.Element, tally: Counter[str]) -> None:
    for name in ("tests", "failures", "errors"):
        element.set(name, str(tally[name]))
    if element.tag == "testsuite":
        element.set("skipped", str(tally["skipped"]))


def _fleet_suite(suites: ET.Element, report: dict[str, Any], table: dict[str, Any]) -> Counter[str]:
    """A fleet table as a suite of its own: a case per group, failing when the
    group has a violation at or above the threshold; the case's system-out
    holds its rules (count, since) and its days, the suite's the table."""
    title, by_day = fleet_headings(table)
    suite = ET.SubElement(suites, "testsuite", name=_x(f"whiztap {title.lower()}"),
                          timestamp=_timestamp(report), hostname=socket.gethostname())
    tally: Counter[str] = Counter()
    key = fleet_key(table)
    for g in table["groups"]:
        name = group_name(table, g)
        case = ET.SubElement(suite, "testcase", classname=_x(f"whiztap.fleet.{key}"), name=_x(f"{key} {name}"))
        tally["tests"] += 1
        lines = [f"{plural(g['recordings'], 'recording')}, {plural(g['connections'], 'connection')}, "
                 f"{plural(g['frames'], 'item')}, {plural(g['violations'], 'violation')}: {rules_since(g)}",
                 f"{by_day}:"]
        lines += [f"  {d['day'] or 'unknown'}: {plural(d['recordings'], 'recording')}, "
                  f"{plural(d['violations'], 'violation')} ({rule_counts_words(d['rule_counts'])})" for d in g["days"]]
        if not g["passed"]:
            sev = g["violations_by_severity"]
            ET.SubElement(case, "failure", type="fleet", message=_x(
                f"{plural(sev['error'], 'error')}, {plural(sev['warning'], 'warning')}: {rules_since(g)}"))
            tally["failures"] += 1
        ET.SubElement(case, "system-out").text = "\n".join(_x(line) for line in lines)
    _set_tally(suite, tally)
    return tally


def _rule_cases(suite: ET.Element, report: dict[str, Any], tally: Counter[str]) -> None:
    """A case per rule per connection that broke it; one for the whole recording when none did."""
    listed: dict[tuple[str, str, int], list[dict[str, Any]]] = defaultdict(list)
    for v in report["violations"]:
        listed[(v["rule_id"], v["file"], v["conn"])].append(v)
    counted: dict[str, dict[tuple[str, int], int]] = defaultdict(dict)
    for c in report["connections"]:
        for rule_id, n in c["violations"].items():
            counted[rule_id][(c["file"], c["conn"])] = n
    ignored = set(report["ignored_rules"])
    threshold = Severity.parse(report["severity_threshold"])
    for rule_id, rule in RULES.items():
        classname = f"whiztap.{rule.section}"
        where = sorted(counted.get(rule_id, {}).items())
        if rule_id in ignored or not where:
            case = ET.SubElement(suite, "testcase", classname=classname, name=f"{rule_id}: {rule.summary}")
            tally["tests"] += 1
            if rule_id in ignored:
                ET.SubElement(case, "skipped", message="ignored by --ignore")
                tally["skipped"] += 1
            continue
        fails = rule.severity >= threshold
        for (file, conn), n in where:
            case = ET.SubElement(suite, "testcase", classname=classname,
                                 name=_x(f"{rule_id}: {rule.summary} [{file} conn {conn}]"))
            tally["tests"] += 1
            shown = listed.get((rule_id, file, conn), [])
            texts = [_violation_text(report, v) for v in shown]
            if not fails:
                if texts:
                    ET.SubElement(case, "system-out").text = "\n\n".join(texts)
                continue
            tally["failures"] += 1
            for v, text in zip(shown, texts):
                ET.SubElement(case, "failure", type=v["severity"], message=_x(v["detail"])).text = text
            if n > len(shown):
                ET.SubElement(case, "failure", type=str(rule.severity), message=f"{n - len(shown):,} more not listed")


def _violation_text(report: dict[str, Any], v: dict[str, Any]) -> str:
    return (_x(f"{v['file']} conn {v['conn']} {v['dir'] or ''}{side_words(report, v)} at +{v['t_rel_s']:.6f}s")
            + "\n" + _x(f"frame: {v['frame']}") + "\n" + _x(v["detail"]))


def _interventions_text(report: dict[str, Any]) -> str:
    """The interventions section as the suite's system-out: causes, then effects."""
    heading, rows = intervention_lines(report)
    lines = [_x(heading)] + [_x(f"  {cause}: {n} ({actions})") for cause, n, actions in rows]
    section = report["interventions"]
    if section["effects"]:
        lines += ["", _x(EFFECTS_HEADING)] + [f"{v['rule_id']}: " + _violation_text(report, v).replace("\n", "; ")
                                              for v in section["effects"]]
    if section["effects_not_listed"]:
        lines.append(f"... and {plural(section['effects_not_listed'], 'more effect')} not listed")
    for label, latencies in latency_tables(report):
        lines += ["", _x(f"Latency by request, {label}" if label else "Latency by request")]
        lines += [_x(f"  {r['request']}: {plural(r['count'], 'answer')}, p50 {r['p50_ns'] / 1e6:.3f} ms, "
                     f"p99 {r['p99_ns'] / 1e6:.3f} ms, max {r['max_ns'] / 1e6:.3f} ms") for r in latencies]
    return "\n".join(lines)


def _effects_case(suite: ET.Element, report: dict[str, Any], tally: Counter[str]) -> None:
    """The interventions' effects as a case: listed in its system-out; failing,
    one failure each at or above the threshold, only with --fail-on-interventions."""
    section = report["interventions"]
    case = ET.SubElement(suite, "testcase", classname="whiztap.interventions", name="the interventions' effects")
    tally["tests"] += 1
    threshold = Severity.parse(report["severity_threshold"])
    ignored = set(report["ignored_rules"])
    failing = [v for v in section["effects"] if section["fail_on_interventions"] and v["rule_id"] not in ignored
               and Severity.parse(v["severity"]) >= threshold]
    fails = section["fail_on_interventions"] and any(
        n for s, n in section["effects_by_severity"].items() if Severity.parse(s) >= threshold)
    if fails:
        tally["failures"] += 1
        for v in failing:
            ET.SubElement(case, "failure", type=v["severity"], message=_x(v["detail"])).text = \
                _violation_text(report, v)
        if not failing:
            ET.SubElement(case, "failure", type="effect", message="effects of the interventions, not listed")
    texts = [f"{v['rule_id']}: " + _violation_text(report, v) for v in section["effects"] if v not in failing]
    if texts:
        ET.SubElement(case, "system-out").text = "\n\n".join(texts)


def _input_cases(suite: ET.Element, report: dict[str, Any], tally: Counter[str]) -> None:
    """The cases about the inputs: there was traffic to judge; every recording could be read."""
    if report.get("nothing_judged"):
        case = ET.SubElement(suite, "testcase", classname="whiztap.input", name="the recordings hold traffic to judge")
        tally["tests"] += 1
        if not report["passed"]:
            ET.SubElement(case, "failure", type="nothing_judged", message=_x(report["nothing_judged"]))
            tally["failures"] += 1
    if report.get("unreadable"):
        case = ET.SubElement(suite, "testcase", classname="whiztap.input", name="every recording could be read")
        tally["tests"] += 1
        tally["errors"] += 1
        for u in report["unreadable"]:
            ET.SubElement(case, "error", type="unreadable", message=_x(u["error"])).text = _x(u["file"])


def _timestamp(report: dict[str, Any]) -> str:
    """When the recorded traffic began (ISO 8601, UTC), else now."""
    first = report["summary"]["first_ns"]
    t = (datetime.datetime.fromtimestamp(first / 1e9, datetime.UTC) if first is not None
         else datetime.datetime.now(datetime.UTC))
    return t.replace(tzinfo=None).isoformat(timespec="seconds")
