"""Words every rendering of a report shares about the proxy in the middle and
the fleet tables, kept free of any rendering library so that each format
loads only its own."""

from __future__ import annotations

from typing import Any


def side_words(report: dict[str, Any], v: dict[str, Any]) -> str:
    """Whose conduct a violation is about, in words, when the report has
    sides to tell apart (the proxy stood in the middle); else nothing."""
    if "interventions" not in report:
        return ""
    return f" ({v['side']} side)" if "side" in v else f" (seen by the {v['seen_by']}; neither side's doing)"


def intervention_lines(report: dict[str, Any]) -> tuple[str, list[tuple[str, int, str]]]:
    """The interventions section's heading and (cause, count, actions) rows."""
    section = report["interventions"]
    conns = section["connections"]
    heading = (f"The proxy stood in the middle of {conns} connection{'s' * (conns != 1)} "
               f"and made {section['count']} change{'s' * (section['count'] != 1)}; "
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


def rules_since(group: dict[str, Any]) -> str:
    """The rules a group broke, each with its count and the first day it broke:
    ``PW-PAIR-UNANSWERED 12 since 2026-03-02``."""
    return ", ".join(f"{r['rule_id']} {r['count']} since {r['since'] or 'an unknown day'}"
                     for r in group["rules"]) or "none"


def rule_counts_words(counts: dict[str, int]) -> str:
    """``PW-A 2, PW-B 1``; ``-`` for none."""
    return ", ".join(f"{rule_id} {n}" for rule_id, n in counts.items()) or "-"


def fleet_headings(table: dict[str, Any]) -> tuple[str, str]:
    """The titles of a fleet table and of its table by day."""
    key = fleet_key(table)
    return f"Fleet by {key}", f"Violations by {key} and day (UTC; the day each recording began)"
