"""A probe report in each format: ``render(report, fmt)``, shared by ``probe server`` and ``probe client``.

Every format lists the cases grouped by spec section (``ProbeReport.by_section``)
with their verdicts, each failure with its findings and each skip with its
reason:

- ``text``: for a terminal (``colour=True`` colours the verdicts) or a log;
- ``markdown``: a table per section, for a CI job summary or a pull request;
- ``json``: ``ProbeReport.to_json``, the documented shape CI jobs read;
- ``junit``: a ``testcase`` per case, its ``classname`` the spec section, a
  ``failure`` with the findings, a ``skipped`` with the reason;
- ``html``: one self-contained file; with a recording of the run (the
  ``recording`` argument, else the report's own), each case links to its
  connection's frames, decoded, as the analyzer reads them.

The interface other commands call is ``render`` and ``FORMATS``; nothing here
prints or reads a socket.  A report never holds a password: findings are
made from what the server sent and the probe's own words, and a recording
keeps only a password's length (docs/recording-format.md).
"""

from __future__ import annotations

import html
import json
import xml.etree.ElementTree as ET
from collections.abc import Iterator

from whiztap.analyzer.probe.model import CaseResult, Outcome, ProbeReport
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.text import escape, plural

FORMATS = ("text", "json", "junit", "markdown", "html")
FRAME_SHOWN = 120  # characters of a frame's bytes shown in the HTML report
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

FrameRow = tuple[str, str, str, list[str]]  # direction, bytes as escaped text, meaning, violations


def read_frames(path: str) -> dict[int, list[FrameRow]]:
    """Every connection's items in a recording, decoded and judged by the
    analyzer's session, by connection number."""
    from whiztap.analyzer.protocol.session import Session
    from whiztap.analyzer.recording.sets import find_one, scan_set
    from whiztap.analyzer.traffic import Traffic

    traffic = Traffic(Session)
    frames: dict[int, list[FrameRow]] = {}

    def add(conn: int, events: list) -> None:
        for event in events:
            if isinstance(event, Observation):
                text = escape(event.item.raw)
                if len(text) > FRAME_SHOWN:
                    text = f"{text[:FRAME_SHOWN]}... ({plural(len(event.item.raw), 'byte')})"
                broken = [f"{v.rule_id}: {v.detail}" for v in event.violations]
                frames.setdefault(conn, []).append((str(event.direction), text, meaning(event), broken))

    for event in scan_set(find_one([path])):
        add(event.conn, traffic.receive(event))
    for conn, events in traffic.finish():
        add(conn, events)
    return frames


_STYLE = """body{font-family:sans-serif;margin:2em;color:#222}table{border-collapse:collapse;width:100%}
td,th{border:1px solid #ccc;padding:4px 8px;text-align:left;vertical-align:top}
.pass{color:#1a7f37}.fail{color:#c62828;font-weight:bold}.skip{color:#9a6700}code{font-size:90%}
.frames td{font-family:monospace;font-size:85%}.c2s{background:#f3f8ff}.s2c{background:#f6fff3}"""


def _case_row(case: CaseResult, linked: bool) -> str:
    e = html.escape
    notes = [f"<code>{e(f.rule)}</code> {e(f.detail)}" for f in case.findings]
    notes += [e(case.reason)] if case.reason else []
    frames = f' <a href="#conn-{case.conn}">frames (connection {case.conn})</a>' if linked else ""
    return (f'<tr id="case-{e(case.id)}"><td class="{case.verdict}">{case.verdict}</td><td><code>{e(case.id)}</code>'
            f"{frames}</td><td>{e(case.title)}</td><td>{'<br>'.join(notes)}</td></tr>")


def _frames_table(conn: int, rows: list[FrameRow], cases: list[CaseResult]) -> str:
    e = html.escape
    which = ", ".join(f'<a href="#case-{e(c.id)}"><code>{e(c.id)}</code></a>' for c in cases)
    body = "".join(f'<tr class="{d}"><td>{d}</td><td>{e(raw)}</td><td>{e(what)}</td><td>{e("; ".join(vs))}</td></tr>'
                   for d, raw, what, vs in rows)
    return (f'<h3 id="conn-{conn}">Connection {conn} ({which})</h3><table class="frames">'
            f"<tr><th>dir</th><th>bytes</th><th>meaning</th><th>rules broken</th></tr>{body}</table>")


def _html(report: ProbeReport, frames: dict[int, list[FrameRow]]) -> str:
    e = html.escape
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(heading(report))}</title>"
             f"<style>{_STYLE}</style></head><body><h1>{e(heading(report))}</h1>",
             f"<p class='{'fail' if report.failed else 'pass'}'>{e(totals(report))}</p>"]
    for section, cases in report.by_section().items():
        parts.append(f"<h2>{e(section)}</h2><table><tr><th>verdict</th><th>case</th><th>title</th><th>findings</th></tr>")
        parts += [_case_row(case, case.conn is not None and case.conn in frames) for case in cases]
        parts.append("</table>")
    if frames:
        by_conn: dict[int, list[CaseResult]] = {}
        for case in report.cases:
            if case.conn is not None:
                by_conn.setdefault(case.conn, []).append(case)
        parts.append(f"<h2>Frames</h2><p>From {e(report.recording or 'the recording')}, decoded.</p>")
        parts += [_frames_table(conn, frames[conn], by_conn[conn]) for conn in sorted(by_conn) if conn in frames]
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
