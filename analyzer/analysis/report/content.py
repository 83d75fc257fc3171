"""The report as plain data: what every format renders, and the JSON report."""

from __future__ import annotations

from typing import Any

from whiztap.analyzer import __version__
from whiztap.analyzer.analysis.facts import NS, Analysis, ConnectionSummary, ViolationRecord
from whiztap.analyzer.analysis.verdict import analysis_verdict
from whiztap.analyzer.protocol.checksum import get_rule
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.text import escape

REPORT_SCHEMA_ID = "whiztap.report"
REPORT_VERSION = 1


def build(analysis: Analysis, threshold: Severity = Severity.ERROR, ignore: frozenset[str] = frozenset(),
          unreadable: list[dict[str, str]] | None = None, allow_empty: bool = False,
          group_by: list[tuple[str, ...]] | None = None, fail_on_interventions: bool = False) -> dict[str, Any]:
    """The report as plain data (the JSON format, documented in docs/analyze.md).
    ``unreadable``: {"file", "error"} of the inputs left out because they could
    not be read (the key is there only when there are some).  A report on no
    traffic (``nothing_judged`` says why) does not pass unless ``allow_empty``.
    ``group_by``: the fleet tables' key sets (``fleet``, docs/fleet.md), only when asked.
    ``fail_on_interventions``: the effects of the proxy's interventions fail
    it too.  Whether it passes is ``verdict.verdict_of``'s, the one verdict."""
    counts = {r: n for r, n in analysis.violation_counts.items() if r not in ignore}
    nothing = nothing_judged(analysis)
    verdict = analysis_verdict(analysis, threshold=threshold, ignore=ignore, nothing_judged=nothing,
                               fail_on_interventions=fail_on_interventions, allow_empty=allow_empty)
    start = analysis.first_ns or 0
    listed = listed_violations(analysis, ignore)
    rule = get_rule(analysis.checksum_rule)
    report: dict[str, Any] = {
        "schema": REPORT_SCHEMA_ID,
        "version": REPORT_VERSION,
        "whiztap_version": __version__,
        "spec_revision": "1.8",
        "files": list(analysis.files),
        "checksum_rule": {"name": rule.name, "description": rule.description},
        "severity_threshold": str(threshold),
        "ignored_rules": sorted(ignore),
        "passed": verdict.passed,
        "summary": _summary(analysis, counts),
        "connections": [_connection(c, ignore) for c in analysis.connections],
        "rule_counts": {r: counts[r] for r in RULES if counts.get(r)},
        "violations": [_violation(v, start) for v in listed],
        "violations_not_listed": sum(counts.values()) - len(listed),
        "latency": latency_rows(analysis.latencies),
        "unanswered": dict(sorted(analysis.unanswered.items())),
        "set_configurations": [{
            "file": c.file, "conn": c.conn, "t_ns": c.t_ns, "checksum": c.checksum,
            "expected": c.expected, "ok": c.checksum == c.expected, "satisfies": list(c.satisfies),
        } for c in analysis.set_configs],
        "per_file": _per_file(analysis, ignore),
    }
    if analysis.assumed_channels:
        report["assumed_channels"] = analysis.assumed_channels
    if unreadable:
        report["unreadable"] = list(unreadable)
    if nothing is not None:
        report["nothing_judged"] = nothing
    if analysis.interventions or any(c.middle for c in analysis.connections):
        report["interventions"] = _interventions(analysis, start, fail_on_interventions,
                                                 verdict.effects_by_severity)
        if any(c.middle for c in analysis.connections):
            report["client_latency"] = latency_rows(analysis.client_latencies)
    if group_by:
        from whiztap.analyzer.analysis.fleet import fleet_tables

        report["fleet"] = fleet_tables(analysis, group_by, threshold, ignore)
    return report


def listed_violations(analysis: Analysis, ignore: frozenset[str]) -> list[ViolationRecord]:
    """The violations the report lists, in its order (the HTML report's frame
    view numbers them so)."""
    return [v for v in analysis.violations if v.rule_id not in ignore]


def _summary(analysis: Analysis, counts: dict[str, int]) -> dict[str, Any]:
    """The report's totals; ``counts``: violations by rule, ignored rules left out."""
    by_severity = {str(s): 0 for s in (Severity.ERROR, Severity.WARNING, Severity.INFO)}
    for rule_id, n in counts.items():
        by_severity[str(RULES[rule_id].severity)] += n
    frames_by_kind: dict[str, dict[str, int]] = {"c2s": {}, "s2c": {}}
    for c in analysis.connections:
        for (direction, kind), n in c.frames.items():
            frames_by_kind[direction][kind] = frames_by_kind[direction].get(kind, 0) + n
    return {
        "connections": len(analysis.connections),
        "frames": analysis.frames,
        "first_ns": analysis.first_ns,
        "last_ns": analysis.last_ns,
        "duration_s": round(analysis.duration_s, 6),
        "frames_by_kind": frames_by_kind,
        "violations_by_severity": by_severity,
    }


def _connection(c: ConnectionSummary, ignore: frozenset[str]) -> dict[str, Any]:
    """One connection; one the proxy stood in the middle of also says how
    many changes it made (the key is there only then)."""
    connection = {
        "file": c.file, "conn": c.conn, "client": c.client, "upstream": c.upstream,
        "mode": c.mode, "handshake": c.handshake, "first_ns": c.first_ns, "last_ns": c.last_ns,
        "frames": sum(c.frames.values()),
        "violations": {r: n for r, n in sorted(c.violations.items()) if r not in ignore},
        "channel_map": {str(ch): {"unit_type": cfg.unit_type, "unused": cfg.unused,
                                  "switch_type": cfg.switch_type}
                        for ch, cfg in sorted(c.channel_map.items())},
        "closed_by": c.closed_by, "notes": list(c.notes),
    }
    if c.middle:
        connection["interventions"] = c.interventions
    return connection


def _violation(v: ViolationRecord, start: int) -> dict[str, Any]:
    """One violation; ``t_rel_s`` counts from ``start``, the first traffic;
    ``side``: whose conduct it is about (client or server)."""
    return {
        "rule_id": v.rule_id, "severity": str(v.severity), "section": v.section or RULES[v.rule_id].section,
        "file": v.file, "conn": v.conn, "dir": v.direction, "t_ns": v.t_ns,
        "t_rel_s": round((v.t_ns - start) / NS, 6), "index": v.index,
        "frame": escape(v.raw) + ("…" if v.cut else ""),
        "detail": v.detail,
        "late": v.late,
        "side": v.side,
    }


def latency_rows(latencies: dict) -> list[dict[str, Any]]:
    """Latency statistics by request title, as the report's rows."""
    return [{
        "request": title, "count": s.count, "mean_ns": round(s.mean), "p50_ns": s.percentile(50),
        "p95_ns": s.percentile(95), "p99_ns": s.percentile(99), "max_ns": s.max,
    } for title, s in sorted(latencies.items())]


def _interventions(analysis: Analysis, start: int, fail_on_interventions: bool,
                   by_severity: dict[str, int]) -> dict[str, Any]:
    """What the proxy changed when it stood in the middle: each cause (a
    fault's name and SPEC, a script, a hand edit, an injection) with its
    counts by action, and the effects: violations one side saw that the other
    did not commit (a frame the proxy broke), and what follows directly from
    a frame the proxy made or changed, each with the change it follows from;
    they count against neither side, and fail the report only with
    ``fail_on_interventions``."""
    causes: dict[str, dict[str, int]] = {}
    for (cause, action), n in analysis.interventions.items():
        causes.setdefault(cause, {})[action] = n
    effects = []
    for v in analysis.effects:
        effect = _violation(v, start)
        effect["seen_by"] = effect.pop("side")
        effect["cause"] = v.cause
        effects.append(effect)
    return {
        "count": sum(analysis.interventions.values()),
        "connections": sum(1 for c in analysis.connections if c.middle),
        "causes": [{"cause": cause, "count": sum(actions.values()), "actions": dict(sorted(actions.items()))}
                   for cause, actions in causes.items()],
        "effect_counts": {r: analysis.effect_counts[r] for r in RULES if analysis.effect_counts.get(r)},
        "effects": effects,
        "effects_not_listed": sum(analysis.effect_counts.values()) - len(analysis.effects),
        "effects_by_severity": by_severity,
        "fail_on_interventions": fail_on_interventions,
    }


def nothing_judged(analysis: Analysis) -> str | None:
    """Why the recordings give nothing to judge (None when they do): a gate
    must not go green on a recording of nothing."""
    if not analysis.connections:
        return "no connection in the recording (is it a whiztap recording of traffic?)"
    if all(any(n.startswith("upstream failed") for n in c.notes) for c in analysis.connections):
        return "the server was never reached on any connection"
    return None


def _per_file(analysis: Analysis, ignore: frozenset[str]) -> list[dict[str, Any]]:
    rows: dict[str, dict[str, Any]] = {f: {"file": f, "connections": 0, "frames": 0, "violations": 0}
                                       for f in analysis.files}
    for c in analysis.connections:
        row = rows.setdefault(c.file, {"file": c.file, "connections": 0, "frames": 0, "violations": 0})
        row["connections"] += 1
        row["frames"] += sum(c.frames.values())
        row["violations"] += sum(n for r, n in c.violations.items() if r not in ignore)
    return list(rows.values())
