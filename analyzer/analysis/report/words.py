"""Words every rendering of a report shares about the proxy in the middle and
the fleet tables, kept free of any rendering library so that each format
loads only its own."""

from __future__ import annotations

from typing import Any

from whiztap.analyzer.analysis.verdict import counts_words
from whiztap.analyzer.protocol.text import plural


def assumed_words(report: dict[str, Any]) -> str | None:
    """The sentence every format gives when a stated channel map judged a
    connection that never heard the server's own (docs/analyze.md)."""
    spec = report.get("assumed_channels")
    if not spec:
        return None
    return f"Channel map assumed where the server never announced one: --channels {spec}"


def side_words(report: dict[str, Any], v: dict[str, Any]) -> str:
    """Whose conduct a violation is about, in words, when the report has
    sides to tell apart (the proxy stood in the middle); else nothing."""
    if "interventions" not in report:
        return ""
    if "side" in v:
        return f" ({v['side']} side)"
    cause = f"; follows from {v['cause']}" if v.get("cause") else ""
    return f" (seen by the {v['seen_by']}; neither side's doing{cause})"


def side_cell(v: dict[str, Any]) -> str:
    """A violation's side, or an effect's viewer and cause, for a table's side column."""
    if v.get("side"):
        return v["side"]
    return f"seen by the {v['seen_by']}" + (f"; follows from {v['cause']}" if v.get("cause") else "")


def several_files(report: dict[str, Any]) -> bool:
    """Whether the report covers more than one recording: then connection
    numbers repeat (each file counts from 1), and each is named with its file."""
    return len(report["files"]) > 1


def conn_words(report: dict[str, Any], item: dict[str, Any]) -> str:
    """``conn 3``, or ``r7.mcap conn 3`` when the report covers several files."""
    return f"{item['file']} conn {item['conn']}" if several_files(report) else f"conn {item['conn']}"


SERVER_LATENCY = "the server's: from the request as it received it to the answer it sent"
CLIENT_LATENCY = "the client's: from the request as it sent it to the answer as it received it"


def latency_tables(report: dict[str, Any]) -> list[tuple[str, list[dict[str, Any]]]]:
    """(label, rows) of each latency table: one, unlabelled, unless the proxy
    stood in the middle, when the server's and the client's differ and each is
    named ('' when there is no row at all)."""
    if "client_latency" not in report:
        return [("", report["latency"])] if report["latency"] else []
    return [(SERVER_LATENCY, report["latency"]), (CLIENT_LATENCY, report["client_latency"])]


def verdict_words(report: dict[str, Any]) -> str:
    """The verdict line every rendering ends with (or begins with)."""
    sev = report["summary"]["violations_by_severity"]
    section = report.get("interventions")
    counts = counts_words(sev, sum(section["effects_by_severity"].values()) if section else 0)
    threshold = report["severity_threshold"]
    above = [s for s in ("error", "warning", "info") if _LEVEL[s] >= _LEVEL[threshold]]
    if report["passed"]:
        text = f"PASS: no violation at or above {threshold} ({counts})"
    elif section and section["fail_on_interventions"] and not any(sev[s] for s in above) \
            and any(section["effects_by_severity"][s] for s in above):
        text = f"FAIL: effects of the interventions at or above {threshold}, --fail-on-interventions ({counts})"
    else:
        text = f"FAIL: violations at or above {threshold} ({counts})"
    if report.get("nothing_judged"):
        allowed = " (allowed by --allow-empty)" if report["passed"] else ""
        text = f"NOTHING TO JUDGE: {report['nothing_judged']}{allowed}"
    unreadable = len(report.get("unreadable", ()))
    if unreadable:
        text = f"INCOMPLETE: {plural(unreadable, 'input')} could not be read. {text}"
    return text


_LEVEL = {"info": 1, "warning": 2, "error": 3}


def intervention_lines(report: dict[str, Any]) -> tuple[str, list[tuple[str, int, str]]]:
    """The interventions section's heading and (cause, count, actions) rows."""
    section = report["interventions"]
    conns = section["connections"]
    heading = (f"The proxy stood in the middle of {plural(conns, 'connection')} "
               f"and made {plural(section['count'], 'change')}; "
               "each side is judged by what it sent and what it received")
    rows = [(c["cause"], c["count"], ", ".join(f"{action} {n}" for action, n in c["actions"].items()))
            for c in section["causes"]]
    return heading, rows


EFFECTS_HEADING = "Effects of the interventions: what one side saw that the other side did not do (no side's violation)"


# -- the fleet tables (docs/fleet.md) -----------------------------------------------------------


def fleet_key(table: dict[str, Any]) -> str:
    """What a fleet table groups by: ``robot``, ``robot / firmware``."""
    return " / ".join(table["group_by"])


def group_name(table: dict[str, Any], group: dict[str, Any]) -> str:
    """A group's values as a person reads them: ``r7 / 2.3``; ``(none)`` for a
    recording without the key."""
    return " / ".join("(none)" if group["group"][k] is None else str(group["group"][k]) for k in table["group_by"])


def rules_since_each(group: dict[str, Any]) -> list[str]:
    """Each rule a group broke, with its count and the first day it broke:
    ``PW-PAIR-UNANSWERED 12 since 2026-03-02``."""
    return [f"{r['rule_id']} {r['count']:,} since {r['since'] or 'an unknown day'}" for r in group["rules"]]


def rules_since(group: dict[str, Any]) -> str:
    """``rules_since_each`` in one line; ``none`` for none."""
    return ", ".join(rules_since_each(group)) or "none"


def rule_counts_each(counts: dict[str, int]) -> list[str]:
    """``PW-A 2``, ``PW-B 1``: each rule and its count."""
    return [f"{rule_id} {n:,}" for rule_id, n in counts.items()]


def rule_counts_words(counts: dict[str, int]) -> str:
    """``PW-A 2, PW-B 1``; ``-`` for none."""
    return ", ".join(rule_counts_each(counts)) or "-"


def fleet_headings(table: dict[str, Any]) -> tuple[str, str]:
    """The titles of a fleet table and of its table by day."""
    key = fleet_key(table)
    return f"Fleet by {key}", f"Violations by {key} and day (UTC; the day each recording began)"
