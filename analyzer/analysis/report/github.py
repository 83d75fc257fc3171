"""GitHub Actions workflow commands: one annotation line per violation, shown
inline on the run's page and, with a file that is in the repository, beside it.

``::error`` / ``::warning`` / ``::notice`` by the rule's severity (an
intervention's effect is a notice unless ``--fail-on-interventions``), the
rule and its spec section as the title, the detail and the frame as the
message.  At most ``MAX_ANNOTATIONS`` lines: GitHub shows only ten errors
and ten warnings a step (fifty a job), and a log of thousands helps no one;
past it, one notice counts what was left out.  A last line gives the
verdict.  Values are escaped as the runner requires (``%``, CR and LF in
the message; also ``:`` and ``,`` in a property), after ``printable``.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from whiztap.analyzer.analysis.report.text import headline, verdict
from whiztap.analyzer.protocol.text import plural, printable

MAX_ANNOTATIONS = 50
COMMANDS = {"error": "error", "warning": "warning", "info": "notice"}


def escape_data(text: str) -> str:
    """A workflow command's message, as the runner reads it back."""
    return text.replace("%", "%25").replace("\r", "%0D").replace("\n", "%0A")


def escape_property(text: str) -> str:
    """A workflow command's property value (file=, title=)."""
    return escape_data(text).replace(":", "%3A").replace(",", "%2C")


def _line(v: dict[str, Any], command: str, effect: bool) -> str:
    title = f"{v['rule_id']} ({v['section']})" + (" effect of an intervention" if effect else "")
    where = f"conn {v['conn']}, {v['dir'] or 'both'}, item {v.get('index', -1)}, t {v['t_rel_s']:.6f} s"
    message = printable(f"{v['detail']}: {v['frame'][:160]} [{where}]")
    return (f"::{command} file={escape_property(printable(v['file']))},"
            f"title={escape_property(printable(title))}::{escape_data(message)}")


def render_github(report: dict[str, Any]) -> str:
    """The annotation lines of ``report``, then the verdict."""
    entries = [(v, COMMANDS[v["severity"]], False) for v in report["violations"]]
    section = report.get("interventions")
    if section is not None:
        failing = section["fail_on_interventions"]
        entries += [(v, COMMANDS[v["severity"]] if failing else "notice", True) for v in section["effects"]]
    lines = [_line(v, command, effect) for v, command, effect in entries[:MAX_ANNOTATIONS]]
    left = Counter(command for _, command, _ in entries[MAX_ANNOTATIONS:])
    unlisted = report["violations_not_listed"]
    if left or unlisted:
        counts = ", ".join(plural(n, f"{command} annotation") for command, n in sorted(left.items()))
        more = f"left out: {counts}" if counts else ""
        if unlisted:
            more = "; ".join(filter(None, (more, f"{plural(unlisted, 'more violation')} counted but not listed")))
        lines.append(f"::notice title=whiztap::{escape_data(more + ' (the full report: --format html or json)')}")
    outcome = "notice" if report["passed"] else "error"
    said = printable(f"{verdict(report)} ({headline(report)})")
    lines.append(f"::{outcome} title=whiztap verdict::{escape_data(said)}")
    return "\n".join(lines) + "\n"
