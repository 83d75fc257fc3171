"""A probe report in each format: ``render(report, fmt)``, shared by ``probe server`` and ``probe client``.

Every format lists the cases grouped by spec section (``ProbeReport.by_section``)
with their verdicts, each failure with its findings and each skip with its
reason:

- ``text``: for a terminal (``colour=True`` colours the verdicts) or a log;
- ``markdown``: a table per section, for a CI job summary or a pull request;
- ``json``: ``ProbeReport.to_json``, the documented shape CI jobs read;
- ``junit``: a ``testcase`` per case, its ``classname`` the spec section, a
  ``failure`` with the findings, a ``skipped`` with the reason;
- ``html``: the interactive page ``analyze`` writes (``report.page``): the
  failures first, then the case index by spec section, sortable and
  filtered by section and verdict; with a recording of the run (the
  ``recording`` argument, else the report's own), each case links to its
  connection's frames, decoded, as the analyzer reads them.

The interface other commands call is ``render`` and ``FORMATS``; nothing here
prints or reads a socket.  A report never holds a password: findings are
made from what the server sent and the probe's own words, and a recording
keeps only a password's length (docs/recording-format.md).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from typing import Any

from whiztap.analyzer.probe.model import CaseResult, Outcome, ProbeReport
from whiztap.analyzer.analysis.frame_context import FrameRow, read_frames
from whiztap.analyzer.analysis.report.page import column, frame_view, page, row, table, text
from whiztap.analyzer.protocol.text import plural

FORMATS = ("text", "json", "junit", "markdown", "html")
_COLOURS = {Outcome.PASS: "32", Outcome.FAIL: "31", Outcome.SKIP: "33"}  # ANSI: green, red, yellow


def render(report: ProbeReport, fmt: str, *, recording: str | None = None, colour: bool = False) -> str:
    """``report`` in format ``fmt`` (one of ``FORMATS``), ending with a line
    break.  ``recording``: the run's recording, whose frames the HTML report
    shows (default: ``report.recording``); it may raise the recording
    reader's ``RecordingError``.  ``colour``: ANSI colours in ``text``."""
    if fmt == "json":
        return json.dumps(report.to_json(), indent=2) + "\n"
    if fmt == "text":
        return "\n".join(_text(report, colour)) + "\n"
    if fmt == "markdown":
        return "\n".join(_markdown(report)) + "\n"
    if fmt == "junit":
        return _junit(report)
    if fmt == "html":
        path = recording if recording is not None else report.recording
        return _html(report, read_frames(path) if path else {})
    raise ValueError(f"unknown format {fmt!r}: expected one of {', '.join(FORMATS)}")


def heading(report: ProbeReport) -> str:
    """What was probed, as one line."""
    mode = f" ({report.mode})" if report.mode else ""
    return f"whiztap probe {report.role} {report.target}{mode}, seed {report.seed}"


def totals(report: ProbeReport) -> str:
    return (f"{report.passed} passed, {report.failed} failed, {report.skipped} skipped "
            f"of {plural(len(report.cases), 'case')} in {report.seconds:.1f} s")


def _paint(text: str, outcome: Outcome, colour: bool) -> str:
    return f"\x1b[{_COLOURS[outcome]}m{text}\x1b[0m" if colour else text


def _text(report: ProbeReport, colour: bool) -> Iterator[str]:
    yield heading(report)
    for section, cases in report.by_section().items():
        yield ""
        yield section
        for case in cases:
            yield f"  {_paint(case.verdict.upper().ljust(4), case.verdict, colour)}  {case.id}  {case.title}"
            for finding in case.findings:
                yield f"        {finding.rule}: {finding.detail}"
            if case.reason:
                yield f"        ({case.reason})"
    yield ""
    if report.recording:
        yield f"recording: {report.recording}"
    verdict = Outcome.FAIL if report.failed else Outcome.PASS
    yield _paint(f"{verdict.upper()}: {totals(report)}", verdict, colour)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _markdown(report: ProbeReport) -> Iterator[str]:
    yield f"# {heading(report)}"
    yield ""
    yield f"**{'FAIL' if report.failed else 'PASS'}**: {totals(report)}"
    for section, cases in report.by_section().items():
        yield ""
        yield f"## {section}"
        yield ""
        yield "| verdict | case | title | findings |"
        yield "|---|---|---|---|"
        for case in cases:
            notes = [f"`{f.rule}` {f.detail}" for f in case.findings] + ([case.reason] if case.reason else [])
            yield (f"| {case.verdict} | `{case.id}` | {_cell(case.title)} | "
                   f"{_cell('<br>'.join(notes))} |")


def _junit(report: ProbeReport) -> str:
    suites = ET.Element("testsuites", name=f"whiztap probe {report.role}")
    suite = ET.SubElement(suites, "testsuite", name=f"whiztap probe {report.role} {report.target}",
                          tests=str(len(report.cases)), failures=str(report.failed), errors="0",
                          skipped=str(report.skipped), time=f"{report.seconds:.3f}")
    for case in report.cases:
        element = ET.SubElement(suite, "testcase", name=case.id, classname=case.spec, time=f"{case.seconds:.3f}")
        if case.verdict is Outcome.FAIL:
            failure = ET.SubElement(element, "failure", message=", ".join(dict.fromkeys(f.rule for f in case.findings)),
                                    type="probe")
            failure.text = "\n".join(f"{f.rule}: {f.detail}" for f in case.findings)
        elif case.verdict is Outcome.SKIP:
            ET.SubElement(element, "skipped", message=case.reason)
    ET.indent(suites)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(suites, encoding="unicode") + "\n"


# -- HTML ---------------------------------------------------------------------------------------------


def _frame_views(report: ProbeReport, frames: dict[int, list[FrameRow]]) -> dict[str, Any]:
    """Each recorded case's connection, for the page's frame view."""
    return {f"conn-{case.conn}": frame_view(f"{case.id}: connection {case.conn}", frames[case.conn])
            for case in report.cases if case.conn is not None and frames.get(case.conn)}


def html_cases(cases: list[CaseResult], views: dict[str, Any], table_id: str = "cases") -> dict[str, Any]:
    """The case index: a row per case (section, verdict, id, title, findings),
    each linked to its connection's frames; shared by probe and fuzz pages."""
    rows = []
    for case in cases:
        notes = [f"{f.rule}: {f.detail}" for f in case.findings] + ([case.reason] if case.reason else [])
        key = f"conn-{case.conn}"
        linked = key in views
        rows.append(row([case.spec, str(case.verdict), case.id, case.title, "; ".join(notes),
                         f"connection {case.conn}" if linked else ""],
                        key if linked else None, anchor=f"case-{case.id}"))
    return table(table_id, [column("section", "spec section"), column("verdict", "verdict", "sev"),
                            column("case", "case", "code"), column("title", "title"),
                            column("findings", "findings"), column("frames", "frames", "frames")],
                 rows, ("section", "verdict"))


def _html(report: ProbeReport, frames: dict[int, list[FrameRow]]) -> str:
    views = _frame_views(report, frames)
    failed = [c for c in report.cases if c.verdict is Outcome.FAIL]
    sections: list[dict[str, Any]] = []
    if failed:
        sections.append({"id": "failures", "title": "Failures", "table": html_cases(failed, views, "failures")})
    sections.append({"id": "index", "title": "Cases by spec section", "table": html_cases(
        [c for cases in report.by_section().values() for c in cases], views)})
    lines = [text(f"Recording: {report.recording}" if report.recording else "Not recorded (--record keeps the "
                  "frames, and links each case to them).", "note")]
    return page(heading(report), {"heading": heading(report),
                                  "verdict": {"passed": not report.failed,
                                              "text": f"{'FAIL' if report.failed else 'PASS'}: {totals(report)}"},
                                  "lines": lines, "sections": sections, "frames": views})
