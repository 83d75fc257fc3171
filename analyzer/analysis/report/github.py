"""GitHub Actions workflow commands: one annotation line per violation, shown
on the run's page and, for a file that is in the repository, beside it.

``::error`` / ``::warning`` / ``::notice`` by the rule's severity, the rule
and its spec section as the title, the detail, frame and place as the
message.  An intervention's effect is a notice titled as an effect, unless
``--fail-on-interventions`` makes it count (then its rule's command).  At
most ``MAX_ANNOTATIONS`` such lines: GitHub keeps fifty annotations a job
(and ten errors, ten warnings and ten notices a step; the rest stay in the
log only), and a log of thousands helps no one.  Past them one notice counts
what was left out, by severity; a last line gives the verdict and the
headline as the text report words them.  Values are escaped as the runner
reads them back (``%``, CR and LF in the message; also ``:`` and ``,`` in a
property), after ``printable``, so no value from a recording ends a line or
a property.
"""

from __future__ import annotations

from typing import Any

from whiztap.analyzer.analysis.report.text import headline, verdict
from whiztap.analyzer.analysis.report.words import side_words
from whiztap.analyzer.analysis.verdict import counts_words
from whiztap.analyzer.protocol.text import plural, printable

MAX_ANNOTATIONS = 50
COMMANDS = {"error": "error", "warning": "warning", "info": "notice"}
FRAME_IN_MESSAGE = 160  # characters of the frame a message quotes
EFFECT = "effect of an intervention"


def escape_data(text: str) -> str:
    """A workflow command's message, as the runner reads it back."""
    return text.replace("%", "%25").replace("\r", "%0D").replace("\n", "%0A")


def escape_property(text: str) -> str:
    """A workflow command's property value (file=, title=): a ':' would end
    the properties, a ',' the value."""
    return escape_data(text).replace(":", "%3A").replace(",", "%2C")


def _line(report: dict[str, Any], v: dict[str, Any], command: str, effect: bool) -> str:
    title = f"{v['rule_id']} ({v['section']})" + (f" {EFFECT}" if effect else "")
    index = f", item {v['index']}" if v.get("index", -1) >= 0 else ""
    where = f"conn {v['conn']}, {v['dir'] or 'both'}{index}, +{v['t_rel_s']:.6f} s"
    frame = v["frame"] if len(v["frame"]) <= FRAME_IN_MESSAGE else v["frame"][:FRAME_IN_MESSAGE] + "…"
    message = printable(f"{v['detail']}: {frame} [{where}]{side_words(report, v)}")
    return (f"::{command} file={escape_property(printable(v['file']))},"
            f"title={escape_property(printable(title))}::{escape_data(message)}")


def _entries(report: dict[str, Any]) -> list[tuple[dict[str, Any], str, bool]]:
    """(violation or effect, command, is an effect), violations first."""
    entries = [(v, COMMANDS[v["severity"]], False) for v in report["violations"]]
    section = report.get("interventions")
    if section is not None:
        ignored = set(report["ignored_rules"])
        entries += [(v, COMMANDS[v["severity"]] if section["fail_on_interventions"] and v["rule_id"] not in ignored
                     else "notice", True) for v in section["effects"]]
    return entries


def _left_out(report: dict[str, Any], left: list[tuple[dict[str, Any], str, bool]]) -> str:
    """The words of the notice on what has no line: past the cap, by
    severity, and what the report itself counted without listing."""
    said = []
    if left:
        by_severity = {"error": 0, "warning": 0, "info": 0}
        for v, _, effect in left:
            if not effect:
                by_severity[v["severity"]] += 1
        effects = sum(1 for _, _, effect in left if effect)
        said.append(f"{plural(len(left), 'more annotation')} not shown ({counts_words(by_severity, effects)})")
    if report["violations_not_listed"]:
        said.append(f"{plural(report['violations_not_listed'], 'more violation')} counted but not listed")
    section = report.get("interventions")
    if section is not None and section["effects_not_listed"]:
        said.append(f"{plural(section['effects_not_listed'], 'more effect')} of the interventions "
                    "counted but not listed")
    return "; ".join(said)


def render_github(report: dict[str, Any]) -> str:
    """The annotation lines of ``report``, the notice on the rest, then the verdict."""
    entries = _entries(report)
    lines = [_line(report, v, command, effect) for v, command, effect in entries[:MAX_ANNOTATIONS]]
    more = _left_out(report, entries[MAX_ANNOTATIONS:])
    if more:
        lines.append(f"::notice title=whiztap::{escape_data(more + ' (every listed one: --format json or html)')}")
    outcome = "notice" if report["passed"] else "error"
    said = printable(f"{verdict(report)} ({headline(report)})")
    lines.append(f"::{outcome} title=whiztap verdict::{escape_data(said)}")
    return "\n".join(lines) + "\n"
