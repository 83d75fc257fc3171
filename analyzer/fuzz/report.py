"""``whiztap fuzz server --format html``: the fuzz run on the page every
HTML report uses (``analysis.report.page``).

The findings first, each with its minimal session one click away: the
frames of its recording (``finding-N.mcap``), decoded and judged as
``analyze`` judges them.  Takes the run's JSON (``FuzzReport.to_json``), so
the analyzer needs nothing of the sniffer that ran it."""

from __future__ import annotations

from typing import Any

from whiztap.analyzer.analysis.frame_context import FrameRow
from whiztap.analyzer.analysis.report.page import column, frame_view, page, row, table, text
from whiztap.analyzer.protocol.text import plural


def heading(run: dict[str, Any]) -> str:
    return f"whiztap fuzz server {run['target']} ({run['mode'] or 'mode unknown'}), seed {run['seed']}"


def render_html(run: dict[str, Any], sessions: dict[str, list[FrameRow]]) -> str:
    """The page for a run; ``sessions``: each finding's frames by finding id
    (read from its recording; a finding without them links to nothing)."""
    findings = run["findings"]
    views = {f"finding-{fid}": frame_view(f"{fid}: its minimal session", rows) for fid, rows in sessions.items()}
    rows = [row([f["id"], f["kind"], f["rule"] or "", f["frames"], "yes" if f["shrunk"] else "no", f["detail"],
                 f["recording"], f["test"], "session" if f"finding-{f['id']}" in views else ""],
                f"finding-{f['id']}" if f"finding-{f['id']}" in views else None, anchor=f"finding-{f['id']}")
            for f in findings]
    columns = [column("id", "finding", "code"), column("kind", "kind"), column("rule", "rule", "rule"),
               column("frames", "frames", "num"), column("shrunk", "shrunk"), column("detail", "detail"),
               column("recording", "recording", "code"), column("test", "regression test", "code"),
               column("session", "minimal session", "frames")]
    listed = table("findings", columns, rows, ("kind", "rule")) if findings else None
    sections: list[dict[str, Any]] = [{"id": "findings", "title": "Findings", "table": listed,
                                       "paragraphs": [] if findings else [text("None.")]}]
    summary = (f"{plural(run['executions'], 'execution')} (and {run['shrink_executions']} shrinking), stopped by "
               f"{run['stopped']}")
    verdict = f"{'FAIL' if findings else 'PASS'}: {plural(len(findings), 'finding')}"
    return page(heading(run), {"heading": heading(run), "verdict": {"passed": not findings, "text": verdict},
                               "lines": [text(summary + ".")], "sections": sections, "frames": views})
