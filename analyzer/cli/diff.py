"""``whiztap diff A B``: two recordings compared exchange by exchange.

The pairing and the judging are ``analysis.diff``'s; this module reads the
two files (the project's one-line reading errors) and renders the result as
text, JSON, Markdown or HTML.  Exit status 0 when they are equal, 1 when
they differ, 2 when either cannot be read.
"""

from __future__ import annotations

import html
import json
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.analysis.compare import LATENCY_TOLERANCE_MS
from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.reading import one_recording, scan_recording

if TYPE_CHECKING:
    from whiztap.analyzer.analysis.diff import Difference, DiffResult
    from whiztap.analyzer.analysis.exchanges import RecordedSessions

COLUMNS = ("connection", "exchange", "kind", "what", "A", "B", "breaks the spec")


def _load(path: str) -> RecordedSessions:
    """One recording's exchanges, or the one line every reader says about it."""
    from whiztap.analyzer.analysis.exchanges import load_exchanges
    from whiztap.analyzer.recording.scan import RecordingError

    recording = one_recording((path,))
    try:
        return load_exchanges(recording)
    except (OSError, RecordingError):
        for _ in scan_recording(recording):  # read again to the failure: it says why in the readers' words
            pass
        raise
    except KeyError as e:  # a message without a field the format requires
        fail(f"{path}: not a readable recording ({e})")


def _fault(d: Difference) -> str:
    if not d.breaches:
        return "neither"
    return "; ".join(f"{b.recording}'s {b.side or 'side'}: {b.rule_id}" for b in d.breaches)


def _rows(result: DiffResult) -> list[tuple[str, ...]]:
    return [(str(d.connection), d.exchange, d.kind.value, d.what, d.a, d.b, _fault(d)) for d in result.differences]


def _summary(result: DiffResult) -> str:
    from whiztap.analyzer.protocol.text import plural

    if result.equal:
        return f"equal: {plural(result.exchanges, 'exchange')}, no difference"
    counts = ", ".join(f"{n} {kind}" for kind, n in result.counts().items())
    shown = f"; the first {len(result.differences):,} shown" if result.total > len(result.differences) else ""
    return f"{plural(result.total, 'difference')} in {plural(result.exchanges, 'exchange')} ({counts}{shown})"


def render_text(result: DiffResult) -> str:
    lines = [f"A: {result.a}", f"B: {result.b}",
             f"latency tolerance: {result.latency_tolerance_ms:g} ms", _summary(result)]
    for d in result.differences:
        lines.append(f"connection {d.connection}  {d.exchange}: {d.kind.value}: {d.what}")
        if d.a:
            lines.append(f"  A: {d.a}")
        if d.b:
            lines.append(f"  B: {d.b}")
        lines.append(f"  breaks the spec: {_fault(d)}")
    return "\n".join(lines)


def render_json(result: DiffResult) -> str:
    return json.dumps({
        "a": result.a, "b": result.b, "latency_tolerance_ms": result.latency_tolerance_ms,
        "equal": result.equal, "exchanges": result.exchanges, "counts": result.counts(),
        "differences_total": result.total,
        "differences": [{
            "connection": d.connection, "exchange": d.exchange, "kind": d.kind.value, "what": d.what,
            "a": d.a, "b": d.b, "at_fault": d.at_fault,
            "breaches": [{"recording": b.recording, "side": b.side, "rule": b.rule_id, "detail": b.detail}
                         for b in d.breaches],
        } for d in result.differences],
    }, indent=2)


def render_markdown(result: DiffResult) -> str:
    def cell(text: str) -> str:
        return text.replace("|", "\\|").replace("\n", " ")

    lines = ["# whiztap diff", "", f"- A: `{result.a}`", f"- B: `{result.b}`",
             f"- latency tolerance: {result.latency_tolerance_ms:g} ms", f"- {_summary(result)}"]
    if not result.equal:
        lines += ["", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in _rows(result)]
    return "\n".join(lines)


def render_html(result: DiffResult) -> str:
    e = html.escape
    head = "".join(f"<th>{e(c)}</th>" for c in COLUMNS)
    body = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>\n" for row in _rows(result))
    table = f"<table>\n<tr>{head}</tr>\n{body}</table>\n" if body else ""
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>whiztap diff</title></head><body>\n"
            f"<h1>whiztap diff</h1>\n<p>A: <code>{e(result.a)}</code><br>B: <code>{e(result.b)}</code><br>"
            f"latency tolerance: {result.latency_tolerance_ms:g} ms</p>\n<p>{e(_summary(result))}</p>\n"
            f"{table}</body></html>")


RENDER = {"text": render_text, "json": render_json, "markdown": render_markdown, "html": render_html}


@click.command("diff")
@click.argument("a", metavar="A.mcap")
@click.argument("b", metavar="B.mcap")
@click.option("--latency-tolerance", type=click.FloatRange(min=0), default=LATENCY_TOLERANCE_MS,
              show_default=True, metavar="MS", help="Latency differences up to this many milliseconds are equal.")
@click.option("--format", "fmt", type=click.Choice(list(RENDER)), default="text", show_default=True)
@click.option("-o", "--output", type=click.Path(dir_okay=False, allow_dash=True), default=None,
              help="Write the report here instead of standard output.")
@click.option("--force", is_flag=True, help="Write over an existing --output file.")
def diff_command(a: str, b: str, latency_tolerance: float, fmt: str, output: str | None, force: bool) -> None:
    """Compare two recordings exchange by exchange (a request and its
    answer), paired by connection order, message, channel and position, not
    by bytes: what differs (a value, the timing beyond --latency-tolerance,
    missing in B, extra in B, a handshake's outcome) and which recording, if
    either, breaks the spec there.  Exit status 0 when equal, 1 when not."""
    from whiztap.analyzer.analysis.diff import diff_sessions
    from whiztap.analyzer.protocol.text import printable

    check_output(output, (a, b), force=force)
    left, right = _load(a), _load(b)
    result = diff_sessions(left.connections, right.connections, printable(a), printable(b), latency_tolerance)
    with output_stream(output, force) as out:
        out.write(RENDER[fmt](result) + "\n")
    if not result.equal:
        raise SystemExit(1)
