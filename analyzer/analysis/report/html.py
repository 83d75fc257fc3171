"""The conformance report as one interactive, self-contained HTML page.

The verdict and the violations come first, for the CI reader who came for
them: a table that sorts and filters (rule, severity, connection, side,
file), each row linked to its frames in the frame view (the items around it
on its connection, decoded, with their bytes and spec sections:
``frame_context``).  Then the interventions and their effects, the plots
(uPlot, drawn by the page itself: no extra to install), connections,
latency, checksums, and a section per file or fleet group.  ``page`` writes
the shell; this module only shapes the report's values for it.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from whiztap.analyzer.analysis.facts import NS, Analysis
from whiztap.analyzer.analysis.frame_context import AROUND, Hits, Views
from whiztap.analyzer.analysis.report.page import column, frame_view, page, row, table, text
from whiztap.analyzer.analysis.report.text import FLEET_COLUMNS, FLEET_DAY_COLUMNS, duration, fleet_rows, headline
from whiztap.analyzer.analysis.report.text import verdict as verdict_words
from whiztap.analyzer.analysis.report.words import (
    CLIENT_LATENCY,
    EFFECTS_HEADING,
    SERVER_LATENCY,
    assumed_words,
    fleet_headings,
    fleet_key,
    group_name,
    intervention_lines,
    latency_tables,
    several_files,
    side_cell,
)
from whiztap.analyzer.protocol.text import plural, printable



_SEVERITY_COLOURS = {"error": "#cf222e", "warning": "#bf8700", "info": "#0969da"}


def _view_key(file: str, conn: int) -> str:
    return f"{file}#{conn}"


def _violations_table(table_id: str, report: dict[str, Any], violations: list[dict[str, Any]],
                      hits: Hits) -> dict[str, Any]:
    files = several_files(report)
    middle = "interventions" in report
    columns = [column("rule", "rule", "rule"), column("severity", "severity", "sev"), column("section", "section")]
    columns += [column("file", "file")] if files else []
    columns += [column("conn", "conn", "num")] + ([column("side", "side")] if middle else [])
    columns += [column("t", "t (s)", "num"), column("frame", "frame", "code"), column("detail", "detail"),
                column("frames", "frames", "frames")]
    rows = []
    for number, v in enumerate(violations):
        cells = [v["rule_id"], v["severity"], v["section"]] + ([v["file"]] if files else []) + [v["conn"]]
        cells += [side_cell(v)] if middle else []
        cells += [v["t_rel_s"], printable(v["frame"][:200]), printable(v["detail"])]
        hit = hits.get(number)
        cells.append("frames" if hit else "")
        rows.append(row(cells, _view_key(*hit[0]) if hit else None, hit[1] if hit else -1,
                        anchor=f"{table_id}-{number}"))
    filters = ("rule", "severity", "conn") + (("side",) if middle else ()) + (("file",) if files else ())
    return table(table_id, columns, rows, filters)


PLOT_BINS = 2_000  # at most this many bins on a plot of counts over time


def _counts_plot(plot_id: str, title: str, what: str, counts: dict[str, Counter],
                 colours: dict[str, str] | None = None) -> dict[str, Any]:
    """Counts per second (from 0) as a plot with every bin drawn, empty ones
    at 0, so that a line never bridges a quiet stretch; seconds are grouped
    into bins of several when the span has more than ``PLOT_BINS``."""
    span = max((s for c in counts.values() for s in c), default=0) + 1
    width = -(-span // PLOT_BINS)
    unit = "second" if width == 1 else f"{width} s"
    series = []
    for label, by_second in counts.items():
        bins: Counter = Counter()
        for second, n in by_second.items():
            bins[second // width] += n
        series.append({"label": label, "color": (colours or {}).get(label),
                       "points": [[b * width, bins.get(b, 0)] for b in range(-(-span // width))]})
    return {"id": plot_id, "title": title, "x_label": "seconds from start", "y_label": f"{what} per {unit}",
            "series": series}


def _plots(analysis: Analysis, report: dict[str, Any]) -> list[dict[str, Any]]:
    """Each plot's series as points: what the page draws with uPlot."""
    start = analysis.first_ns or 0
    plots = []
    kinds = sorted({k for c in analysis.frames_per_second.values() for k in c})
    if kinds:
        first = start // NS
        plots.append(_counts_plot("items", "Items over time, by kind", "items", {
            kind: Counter({s - first: n for s, c in analysis.frames_per_second.items() if (n := c.get(kind, 0))})
            for kind in kinds}))
    if report["violations"]:
        per_second: dict[str, Counter] = {}
        for v in report["violations"]:
            per_second.setdefault(v["severity"], Counter())[int(v["t_rel_s"])] += 1
        plots.append(_counts_plot("violations", "Violations over time (those listed), by severity", "violations",
                                  dict(sorted(per_second.items())), _SEVERITY_COLOURS))
    both = bool(analysis.client_latencies)
    for latencies, title, plot_id in (
            (analysis.latencies, f"Response latency, {SERVER_LATENCY}" if both else "Response latency", "latency"),
            (analysis.client_latencies, f"Response latency, {CLIENT_LATENCY}", "client-latency")):
        if latencies:
            plots.append({"id": plot_id, "title": title, "x_label": "latency (ms)", "y_label": "responses",
                          "x_log": True, "step": True, "series": [
                              {"label": request, "points": [[round((lo + hi) / 2 / 1e6, 6), n]
                                                            for lo, hi, n in stats.histogram()]}
                              for request, stats in sorted(latencies.items())]})
    for kind, label in (("sensor", "Sensor values"), ("servo", "Servo positions (data / 4)")):
        series = [(ch, s) for (k, ch), s in sorted(analysis.values.items()) if k == kind]
        if series:
            plots.append({"id": kind, "title": f"{label} per channel", "x_label": "seconds from start",
                          "y_label": label.lower(), "series": [
                              {"label": f"ch {ch}", "points": [[round((t - start) / NS, 6), v] for t, v in s.points]}
                              for ch, s in series]})
    return plots


def _frames(views: Views, start: int) -> dict[str, Any]:
    return {_view_key(file, conn): frame_view(f"{file} · connection {conn}",
                                              [frames.rows[i] for i in sorted(frames.rows)], start)
            for (file, conn), frames in views.items()}


def _interventions(report: dict[str, Any], hits: Hits) -> dict[str, Any]:
    """The causes, and the effects (numbered after the violations in ``hits``)."""
    heading, rows = intervention_lines(report)
    listed = len(report["violations"])
    section: dict[str, Any] = {"id": "interventions", "title": "Interventions", "paragraphs": [text(heading + ".")]}
    if rows:
        section["table"] = table("causes", [column("cause", "cause", "code"), column("count", "count", "num"),
                                            column("actions", "actions")],
                                 [row([c, n, a]) for c, n, a in rows])
    effects = report["interventions"]
    if effects["effects"]:
        after = [text(f"… and {plural(effects['effects_not_listed'], 'more effect')} not listed.")] \
            if effects["effects_not_listed"] else []
        section["sections"] = [{"id": "effects", "title": EFFECTS_HEADING,
                                "table": _violations_table("effects", report, effects["effects"], {
                                    n - listed: hit for n, hit in hits.items() if n >= listed}),
                                "after": after}]
    return section


def _fleet(table_data: dict[str, Any], n: int) -> dict[str, Any]:
    title, by_day = fleet_headings(table_data)
    key = fleet_key(table_data)
    groups, days = fleet_rows(table_data, lambda entries, empty: "; ".join(entries) or empty)
    numeric = {"recordings", "connections", "violations", "errors", "warnings"}
    head = [column("group", key)] + [column(c, c, "num" if c in numeric else "text") for c in FLEET_COLUMNS]
    day_head = [column("group", key)] + [column(c, c, "num" if c in numeric else "text") for c in FLEET_DAY_COLUMNS]
    subsections: list[dict[str, Any]] = []
    for g in table_data["groups"]:
        rules = ", ".join(f"{r['rule_id']} × {r['count']}" for r in g["rules"]) or "none"
        name = printable(f"{key} {group_name(table_data, g)}")
        subsections.append({"id": f"fleet{n}-{len(subsections)}", "title": name,
                            "paragraphs": [text(f"{plural(g['recordings'], 'recording')}, "
                                                f"{plural(g['violations'], 'violation')}: {rules}; "
                                                f"{'passes' if g['passed'] else 'FAILS'}.",
                                                None if g["passed"] else "warning")]})
    return {"id": f"fleet{n}", "title": title, "table": table(f"fleet{n}", head, [row(r) for r in groups],
                                                              ("verdict",)),
            "sections": [{"id": f"fleet{n}-days", "title": by_day,
                          "table": table(f"fleet{n}-days", day_head, [row(r) for r in days], ("group",))},
                         *subsections]}


def _files(report: dict[str, Any]) -> dict[str, Any]:
    """A section per recording: its counts and its violations by rule."""
    by_file: dict[str, Counter] = {}
    for c in report["connections"]:
        by_file.setdefault(c["file"], Counter()).update(c["violations"])
    subsections = []
    for i, f in enumerate(report["per_file"]):
        counts = by_file.get(f["file"], Counter())
        rules = ", ".join(f"{r} × {n}" for r, n in counts.most_common()) or "none"
        subsections.append({"id": f"file-{i}", "title": printable(f["file"]), "paragraphs": [
            text(f"{plural(f['connections'], 'connection')}, {plural(f['frames'], 'item')}, "
                 f"{plural(f['violations'], 'violation')}: {rules}.")]})
    return {"id": "files", "title": "Files", "sections": subsections}


def _tables(report: dict[str, Any]) -> list[dict[str, Any]]:
    """The sections after the plots: connections, latency, unanswered
    requests, checksums, files that could not be read."""
    sections: list[dict[str, Any]] = []
    sections.append({"id": "connections", "title": "Connections", "table": table(
        "connections", [column("file", "file"), column("conn", "conn", "num"), column("client", "client"),
                        column("mode", "mode"), column("handshake", "handshake"), column("items", "items", "num"),
                        column("violations", "violations", "num")],
        [row([c["file"], c["conn"], c["client"] or "-", c["mode"], c["handshake"], c["frames"],
              sum(c["violations"].values())]) for c in report["connections"]], ("file", "mode", "handshake"))})
    for label, rows in latency_tables(report):
        sections.append({"id": "latency" if not label else f"latency-{len(sections)}",
                         "title": f"Latency, {label}" if label else "Latency", "table": table(
                             f"latency-{len(sections)}", [column("request", "request"), column("count", "count", "num"),
                                                          column("p50", "p50"), column("p95", "p95"),
                                                          column("p99", "p99"), column("max", "max")],
                             [row([r["request"], r["count"], duration(r["p50_ns"]), duration(r["p95_ns"]),
                                   duration(r["p99_ns"]), duration(r["max_ns"])]) for r in rows])})
    if report["unanswered"]:
        sections.append({"id": "unanswered", "title": "Never answered", "paragraphs": [text(", ".join(
            f"{n} × {t}" for t, n in report["unanswered"].items()))]})
    if report["set_configurations"]:
        sections.append({"id": "checksums", "title": "Set Configuration checksums", "table": table(
            "checksums", [column("file", "file"), column("conn", "conn", "num"), column("checksum", "checksum", "num"),
                          column("expected", "expected", "num"), column("fits", "candidate rules it fits")],
            [row([c["file"], c["conn"], c["checksum"], c["expected"], ", ".join(c["satisfies"]) or "none"])
             for c in report["set_configurations"]])})
    if report.get("unreadable"):
        sections.append({"id": "unreadable", "title": "Not in this report (could not be read)",
                         "paragraphs": [text(u["error"], "warning") for u in report["unreadable"]]})
    return sections


def render_html(report: dict[str, Any], analysis: Analysis, views: Views | None = None,
                hits: Hits | None = None) -> str:
    """The page.  ``views``/``hits`` (``frame_context``): the frames kept and,
    by number (``report["violations"]``, then the interventions' effects),
    its view and item; without them nothing links to frames."""
    hits = hits or {}
    rule = report["checksum_rule"]
    lines = [text(f"{headline(report)}. Spec Rev {report['spec_revision']}; checksum rule {rule['name']} "
                  f"({rule['description']}).")]
    assumed = assumed_words(report)
    if assumed:
        lines.append(text(assumed + ".", "warning"))
    sections: list[dict[str, Any]] = []
    listed = report["violations"]
    more = [text(f"… and {report['violations_not_listed']:,} more not listed (the first "
                 f"{len(listed):,} are, with the frames around each).")] if report["violations_not_listed"] else []
    sections.append({"id": "violations", "title": "Violations",
                     "paragraphs": [] if listed else [text("None.")],
                     "table": _violations_table("violations", report, listed, hits) if listed else None,
                     "after": more})
    if "interventions" in report:
        sections.append(_interventions(report, hits))
    plots = _plots(analysis, report)
    if plots:
        sections.append({"id": "plots", "title": "Plots", "plots": plots, "paragraphs": [
            text("Drag across a plot to zoom in, double-click to zoom out; the legend shows the values under "
                 "the cursor.", "note")]})
    for n, table_data in enumerate(report.get("fleet", ())):
        sections.append(_fleet(table_data, n))
    if several_files(report):
        sections.append(_files(report))
    sections += _tables(report)
    start = analysis.first_ns or 0
    data = {"heading": "whiztap conformance report",
            "verdict": {"passed": report["passed"], "text": verdict_words(report)},
            "lines": lines, "sections": sections, "around": AROUND,
            "frames": _frames(views or {}, start)}
    return page("whiztap report", data)
