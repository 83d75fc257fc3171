"""Words every rendering of a report shares about the proxy in the middle,
kept free of any rendering library so that each format loads only its own."""

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
